"""The writers of a run's outputs (the file names: :mod:`fgslam.run.files`; what each holds:
:mod:`fgslam.run.runner`): trajectories, PLY, keyframe depths, ``map.npz``, the plot and
``summary.json``. Each goes through an :class:`OutputWriter`, which writes it on its own: a file that
fails is removed rather than left truncated, its error is recorded, and it never costs the others.
The runner decides what is written; the writers only write."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ..eval.trajectory import EvalResult
from ..export.map import RunMap, save_run_map
from ..export.ply import PlyExportConfig, kept_points, write_ply
from ..frontends.base import Frontend
from ..io.datasets import Dataset
from ..io import plot  # called through the module: a test replaces plot.plot_trajectories
from ..io.run_files import SUMMARY_FILE, TUM_FILE
from ..io.trajectory import Trajectory, write_trajectory
from .config import SlamConfig
from .files import DEPTH_DIR, KITTI_FILE, KITTI_TIMES_FILE, MAP_FILE, PLOT_FILE, PLY_FILE
from .results import RunState, RunSummary

logger = logging.getLogger(__name__)


class OutputWriter:
    """Writes the outputs of one run into its folder ``out``, each on its own; ``written`` (kind ->
    path) and ``errors`` (kind -> why it could not be written) are what the summary reports."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.written: dict[str, str] = {}
        self.errors: dict[str, str] = {}

    def write(self, kind: str, paths: list[Path], write: Callable[[], object]) -> bool:
        """Run ``write`` (which writes ``paths``); on any failure remove what it left (never a truncated
        file), record the reason under ``kind`` and carry on. True when written."""
        try:
            write()
        except Exception as exc:  # noqa: BLE001 - one output's failure never costs the others
            for path in paths:
                try:
                    path.unlink(missing_ok=True)
                except OSError:
                    pass
            self.written.pop(kind, None)
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            self.errors[kind] = f"{paths[0].name}: {type(exc).__name__}: {why}"
            logger.error("could not write %s: %s: %s", paths[0], type(exc).__name__, why)
            return False
        self.written[kind] = str(paths[0])
        return True

    def record(self, kind: str, path: str) -> None:
        """Report ``path`` as the output ``kind`` (one written by another step, or a folder)."""
        self.written[kind] = path

    def fail(self, kind: str, why: str) -> None:
        """Report that the output ``kind`` could not be made, and why."""
        self.errors[kind] = why


def write_trajectories(writer: OutputWriter, traj: Trajectory) -> None:
    """``trajectory_tum.txt``, and ``trajectory_kitti.txt`` with its timestamps, each on its own."""
    out = writer.out
    writer.write("tum", [out / TUM_FILE], lambda: write_trajectory(out / TUM_FILE, traj, "tum"))
    kitti_paths = [out / KITTI_FILE, out / KITTI_TIMES_FILE]
    if writer.write("kitti", kitti_paths, lambda: write_trajectory(kitti_paths[0], traj, "kitti", kitti_paths[1])):
        writer.record("kitti_times", str(out / KITTI_TIMES_FILE))


def write_points(writer: OutputWriter, points: tuple[np.ndarray, np.ndarray], traj: Optional[Trajectory],
                 config: PlyExportConfig) -> None:
    """``points.ply``: binary little-endian PLY of the finite points ``(X_W (N, 3), colour (N, 3) uint8)``,
    without the far ones (``config.max_point_range_factor`` against the camera positions of ``traj``)."""
    path = writer.out / PLY_FILE

    def write() -> None:  # inside the writer: a failure is this output's, the others are still written
        X_W, colour = points
        keep, _ = kept_points(X_W, np.zeros((0, 3)) if traj is None else traj.T_WC[:, :3, 3], config)
        write_ply(path, X_W[keep], colour[keep])

    writer.write("ply", [path], write)


def write_keyframe_depths(writer: OutputWriter, frontend: Frontend, notes: list[str]) -> None:
    """``depth/<kf:06d>.png`` per keyframe of ``frontend.keyframe_depths()``, 16-bit millimetres (0: no
    depth; depths beyond 65.535 m clipped), written as one output (a frontend without depths: a note)."""
    try:
        depths = frontend.keyframe_depths()
    except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
        writer.fail("depth", f"keyframe_depths(): {type(exc).__name__}: {exc}")
        logger.error("could not get the keyframe depths: %s: %s", type(exc).__name__, exc)
        return
    if not depths:
        notes.append(f"output.write_depth: frontend '{frontend.name}' provides no keyframe depths; none written")
        return
    folder = writer.out / DEPTH_DIR
    paths = [folder / f"{kf:06d}.png" for kf in sorted(depths)]

    def write() -> None:
        import cv2  # deferred: cv2

        folder.mkdir(exist_ok=True)
        for path, kf in zip(paths, sorted(depths)):
            depth = np.nan_to_num(np.asarray(depths[kf][1], dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
            mm = np.clip(np.rint(depth * 1000.0), 0, np.iinfo(np.uint16).max).astype(np.uint16)
            if not cv2.imwrite(str(path), mm):
                raise OSError(f"cv2.imwrite failed for {path}")

    if writer.write("depth", paths, write):
        writer.record("depth", str(folder))


def write_map(writer: OutputWriter, dataset: Dataset, frontend: Frontend, sensor: str, state: RunState,
              notes: list[str]) -> None:
    """``map.npz`` for ``fgslam export``: the frontend's :meth:`~fgslam.frontends.base.Frontend.map_export`
    with the calibration of the images it saw and the run's frames (a frontend without a map: a note)."""
    path = writer.out / MAP_FILE
    try:
        exported = frontend.map_export()
    except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
        writer.fail("map", f"{path.name}: map_export() failed: {type(exc).__name__}: {exc}")
        logger.error("could not export the map: %s: %s", type(exc).__name__, exc)
        return
    if exported is None:
        notes.append(f"frontend '{frontend.name}' exports no map: no {path.name} written")
        return
    c = dataset.calibration
    indices = np.array(sorted(state.frame_paths), dtype=np.int64)
    run_map = RunMap(exported, np.asarray(c.K, dtype=np.float64), int(c.width), int(c.height),
                     dataset.timestamps[indices] if indices.size else np.zeros(0), indices,
                     [state.frame_paths[int(i)] for i in indices], sensor)
    writer.write("map", [path], lambda: save_run_map(path, run_map))


def write_plot(writer: OutputWriter, gt: Optional[Trajectory], traj: Trajectory, result: Optional[EvalResult],
               config: SlamConfig) -> None:
    """``trajectory.png``: top view of the (aligned) estimate against the ground truth."""
    path = writer.out / PLOT_FILE
    writer.write("plot", [path], lambda: _plot(path, gt, traj, result, config))


def write_summary(writer: OutputWriter, summary: RunSummary) -> bool:
    """``summary.json``, last: it lists itself among the outputs (and, when it cannot be written,
    among the errors instead: the caller's report still has it). True when written."""
    path = writer.out / SUMMARY_FILE
    writer.record("summary", str(path))
    if writer.write("summary", [path], lambda: _write_summary(path, summary)):
        return True
    logger.error("%s could not be written; the run summary is only on the console", path)
    return False


def _write_summary(path: Path, summary: RunSummary) -> None:
    """summary.json, written to a temporary file and renamed: never a truncated one."""
    text = json.dumps(summary.to_dict(), indent=2, default=_json_default) + "\n"
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _json_default(obj: object) -> object:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _plot(
    path: Path, gt: Optional[Trajectory], traj: Trajectory, result: Optional[EvalResult], config: SlamConfig
) -> Path:
    est = traj if result is None else result.aligned_est
    plane = config.output.plot_plane
    if plane == "auto":
        plane = auto_plane(gt if gt is not None else est)
    if result is not None:
        title = (f"{config.frontend} {config.sensor}: ATE {result.ate.rmse:.3f} m "
                 f"({result.align}, {result.n_matched} poses)")
    else:
        title = f"{config.frontend} {config.sensor}: estimate ({len(traj)} poses, no ground truth)"
    errors = None if result is None else {"estimate": plot.pose_errors(result.matched_gt, result.aligned_est)}
    return plot.plot_trajectories(path, gt, est, title=title, plane=plane, errors=errors)


def auto_plane(traj: Trajectory) -> str:
    """The plane of the two axes along which ``traj`` extends most (a top view for ground vehicles
    and hand-held sequences alike, whatever the world frame's up axis)."""
    extent = np.ptp(traj.t_WC, axis=0) if len(traj) else np.zeros(3)
    a, b = sorted(np.argsort(extent)[-2:])
    return "xyz"[a] + "xyz"[b]
