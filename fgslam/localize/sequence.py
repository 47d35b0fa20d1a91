"""``fgslam localize MAP --data SEQ --out DIR``: every frame of a new sequence localised in a stored
map (:class:`fgslam.localize.localizer.MapLocalizer`), a pose in the map's frame or "not localised".

Outputs (``DIR``): ``trajectory_tum.txt`` (localised frames only, map frame), ``localization.csv``
(every frame: raw (source) frame index, as ``--start`` counts, timestamp, status ``tracked`` / ``relocalised`` / ``not_localised``, keyframe id,
inliers, ``position_std``: :func:`~fgslam.localize.localizer.relative_position_std` of the pose, empty without one) and ``summary.json`` (counts, CPU time per frame, the map, and, when the sequence has ground
truth and the map its run's alignment to ground truth, the ATE of the localised poses with that
alignment applied unchanged, beside the ATE of holding the first localised pose: doing nothing).
A sequence where no frame localises writes the CSV and summary and raises :class:`NotLocalisedError`.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import resource
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..core.config import from_dict, to_dict
from ..core.errors import FGSlamError
from ..export.mapfile import check_map_camera, load_stored_map
from ..io.datasets import DatasetConfig, open_dataset
from ..io.run_files import LOCALIZATION_FILE, SUMMARY_FILE, TUM_FILE
from ..io.trajectory import Trajectory, write_trajectory
from .localizer import STATUSES, LocalizeConfig, Localizer

logger = logging.getLogger(__name__)

TRAJECTORY_FILE = TUM_FILE
STATUS_FILE = LOCALIZATION_FILE  # also in fgslam.run.files.RUN_OUTPUT_FILES (a previous run's outputs)


class NotLocalisedError(FGSlamError):
    """No frame of the sequence localised in the map (outputs written; no trajectory)."""


def _ate(positions: np.ndarray, gt: np.ndarray, A: np.ndarray) -> float:
    aligned = positions @ A[:3, :3].T + A[:3, 3]
    return float(np.sqrt(np.mean(np.sum((aligned - gt) ** 2, axis=1))))


def run_localization(map_path: str | Path, data: str | Path, out_dir: str | Path, config: LocalizeConfig | None = None,
                     fmt: str = "auto", start: int | None = None, end: int | None = None, stride: int | None = None,
                     prepare_out: Callable[[Path], object] | None = None) -> dict[str, Any]:
    """Localise the sequence ``data`` (raw frames ``start`` .. ``end``, every ``stride``-th; None: ``config.dataset``'s,
    else the whole sequence; the other dataset settings, e.g. the image size, are the map run's, with ``config.dataset`` merged
    over them) in the map at ``map_path``; writes
    the outputs (module docstring) to ``out_dir`` and returns the summary. ``prepare_out(out_dir)``
    is called once the map, the sequence and their cameras are checked, before anything is written
    (the CLI: ``fgslam run``'s rule for a previous run's outputs, :func:`fgslam.run.prepare.prepare_output`).
    Raises :class:`NotLocalisedError` (after writing) when no frame localised."""
    config = config or LocalizeConfig()
    config.validate()
    cpu0, wall0 = time.process_time(), time.perf_counter()
    stored = load_stored_map(map_path)
    ds_dict = dict((stored.meta.get("config") or {}).get("dataset") or {})
    ds_dict.update(load_rgb=False, load_depth=False, load_right=False, load_imu=False, start=0, end=None,
                   stride=1)
    ds_dict.update(config.dataset)  # the command's dataset section: e.g. a calibration or ground-truth file
    if start is not None:
        ds_dict["start"] = int(start)
    if end is not None:
        ds_dict["end"] = int(end)
    if stride is not None:
        ds_dict["stride"] = int(stride)
    dataset = open_dataset(data, fmt, from_dict(DatasetConfig, ds_dict, f"{map_path} (dataset settings)"))
    c = dataset.calibration
    check_map_camera(stored, c.K, c.width, c.height, map_path, data)
    out = Path(out_dir)
    if prepare_out is not None:
        prepare_out(out)
    out.mkdir(parents=True, exist_ok=True)
    localizer = Localizer(stored, config)  # the public API's (fgslam.Slam.localize_in): one path
    setup_cpu = time.process_time() - cpu0
    rows: list[tuple[int, float, str, int, int, float]] = []
    stamps, poses, gt_pos, has_gt = [], [], [], []
    loop_cpu0 = time.process_time()
    for frame in dataset:
        res = localizer.track(frame.image, frame.timestamp)
        rows.append((int(frame.source_index), float(frame.timestamp), res.status,
                     -1 if res.keyframe_id is None else res.keyframe_id, res.num_valid,
                     float("nan") if res.position_std is None else res.position_std))
        if res.T_WC is not None:
            stamps.append(frame.timestamp)
            poses.append(res.T_WC)
            has_gt.append(frame.T_WC_gt is not None)
            gt_pos.append(frame.T_WC_gt[:3, 3] if frame.T_WC_gt is not None else np.full(3, np.nan))
    loop_cpu = time.process_time() - loop_cpu0
    counts = {s: sum(1 for r in rows if r[2] == s) for s in STATUSES}
    n = len(rows)
    with open(out / STATUS_FILE, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(("frame", "timestamp", "status", "keyframe", "inliers", "position_std"))
        for r in rows:
            w.writerow((r[0], f"{r[1]:.17g}", r[2], r[3], r[4], "" if np.isnan(r[5]) else f"{r[5]:.6g}"))
    localised = n - counts["not_localised"]
    summary: dict[str, Any] = {
        "map": str(map_path), "data": str(data), "frames": n, "localised": localised,
        "not_localised": counts["not_localised"], "tracked": counts["tracked"], "relocalised": counts["relocalised"],
        "localised_fraction": localised / n if n else 0.0, "map_keyframes": stored.num_keyframes,
        "map_family": stored.meta.get("family"), "map_sensor": stored.meta.get("sensor"),
        "cpu_s": time.process_time() - cpu0, "setup_cpu_s": setup_cpu, "wall_s": time.perf_counter() - wall0,
        "cpu_ms_per_frame": 1000.0 * loop_cpu / n if n else None,
        "frames_per_cpu_s": n / loop_cpu if loop_cpu > 0 else None,
        "load_average": list(os.getloadavg()), "max_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "evaluation": None, "config": to_dict(config), "outputs": [STATUS_FILE, SUMMARY_FILE],
    }
    alignment = stored.meta.get("groundtruth_alignment")
    if poses and alignment and any(has_gt):
        sel = np.array(has_gt)
        A = np.asarray(alignment["matrix"], np.float64)
        P = np.stack([T[:3, 3] for T in poses])[sel]
        G = np.stack(gt_pos)[sel]
        summary["evaluation"] = {
            "align": f"the map run's own ({alignment['align']}), applied unchanged",
            "n_matched": int(sel.sum()),
            "ate_rmse_m": _ate(P, G, A),
            "stationary_ate_rmse_m": _ate(np.repeat(P[:1], len(P), axis=0), G, A),
        }
    if poses:
        write_trajectory(out / TRAJECTORY_FILE, Trajectory(np.array(stamps), np.stack(poses)), "tum")
        summary["outputs"].insert(0, TRAJECTORY_FILE)
    else:
        (out / TRAJECTORY_FILE).unlink(missing_ok=True)
    tmp = out / f".{SUMMARY_FILE}.tmp"
    tmp.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    os.replace(tmp, out / SUMMARY_FILE)
    if not poses:
        raise NotLocalisedError(f"{data}: none of the {n} frames localised in the map {map_path} "
                                f"(every frame 'not localised' in {out / STATUS_FILE}; no trajectory written)")
    return summary
