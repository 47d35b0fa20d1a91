"""``fgslam localize MAP --data SEQ --out DIR``: every frame of a new sequence localised in a stored
map (:class:`fgslam.localize.localizer.MapLocalizer`), a pose in the map's frame or "not localised".

With an odometry (``odometry.enabled``; :mod:`fgslam.localize.anchor`: the map run's own SLAM config on the
sequence, built by the caller), every frame it poses gets its anchored pose in the map's frame.

Outputs (``DIR``): ``trajectory_tum.txt`` (posed frames only, map frame), ``localization.csv``
(every frame: raw (source) frame index, as ``--start`` counts, timestamp, status ``tracked`` / ``relocalised`` /
``odometry`` (posed by the anchored odometry alone) / ``not_localised``, keyframe id,
inliers, ``position_std``: :func:`~fgslam.localize.localizer.relative_position_std` of the pose, empty without one) and ``summary.json`` (counts, CPU time per frame, the map, and, when the sequence has ground
truth and the map its run's alignment to ground truth, the ATE of the localised poses with that
alignment applied unchanged, beside the ATE of holding the first localised pose: doing nothing).
A sequence where no frame localises writes the CSV and summary and raises :class:`NotLocalisedError`.
A stop (Ctrl-C, a stop signal: ``KeyboardInterrupt``) or an error reading a frame ends the loop: the frames
before it are written (``summary.json`` ``stopped`` says why) and the exception is raised again.
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
from ..io.live import ReadAhead
from ..io.run_files import LOCALIZATION_FILE, SUMMARY_FILE, TUM_FILE
from ..io.trajectory import Trajectory, write_trajectory
from .anchor import Odometry, OdometryAnchor, OdometryFactory
from .localizer import SEQUENCE_STATUSES, LocalizeConfig, Localizer

logger = logging.getLogger(__name__)

TRAJECTORY_FILE = TUM_FILE
STATUS_FILE = LOCALIZATION_FILE  # also in fgslam.run.files.RUN_OUTPUT_FILES (a previous run's outputs)


class NotLocalisedError(FGSlamError):
    """No frame of the sequence localised in the map (outputs written; no trajectory)."""


def _ate(positions: np.ndarray, gt: np.ndarray, A: np.ndarray) -> float:
    aligned = positions @ A[:3, :3].T + A[:3, 3]
    return float(np.sqrt(np.mean(np.sum((aligned - gt) ** 2, axis=1))))


class _OdometryRun:
    """The sequence's odometry while the localisation runs. Any error building or running it is logged with
    its traceback and the localisation goes on without it (the poses it gave stay); ``note`` says why it is
    off or when it stopped (None: it ran to the end)."""

    def __init__(self, factory: OdometryFactory | None, map_config: dict, enabled: bool):
        self.factory = factory if enabled and factory is not None and map_config else None
        self.map_config = map_config
        self.odo: Odometry | None = None
        self.ran = False
        self.note: str | None = None
        if factory is None:
            self.note = "off: none given"
        elif not enabled:
            self.note = "off (odometry.enabled is false)"
        elif not map_config:
            self.note = "off: the map keeps no run config"

    def streams(self) -> dict[str, bool] | None:
        """The dataset streams it reads; None: no odometry (``note`` says why)."""
        if self.factory is None:
            return None
        try:
            return dict(self.factory.dataset_streams(self.map_config))
        except Exception as exc:  # noqa: BLE001 - an old or foreign map's config: localise without the odometry
            self._off(f"off: the map run's config does not build one here ({exc})", exc)
            return None

    def start(self, calibration) -> None:
        if self.factory is None:
            return
        try:
            self.odo = self.factory(self.map_config, calibration)
            self.ran = True
        except Exception as exc:  # noqa: BLE001 - as in streams()
            self._off(f"off: it failed to start ({type(exc).__name__}: {exc})", exc)

    def pose(self, frame) -> np.ndarray | None:
        """The odometry's pose ``T_VC`` of ``frame`` (None: none, or no odometry)."""
        if self.odo is None:
            return None
        try:
            return self.odo.track(frame)
        except Exception as exc:  # noqa: BLE001 - a failing odometry must not end the localisation
            self._off(f"stopped at frame {frame.source_index} ({type(exc).__name__}: {exc})", exc)
            self.close()
            return None

    def close(self) -> None:
        odo, self.odo = self.odo, None
        if odo is not None:
            try:
                odo.close()
            except Exception:  # noqa: BLE001 - logged; its poses are already used
                logger.exception("stopping the odometry failed")

    def _off(self, note: str, exc: Exception) -> None:
        self.factory = None
        self.note = note
        logger.warning("localisation: odometry %s; the localiser's poses alone from here on", note,
                       exc_info=not isinstance(exc, FGSlamError))  # an unexpected error's traceback: in the log


def run_localization(map_path: str | Path, data: str | Path, out_dir: str | Path, config: LocalizeConfig | None = None,
                     fmt: str = "auto", start: int | None = None, end: int | None = None, stride: int | None = None,
                     prepare_out: Callable[[Path], object] | None = None,
                     odometry: OdometryFactory | None = None) -> dict[str, Any]:
    """Localise the sequence ``data`` (raw frames ``start`` .. ``end``, every ``stride``-th; None: ``config.dataset``'s,
    else the whole sequence; the other dataset settings, e.g. the image size, are the map run's, with ``config.dataset`` merged
    over them) in the map at ``map_path``; writes
    the outputs (module docstring) to ``out_dir`` and returns the summary. ``prepare_out(out_dir)``
    is called once the map, the sequence and their cameras are checked, before anything is written
    (the CLI: ``fgslam run``'s rule for a previous run's outputs, :func:`fgslam.run.prepare.prepare_output`).
    ``odometry`` builds the sequence's odometry from the map run's config (a dict) and the sequence's
    calibration (:class:`~fgslam.localize.anchor.OdometryFactory`); used when ``config.odometry.enabled``
    (None: no odometry).
    Raises :class:`NotLocalisedError` (after writing) when no frame localised."""
    config = config or LocalizeConfig()
    config.validate()
    cpu0, wall0 = time.process_time(), time.perf_counter()
    stored = load_stored_map(map_path)
    map_config = dict(stored.meta.get("config") or {})
    odometry_run = _OdometryRun(odometry, map_config, config.odometry.enabled)
    ds_dict = dict(map_config.get("dataset") or {})
    # the localiser reads the grey image alone; the odometry the streams its sensor needs
    ds_dict.update(odometry_run.streams() or dict(load_rgb=False, load_depth=False, load_right=False, load_imu=False))
    ds_dict.update(start=0, end=None, stride=1)
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
    odometry_run.start(dataset.calibration)
    anchor = OdometryAnchor(config.odometry, with_scale=stored.meta.get("sensor") == "mono")
    setup_cpu = time.process_time() - cpu0
    rows: list[tuple[int, float, str, int, int, float]] = []
    stamps, poses, gt_pos, has_gt = [], [], [], []
    loop_cpu0 = time.process_time()
    stopped: BaseException | None = None  # a stop (Ctrl-C, a stop signal) or a damaged frame: the frames before it are written
    reader = ReadAhead(dataset)  # the next frame decodes while this one is localised
    try:
        for frame in reader:
            res = localizer.track(frame.image, frame.timestamp)
            T_VC = odometry_run.pose(frame)
            T_WC = anchor.add(frame.timestamp, T_VC, res.T_WC)
            status = res.status if res.T_WC is not None or T_WC is None else "odometry"
            rows.append((int(frame.source_index), float(frame.timestamp), status,
                         -1 if res.keyframe_id is None else res.keyframe_id, res.num_valid,
                         float("nan") if res.position_std is None else res.position_std))
            if T_WC is not None:
                stamps.append(frame.timestamp)
                poses.append(T_WC)
                has_gt.append(frame.T_WC_gt is not None)
                gt_pos.append(frame.T_WC_gt[:3, 3] if frame.T_WC_gt is not None else np.full(3, np.nan))
    except (KeyboardInterrupt, FGSlamError) as exc:
        stopped = exc
        logger.warning("localisation stopped after %d frames (%s): writing their outputs", len(rows),
                       str(exc) or type(exc).__name__)
    finally:
        try:
            reader.close()
        except KeyboardInterrupt as exc:  # a stop signal while the reader ends: the frames before it are written
            stopped = stopped or exc
        odometry_run.close()
    loop_cpu = time.process_time() - loop_cpu0
    counts = {s: sum(1 for r in rows if r[2] == s) for s in SEQUENCE_STATUSES}
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
        "odometry": counts["odometry"], "odometry_run": {"ran": odometry_run.ran, "note": odometry_run.note},
        "anchor_pairs": anchor.pairs,
        "localised_fraction": localised / n if n else 0.0, "map_keyframes": stored.num_keyframes,
        "map_family": stored.meta.get("family"), "map_sensor": stored.meta.get("sensor"),
        "cpu_s": time.process_time() - cpu0, "setup_cpu_s": setup_cpu, "wall_s": time.perf_counter() - wall0,
        "cpu_ms_per_frame": 1000.0 * loop_cpu / n if n else None,
        "frames_per_cpu_s": n / loop_cpu if loop_cpu > 0 else None,
        "load_average": list(os.getloadavg()), "max_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "evaluation": None, "config": to_dict(config), "outputs": [STATUS_FILE, SUMMARY_FILE],
        "stopped": None if stopped is None else (str(stopped) or type(stopped).__name__),
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
    if stopped is not None:
        raise stopped
    if not poses:
        raise NotLocalisedError(f"{data}: none of the {n} frames localised in the map {map_path} "
                                f"(every frame 'not localised' in {out / STATUS_FILE}; no trajectory written)")
    return summary
