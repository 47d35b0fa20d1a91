"""``fgslam compare-colmap --data PATH``: fgslam against pycolmap's structure from motion on the same
frames (:func:`compare_colmap`; the data side in :mod:`fgslam.export.compare`): time of each and the ratio, registered frames, ATE of
each against the ground truth (Sim(3)), point-cloud accuracy and completion against each other;
``compare.json`` and ``compare.png`` in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import numpy as np

from ..core.errors import ConfigError, DataError, EvaluationError
from ..eval.trajectory import EvalResult, evaluate
from ..core.geometry import Alignment, umeyama
from ..io.datasets import DatasetConfig, open_dataset
from ..io import plot  # called through the module (replaceable in tests, as the run's plot)
from ..io.run_files import TUM_FILE
from ..io.trajectory import Trajectory, read_trajectory

if TYPE_CHECKING:  # the run package and the exports pull torch: imported in run() only (fgslam --help stays fast)
    from ..export.compare import CompareConfig
    from ..run.prepare import PreparedRun

logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, metavar="PATH", help="dataset folder")
    parser.add_argument("--frames", type=int, default=None, metavar="N", help="the first N frames (default: all)")
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="output folder (default: compare-colmap-<sequence name>); refused when it exists "
                             "and is not empty, unless --overwrite")
    parser.add_argument("--overwrite", action="store_true", help="write into an existing output folder")
    parser.add_argument("--format", default="auto", help="dataset loader (default: detect)")
    parser.add_argument("--preset", default=None, metavar="CONFIG",
                        help="fgslam config or preset (default: the format's monocular preset, e.g. patch_kitti_mono)")
    parser.add_argument("-o", "--override", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a field of the fgslam run config (repeatable)")
    parser.add_argument("--features", type=int, default=None, metavar="N", help="COLMAP SIFT features per image (default 8192)")
    parser.add_argument("--no-progress", action="store_true", help="no progress lines")
    parser.add_argument("--json", action="store_true", help="print the report as one JSON object")


def run(args: argparse.Namespace) -> int:
    from ..export.compare import CompareConfig, preset_for  # deferred: torch (fgslam --help stays fast)
    from ..run.config import load_slam_config  # deferred: the run package pulls torch
    from ..run.prepare import new_folder, prepare_output_dir, prepare_run, remove_created_folder  # deferred: as above

    if args.frames is not None and args.frames < 3:
        raise ConfigError(f"--frames must be at least 3 (got {args.frames})")
    if args.features is not None and args.features < 16:
        raise ConfigError(f"--features must be at least 16 (got {args.features})")
    probe = open_dataset(args.data, args.format, DatasetConfig(load_right=False, load_depth=False, load_imu=False))
    preset = args.preset or preset_for(probe.format, probe.root)
    overrides = ["sensor=mono", *args.overrides]
    if args.frames is not None:
        overrides.append(f"dataset.end={probe.config.start + args.frames * probe.config.stride}")
    config = load_slam_config(preset, overrides)
    out = Path(args.out or f"compare-colmap-{probe.name}")
    if out.is_dir() and any(out.iterdir()) and not args.overwrite:
        raise ConfigError(f"{out}: output folder exists and is not empty (use --overwrite or another --out)")
    created = new_folder(out)
    try:
        prepare_output_dir(out, args.data)
        # the compare folder is the command's (refused when not empty unless --overwrite): a previous run in it is replaced
        prepared = prepare_run(args.data, config, out / "fgslam", fmt=args.format, overwrite=True)
    except BaseException:  # refused: no output folder left behind (only an empty one created here)
        remove_created_folder(created)
        raise
    cfg = CompareConfig()
    if args.features is not None:
        cfg = replace(cfg, colmap=replace(cfg.colmap, max_num_features=args.features))
    report = compare_colmap(prepared, out, cfg, progress=not args.no_progress, preset=preset)
    if args.json:
        print(json.dumps(report, default=float))
    else:
        print(format_report(report))
    if report["colmap"].get("error"):  # no comparison: the report says so, and the command fails
        raise DataError(f"{report['colmap']['error']} ({report['colmap']['models']} models; see {out / 'colmap'}): "
                        f"no comparison, report in {report['outputs']['json']}")
    return 0


def format_report(r: dict) -> str:
    fg, cm = r["fgslam"], r["colmap"]
    fmt = lambda v: "-" if v is None else f"{v:.4f} m"  # noqa: E731
    lines = [
        f"{r['dataset']['path']} ({r['dataset']['format']}, {r['dataset']['frames']} frames, load {r['load_average_start']})",
        f"  fgslam ({fg['preset']}): {fg['wall_s']:.1f} s wall ({fg['cpu_s']:.1f} s CPU), {fg['registered_frames']} frames posed, "
        f"{fg['points']} points, ATE {fmt(fg.get('ate_m'))} (on COLMAP's frames {fmt(fg.get('ate_on_colmap_frames_m'))})",
        f"  COLMAP: {cm['wall_s']:.1f} s wall ({cm['cpu_s']:.1f} s CPU), {cm['registered_frames']} frames registered "
        f"({cm['models']} models), {cm['points']} points, ATE {fmt(cm.get('ate_m'))}",
    ]
    if cm.get("error"):
        lines.append(f"  ratio:  none ({cm['error']})")
    else:
        lines.append(f"  ratio:  COLMAP / fgslam time {r['speed_ratio_wall']:.1f}x wall, {r['speed_ratio_cpu']:.1f}x CPU"
                     + (f"; ATE fgslam / COLMAP {r['ate_ratio']:.2f}" if r.get("ate_ratio") is not None else ""))
    if r.get("clouds"):
        d = r["clouds"]["fgslam_against_colmap"]
        lines.append(f"  clouds: fgslam against COLMAP: accuracy {d['accuracy_mean']:.4f} (median {d['accuracy_median']:.4f}), "
                     f"completion {d['completion_mean']:.4f} (median {d['completion_median']:.4f}) in the {r['clouds']['frame']} frame")
    lines.append(f"  outputs: {', '.join(r['outputs'].values())}")
    return "\n".join(lines)


def compare_colmap(run: PreparedRun, out: Path, config: CompareConfig | None = None,
                   progress: bool = True, preset: str = "") -> dict[str, Any]:
    """Run fgslam (the prepared monocular ``run``, into ``out/fgslam``) and COLMAP on its dataset,
    write ``compare.json`` and ``compare.png`` into ``out`` and return the report (see the module
    docstring)."""
    from ..export.colmap import run_colmap_sfm  # deferred: torch (fgslam --help stays fast)
    from ..export.compare import COMPARE_JSON, COMPARE_PNG, CompareConfig, compare_clouds, write_frames  # deferred: torch
    from ..export.map import load_run_map  # deferred: torch
    from ..run.files import MAP_FILE  # deferred: the run package pulls torch
    from ..run.runner import run_prepared  # deferred: as above

    dataset, slam_config = run.dataset, run.config
    config = config or CompareConfig()
    load = [round(v, 2) for v in os.getloadavg()]
    image_dir = out / "images"
    t0 = time.perf_counter()
    names = write_frames(dataset, image_dir)
    write_s = time.perf_counter() - t0

    summary = run_prepared(run, progress=progress)
    sfm = run_colmap_sfm(image_dir, out / "colmap", dataset.calibration.K, config.colmap, sorted(names))

    gt = dataset.groundtruth
    eval_cfg = replace(slam_config.eval, align="sim3")
    report: dict[str, Any] = {
        "dataset": {"path": str(dataset.root), "format": dataset.format, "frames": len(dataset),
                    "resolution": [dataset.calibration.width, dataset.calibration.height],
                    "groundtruth": gt is not None},
        "load_average_start": load,
        "frame_writing_s": write_s,
        "fgslam": {"frontend": slam_config.frontend, "preset": preset, "wall_s": summary.wall_s, "cpu_s": summary.cpu_s,
                   "registered_frames": summary.frames_with_pose, "keyframes": summary.keyframes},
        "colmap": {"wall_s": sfm.seconds["total"], "cpu_s": sfm.cpu_seconds, "stages_s": sfm.seconds,
                   "models": sfm.models, "registered_frames": 0 if sfm.model is None else len(sfm.model.names),
                   "points": 0 if sfm.model is None else int(sfm.model.X_W.shape[0]),
                   "settings": asdict(config.colmap)},
    }
    if report["colmap"]["registered_frames"] == 0:  # nothing to compare against: no ratio of times
        report["colmap"]["error"] = f"COLMAP registered no frame of {len(names)}"
        report["speed_ratio_wall"] = report["speed_ratio_cpu"] = None
    else:
        report["speed_ratio_wall"] = report["colmap"]["wall_s"] / max(summary.wall_s, 1e-9)
        report["speed_ratio_cpu"] = report["colmap"]["cpu_s"] / max(summary.cpu_s, 1e-9)

    fg_traj = read_trajectory(out / "fgslam" / TUM_FILE, "tum") if (out / "fgslam" / TUM_FILE).is_file() else None
    cm_traj = None if sfm.model is None else sfm.model.trajectory(names)
    fg_points = load_run_map(out / "fgslam" / MAP_FILE).map.X_W if (out / "fgslam" / MAP_FILE).is_file() else np.zeros((0, 3))
    cm_points = np.zeros((0, 3)) if sfm.model is None else sfm.model.X_W
    report["fgslam"]["points"] = int(fg_points.shape[0])

    results = {}
    for name, traj in (("fgslam", fg_traj), ("colmap", cm_traj)):
        if gt is None or traj is None or len(traj) < 3:
            report[name]["ate_m"] = None
            continue
        try:
            results[name] = evaluate(gt, traj, eval_cfg)
        except EvaluationError as exc:
            report[name]["ate_m"] = None
            report[name]["evaluation_error"] = str(exc)
            continue
        report[name]["ate_m"] = results[name].ate.rmse
        report[name]["ate_percent_of_path"] = 100 * results[name].ate.rmse / max(results[name].gt_path_length_m, 1e-12)
    if gt is not None and fg_traj is not None and cm_traj is not None and len(cm_traj) >= 3:
        common = np.isin(np.round(fg_traj.timestamps, 6), np.round(cm_traj.timestamps, 6))
        if common.sum() >= 3:
            sub = Trajectory(fg_traj.timestamps[common], fg_traj.T_WC[common])
            try:
                report["fgslam"]["ate_on_colmap_frames_m"] = evaluate(gt, sub, eval_cfg).ate.rmse
            except EvaluationError as exc:
                report["fgslam"]["ate_on_colmap_frames_m"] = None
                logger.warning("fgslam ATE on COLMAP's frames: %s", exc)
    if report["fgslam"].get("ate_m") is not None and report["colmap"].get("ate_m") is not None:
        report["ate_ratio"] = report["fgslam"]["ate_m"] / max(report["colmap"]["ate_m"], 1e-12)

    # point clouds in one frame: the ground truth's (each aligned by its own trajectory), else COLMAP's
    report["clouds"] = None
    if "fgslam" in results and "colmap" in results:
        a_fg, a_cm = results["fgslam"].alignment, results["colmap"].alignment
        report["clouds"] = compare_clouds(
            _apply(a_fg, fg_points), _apply(a_cm, cm_points), _apply(a_fg, fg_traj.t_WC), _apply(a_cm, cm_traj.t_WC),
            config, "ground truth (each run aligned by its own Sim(3) trajectory alignment)")
    elif fg_traj is not None and cm_traj is not None:
        t_fg, t_cm = np.round(fg_traj.timestamps, 6), np.round(cm_traj.timestamps, 6)
        both, i_fg, i_cm = np.intersect1d(t_fg, t_cm, return_indices=True)
        if both.size >= 3:
            try:
                a = umeyama(fg_traj.t_WC[i_fg], cm_traj.t_WC[i_cm], with_scale=True)
                report["clouds"] = compare_clouds(
                    _apply(a, fg_points), cm_points, _apply(a, fg_traj.t_WC), cm_traj.t_WC, config, "COLMAP's (fgslam aligned by Sim(3) on the frames both registered)")
            except EvaluationError as exc:
                logger.warning("cannot align the clouds: %s", exc)

    report["outputs"] = {"json": str(out / COMPARE_JSON)}
    try:
        _plot(out / COMPARE_PNG, gt, results, fg_traj, cm_traj, report)
        report["outputs"]["png"] = str(out / COMPARE_PNG)
    except DataError as exc:
        report["plot_error"] = str(exc)
    (out / COMPARE_JSON).write_text(json.dumps(report, indent=2, default=float) + "\n")
    return report


def _plot(path: Path, gt: Optional[Trajectory], results: dict[str, EvalResult], fg_traj: Optional[Trajectory],
          cm_traj: Optional[Trajectory], report: dict[str, Any]) -> None:
    from ..run.outputs import auto_plane  # deferred: the run package pulls torch

    trajs = {}
    for key, label, traj in (("fgslam", "fgslam", fg_traj), ("colmap", "COLMAP", cm_traj)):
        if traj is not None:
            trajs[label] = results[key].aligned_est if key in results else traj
    if not trajs:
        return
    first, *rest = trajs.items()
    errors = {("fgslam" if k == "fgslam" else "COLMAP"): plot.pose_errors(r.matched_gt, r.aligned_est) for k, r in results.items()}
    fg, cm = report["fgslam"], report["colmap"]
    fmt = lambda v: "-" if v is None else f"{v:.3f} m"  # noqa: E731
    title = (f"fgslam {fmt(fg.get('ate_m'))} in {fg['wall_s']:.0f} s; COLMAP {fmt(cm.get('ate_m'))} in "
             f"{cm['wall_s']:.0f} s ({cm['registered_frames']} frames)")
    plane = auto_plane(gt if gt is not None else first[1])
    plot.plot_trajectories(path, gt, first[1], title=title, plane=plane, others=dict(rest), errors=errors or None,
                           label=first[0])


def _apply(alignment: Alignment, X: np.ndarray) -> np.ndarray:
    return alignment.s * X @ alignment.R.T + alignment.t
