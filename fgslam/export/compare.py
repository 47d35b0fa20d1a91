"""fgslam against COLMAP's structure from motion on the same frames (``fgslam compare-colmap``).

Both run monocular on the same undistorted frames with the same pinhole calibration (COLMAP's kept
fixed): fgslam through :func:`fgslam.slam.run_slam`, COLMAP through
:func:`fgslam.export.colmap.run_colmap_sfm` (SIFT on the CPU, sequential matching, incremental
mapping) on the frames written as PNG files (writing them is timed for neither).

Reported: wall and CPU time of each and their ratio, frames each registered, the ATE of each
against the ground truth (Sim(3) alignment: monocular scale), fgslam's ATE over only the frames
COLMAP registered, and the point clouds' accuracy and completion against each other (MASt3R-SLAM
table 3: accuracy = mean distance from each point of a cloud to the nearest point of the
reference, completion = mean distance from each reference point to the nearest point of the
cloud; here fgslam's cloud against COLMAP's, in the ground truth's metres after each run's own
trajectory alignment, or in COLMAP's frame after aligning fgslam's trajectory to COLMAP's when the
sequence has no ground truth).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..config import MAX_COUNT, MAX_SCALAR, ranged
from ..errors import DataError, EvaluationError
from .colmap import ColmapSfmConfig, run_colmap_sfm

logger = logging.getLogger(__name__)

COMPARE_JSON = "compare.json"
COMPARE_PNG = "compare.png"
IMAGE_NAME = "{index:06d}.png"  # frame images written for COLMAP (dataset index)


@dataclass
class CompareConfig:
    """``fgslam compare-colmap`` settings (the fgslam run's own config is its preset)."""

    colmap: ColmapSfmConfig = field(default_factory=ColmapSfmConfig)
    max_cloud_points: int = ranged(200000, ge=100, le=MAX_COUNT)  # clouds are subsampled (evenly) to this many points for the distances
    max_point_range_factor: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # cloud metrics leave out points farther from every camera of their run than this x the cloud's median such distance


PRESET_BY_FORMAT = {"kitti": "patch_kitti_mono", "7scenes": "patch_7scenes_mono", "euroc": "patch_euroc_mono"}
DEFAULT_PRESET = "patch_mono"


SYNTH_MARKER = "synth_config.yaml"  # written by `fgslam synth` beside the EuRoC layout


def preset_for(fmt: str, root: str | Path | None = None) -> str:
    """The monocular preset for a dataset format (KITTI, 7-Scenes, EuRoC; else ``patch_mono``);
    ``fgslam synth`` renders (EuRoC layout with ``synth_config.yaml``) get ``patch_mono``."""
    if root is not None and (Path(root) / SYNTH_MARKER).is_file():
        return DEFAULT_PRESET
    return PRESET_BY_FORMAT.get(fmt, DEFAULT_PRESET)


def cloud_distances(cloud: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """Accuracy (cloud -> reference) and completion (reference -> cloud): mean and median nearest
    neighbour distances."""
    from scipy.spatial import cKDTree

    if cloud.shape[0] == 0 or reference.shape[0] == 0:
        return {"accuracy_mean": float("nan"), "accuracy_median": float("nan"),
                "completion_mean": float("nan"), "completion_median": float("nan")}
    acc = cKDTree(reference).query(cloud)[0]
    comp = cKDTree(cloud).query(reference)[0]
    return {"accuracy_mean": float(acc.mean()), "accuracy_median": float(np.median(acc)),
            "completion_mean": float(comp.mean()), "completion_median": float(np.median(comp)),
            "chamfer_mean": float(0.5 * (acc.mean() + comp.mean()))}


def _subsample(X: np.ndarray, n: int) -> np.ndarray:
    X = X[np.all(np.isfinite(X), axis=1)]
    if X.shape[0] <= n:
        return X
    return X[np.linspace(0, X.shape[0] - 1, n).astype(np.int64)]


def compare_clouds(fg_cloud: np.ndarray, cm_cloud: np.ndarray, fg_centres: np.ndarray, cm_centres: np.ndarray,
                   config: "CompareConfig", frame: str) -> dict[str, Any]:
    """Accuracy and completion of fgslam's cloud against COLMAP's, both in one frame, each cloud
    without its points farther from every camera of its own run than ``max_point_range_factor``
    times the median such distance of the cloud (far points: near-zero inverse depths, sky),
    counted in the report."""
    from scipy.spatial import cKDTree

    kept, limits = {}, {}
    for name, cloud, centres in (("fgslam", fg_cloud, fg_centres), ("colmap", cm_cloud, cm_centres)):
        cloud = cloud[np.all(np.isfinite(cloud), axis=1)]
        if len(cloud) and len(centres):
            dist = cKDTree(centres).query(cloud)[0]
            limits[name] = float(config.max_point_range_factor * np.median(dist))
            near = dist <= limits[name]
        else:
            near = np.zeros(len(cloud), bool)
        kept[name] = (cloud[near], int((~near).sum()))
    d = cloud_distances(_subsample(kept["fgslam"][0], config.max_cloud_points),
                        _subsample(kept["colmap"][0], config.max_cloud_points))
    return {"frame": frame, "fgslam_against_colmap": d, "range_limits": limits,
            "far_points_left_out": {"fgslam": kept["fgslam"][1], "colmap": kept["colmap"][1]},
            "note": "accuracy: fgslam points to the nearest COLMAP point; completion: COLMAP points to the nearest "
                    "fgslam point (COLMAP against fgslam swaps the two)"}


def _apply(alignment, X: np.ndarray) -> np.ndarray:
    return alignment.s * X @ alignment.R.T + alignment.t


def write_frames(dataset, image_dir: Path) -> dict[str, float]:
    """Write the dataset's (undistorted) grey frames as PNG files; returns name -> timestamp."""
    import cv2

    image_dir.mkdir(parents=True, exist_ok=True)
    names: dict[str, float] = {}
    for frame in dataset:
        name = IMAGE_NAME.format(index=frame.index)
        if not cv2.imwrite(str(image_dir / name), frame.image):
            raise DataError(f"{image_dir / name}: cannot write the frame image")
        names[name] = float(frame.timestamp)
    return names


def compare_colmap(dataset, slam_config, out: Path, config: CompareConfig | None = None,
                   progress: bool = True, preset: str = "") -> dict[str, Any]:
    """Run fgslam and COLMAP on ``dataset`` (monocular), write ``compare.json`` and ``compare.png``
    into ``out`` and return the report (see the module docstring)."""
    import os

    from ..eval import EvalConfig, evaluate, umeyama
    from ..export.map import load_run_map
    from ..io.trajectory import read_trajectory
    from ..slam import MAP_FILE, TUM_FILE, run_slam

    config = config or CompareConfig()
    load = [round(v, 2) for v in os.getloadavg()]
    image_dir = out / "images"
    t0 = time.perf_counter()
    names = write_frames(dataset, image_dir)
    write_s = time.perf_counter() - t0

    # the compare folder is the command's (refused when not empty unless --overwrite): replace a previous run in it
    summary = run_slam(dataset, slam_config, out / "fgslam", progress=progress, overwrite=True)
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
            from ..io.trajectory import Trajectory

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


def _plot(path: Path, gt, results: dict, fg_traj, cm_traj, report: dict) -> None:
    from ..io.plot import plot_trajectories, pose_errors
    from ..slam import _auto_plane

    trajs = {}
    for key, label, traj in (("fgslam", "fgslam", fg_traj), ("colmap", "COLMAP", cm_traj)):
        if traj is not None:
            trajs[label] = results[key].aligned_est if key in results else traj
    if not trajs:
        return
    first, *rest = trajs.items()
    errors = {("fgslam" if k == "fgslam" else "COLMAP"): pose_errors(r.matched_gt, r.aligned_est) for k, r in results.items()}
    fg, cm = report["fgslam"], report["colmap"]
    fmt = lambda v: "-" if v is None else f"{v:.3f} m"  # noqa: E731
    title = (f"fgslam {fmt(fg.get('ate_m'))} in {fg['wall_s']:.0f} s; COLMAP {fmt(cm.get('ate_m'))} in "
             f"{cm['wall_s']:.0f} s ({cm['registered_frames']} frames)")
    plane = _auto_plane(gt if gt is not None else first[1])
    plot_trajectories(path, gt, first[1], title=title, plane=plane, others=dict(rest), errors=errors or None,
                      label=first[0])
