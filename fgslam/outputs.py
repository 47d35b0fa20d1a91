"""A run's outputs (see :mod:`fgslam.slam` for what each file holds): the output folder's checks,
the per-run record the loop fills (:class:`RunState`), and :func:`finalize_run`, which writes the
trajectories, plot, PLY, keyframe depths, map and ``summary.json``, each on its own, so that one
failing output never loses the others."""

from __future__ import annotations

import json
import logging
import os
import resource
import shutil
import signal
import tempfile
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Optional

import numpy as np

from .config import to_dict
from .errors import ConfigError, DataError, EvaluationError
from .eval import EvalResult, evaluate
from .frontends.base import Frontend
from .io.datasets import Dataset
from .io.run_files import LOCALIZATION_FILE, SUMMARY_FILE, TUM_FILE
from .io.trajectory import Trajectory, write_trajectory
from .runconfig import SlamConfig
from .system import SlamSystem

logger = logging.getLogger(__name__)

# Output file names (stable: tools and tests read them; those several layers use: fgslam.io.run_files).
KITTI_FILE = "trajectory_kitti.txt"


KITTI_TIMES_FILE = "trajectory_kitti_times.txt"


PLOT_FILE = "trajectory.png"


PLY_FILE = "points.ply"


MAP_FILE = "map.npz"  # fgslam.export.map.MAP_FILE
MERGED_TUM_FILE = "merged_trajectory_tum.txt"  # fgslam run --map: frames from the merge on, in the stored map's frame
MERGE_FILE = "merge.json"  # fgslam run --map: the merge (transform, keyframes) or why none


DEPTH_DIR = "depth"  # depth/<kf:06d>.png per keyframe (output.write_depth)


#: What a run writes into its output folder (a previous run's outputs: refused, or removed with overwrite).
RUN_OUTPUT_FILES = (TUM_FILE, KITTI_FILE, KITTI_TIMES_FILE, SUMMARY_FILE, SUMMARY_FILE + ".tmp", PLOT_FILE, PLY_FILE,
                    MAP_FILE, MERGED_TUM_FILE, MERGE_FILE, LOCALIZATION_FILE)


#: Images with a side above this many pixels are named as the likely reason when no frame got a
#: pose (the frontends are tuned for VGA to KITTI-width images; resize with dataset.resize_width).
LARGE_IMAGE_SIDE = 4096


SUGGESTED_RESIZE_WIDTH = 640  # the dataset.resize_width that hint suggests (VGA width)


BYTES_PER_KIB = 1024  # ru_maxrss is in KiB on Linux


BYTES_PER_MIB = 1024 * 1024


def prepare_output_dir(out_dir: str | Path, data: str | Path | None = None) -> Path:
    """Create the output folder and check that it is writable, before any work.

    Raises ConfigError when it is the dataset folder ``data`` or inside it (outputs would mix with
    the input data), DataError when it cannot be created or written (a file in the way, no
    permission, a read-only or full file system)."""
    out = Path(out_dir)
    if data is not None:
        out_abs, data_abs = out.resolve(), Path(data).resolve()
        if out_abs == data_abs or data_abs in out_abs.parents:
            where = "is the dataset folder" if out_abs == data_abs else f"is inside the dataset folder {data}"
            raise ConfigError(f"output folder {out} {where}: outputs would mix with the input data; "
                              "choose a folder outside it")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"{out}: cannot create the output folder: {exc.strerror or exc}") from exc
    try:
        fd, probe = tempfile.mkstemp(prefix=".fgslam-write-test-", dir=out)
        try:
            os.write(fd, b"fgslam")
            os.fsync(fd)
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        raise DataError(f"{out}: the output folder is not writable: {exc.strerror or exc}") from exc
    return out


def check_save_map_path(save_map: str | Path, out_dir: str | Path, extend_map: str | Path | None,
                        overwrite: bool) -> None:
    """``--save-map``: ConfigError when the path is one of the run's own output files in ``out_dir``
    (:data:`RUN_OUTPUT_FILES`, ``depth/``), or an existing file that is not the ``--map`` being
    extended and ``overwrite`` is not given (a map is never replaced silently)."""
    path = Path(save_map).resolve()
    out = Path(out_dir).resolve()
    if path.parent == out and path.name in RUN_OUTPUT_FILES or out / DEPTH_DIR in (path, *path.parents):
        raise ConfigError(f"--save-map {save_map}: that is one of the run's own output files in {out_dir}; "
                          "choose another name")
    if path.is_dir():
        raise ConfigError(f"--save-map {save_map}: is a folder")
    if path.exists() and not overwrite and (extend_map is None or Path(extend_map).resolve() != path):
        raise ConfigError(f"--save-map {save_map}: the file exists; use --overwrite to replace it "
                          "(or save the extended map over its --map)")


def previous_run_outputs(out_dir: str | Path) -> list[Path]:
    """The outputs of a previous run in ``out_dir`` (:data:`RUN_OUTPUT_FILES` and ``depth/``)."""
    out = Path(out_dir)
    found = [out / name for name in RUN_OUTPUT_FILES if (out / name).is_file()]
    return found + ([out / DEPTH_DIR] if (out / DEPTH_DIR).is_dir() else [])


def clear_previous_outputs(out_dir: str | Path, overwrite: bool, remove: bool = True) -> None:
    """Refuse an output folder that holds a previous run's outputs (:func:`previous_run_outputs`)
    unless ``overwrite``; then (``remove``) remove those outputs (other files are left alone), so that
    no output of the previous run is ever taken for one of the new run's. ``remove=False`` only
    checks (the CLI, before the dataset is opened: a run that cannot start keeps the old outputs).
    ConfigError naming the folder and ``--overwrite``; DataError when one cannot be removed."""
    out = Path(out_dir)
    previous = previous_run_outputs(out)
    if previous and not overwrite:
        names = ", ".join(p.name for p in previous)
        raise ConfigError(f"output folder {out} holds the outputs of a previous run ({names}); "
                          "use --overwrite to replace them, or another --out")
    if not remove:
        return
    for path in previous:
        try:
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        except OSError as exc:
            raise DataError(f"{path}: cannot remove the previous run's output: {exc.strerror or exc}") from exc
    if previous:
        logger.info("removed the previous run's outputs in %s: %s", out, ", ".join(p.name for p in previous))


@dataclass
class RunSummary:
    """Everything ``summary.json`` holds (``to_dict()``); times in seconds unless named ``_ms``."""

    out_dir: str
    dataset: dict[str, Any]
    frontend: str
    sensor: str
    frames_total: int  # frames of the dataset selection
    frames_read: int  # frames the dataset delivered (not skipped as corrupt)
    frames_processed: int  # frames the frontend consumed
    frames_with_pose: int  # poses in the written trajectory
    keyframes: int
    pose_sources: dict[str, int]  # final trajectory: tracked / motion_model / ...
    failures: dict[str, int]  # tracking (motion-model poses), no_pose, skipped_corrupt, nonfinite_pose
    failure_frames: list[int]  # dataset indices of the frames whose pose came from the motion model
    skipped_frames: list[dict[str, Any]]  # frames skipped by the dataset (unreadable, wrong size): index and reason
    events: dict[str, int]  # frontend events by kind (event_kind: text before the first ':', numbers stripped)
    wall_s: float
    cpu_s: float  # CPU time (user + system, all threads) of the run: comparable across machine loads
    fps: float  # frames processed per second of wall time (reading included)
    fps_frontend: float  # frames per second of frontend time (process + finish)
    max_frame_s: float  # longest frontend.process() of one frame (a stall of tracking)
    read_s: float  # time spent reading frames from the dataset
    stage_s: dict[str, float]  # frontend.stage_times()
    stage_ms_per_frame: dict[str, float]
    peak_rss_mb: float
    motion: dict[str, float]  # estimate (own frame and scale): path length, largest distance from the first pose
    evaluation: Optional[dict[str, Any]]  # None without ground truth
    outputs: dict[str, str]  # file kind -> path
    config: dict[str, Any]
    load_average: list[float]  # os.getloadavg() at the start (shared machines)
    error: Optional[str] = None
    notes: list[str] = field(default_factory=list)
    loop: Optional[dict[str, Any]] = None  # SlamSystem.loop_summary(): loop closure counts (None: off)
    inertial: Optional[dict[str, Any]] = None  # inertial_summary(): the IMU state at the end (None: no IMU service)
    interrupted: Optional[str] = None  # the signal that stopped the run (SIGINT, SIGTERM), None when it ran to the end
    output_errors: dict[str, str] = field(default_factory=dict)  # output kind -> why it could not be written

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def ate_rmse(self) -> Optional[float]:
        return None if self.evaluation is None else self.evaluation["ate"]["rmse"]

    def to_dict(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in self.__dataclass_fields__}


@dataclass
class RunState:
    """What the loop accumulates (kept small: one 4x4 pose per frame)."""

    frames_read: int = 0
    frames_processed: int = 0
    live_t: list[float] = field(default_factory=list)
    live_T: list[np.ndarray] = field(default_factory=list)
    live_source: list[str] = field(default_factory=list)
    failure_frames: list[int] = field(default_factory=list)
    nonfinite: int = 0
    events: Counter = field(default_factory=Counter)
    read_s: float = 0.0
    frontend_s: float = 0.0
    max_frame_s: float = 0.0  # longest frontend.process() call
    wall_s: float = 0.0
    cpu_s: float = 0.0
    frame_paths: dict[int, str] = field(default_factory=dict)  # dataset index -> image path (map.npz)


def outputs_text(out: Path, summary: RunSummary) -> str:
    """Where the outputs went, and which could not be written (for error messages)."""
    errors = summary.output_errors
    if not errors:
        return f"partial outputs written to {out}, see {SUMMARY_FILE}" if summary.error else f"outputs in {out}"
    failed = "; ".join(f"{kind}: {why}" for kind, why in errors.items())
    kept = ", ".join(sorted(summary.outputs)) or "none"
    see = "" if "summary" in errors else f", see {SUMMARY_FILE}"
    return f"could not write {len(errors)} output(s) in {out} ({failed}); written: {kept}{see}"


def _final_trajectory(
    frontend: Frontend, state: RunState, notes: list[str], errors: list[tuple[BaseException, str]]
) -> tuple[Optional[Trajectory], list[str]]:
    """The frontend's final trajectory (non-finite poses dropped). After an error, or when the
    frontend cannot give a valid one (then recorded in ``errors``), the live per-frame estimates."""
    t = T_WC = None
    sources: list[str] = []
    if not errors:
        try:
            t, T_WC, sources = frontend.trajectory()
            t = np.asarray(t, dtype=np.float64).reshape(-1)
            T_WC = np.asarray(T_WC, dtype=np.float64).reshape(-1, 4, 4)
            sources = [str(s) for s in sources]
            if not (t.shape[0] == T_WC.shape[0] == len(sources)):
                raise DataError(f"{t.shape[0]} timestamps, {T_WC.shape[0]} poses, {len(sources)} pose sources")
        except Exception as exc:  # noqa: BLE001 - recorded; the live estimates are written instead
            errors.append((exc, "in trajectory()"))
            t = None
    if t is None:  # after an error: the live per-frame estimates
        notes.append("the trajectory holds the live per-frame estimates (the run stopped before the final one)")
        t = np.asarray(state.live_t, dtype=np.float64)
        T_WC = np.asarray(state.live_T, dtype=np.float64).reshape(-1, 4, 4)
        sources = list(state.live_source)
    if t.shape[0] == 0:
        return None, []
    ok = np.all(np.isfinite(T_WC), axis=(1, 2)) & np.isfinite(t)
    if not np.all(ok):
        state.nonfinite += int((~ok).sum())
        logger.warning("dropping %d non-finite poses from the final trajectory", int((~ok).sum()))
        t, T_WC, sources = t[ok], T_WC[ok], [s for s, k in zip(sources, ok) if k]
        if t.shape[0] == 0:
            return None, []
    T_WC = T_WC.copy()
    T_WC[:, 3, :] = (0.0, 0.0, 0.0, 1.0)
    try:
        return Trajectory(t, T_WC), sources
    except DataError as exc:
        errors.append((exc, "in trajectory() (invalid poses)"))
        notes.append(f"the trajectory could not be written: {exc}")
        return None, []


def _motion(traj: Optional[Trajectory]) -> dict[str, float]:
    if traj is None or len(traj) == 0:
        return {"path_length": 0.0, "max_distance_from_start": 0.0, "bbox_diagonal": 0.0}
    p = traj.t_WC
    return {
        "path_length": traj.path_length(),
        "max_distance_from_start": float(np.linalg.norm(p - p[0], axis=1).max()),
        "bbox_diagonal": float(np.linalg.norm(p.max(axis=0) - p.min(axis=0))),
    }


def _evaluate(gt: Trajectory, est: Trajectory, config: SlamConfig, notes: list[str]) -> Optional[EvalResult]:
    eval_config = replace(config.eval, align=config.alignment())
    try:
        return evaluate(gt, est, eval_config)
    except EvaluationError as exc:
        notes.append(f"evaluation failed: {exc}")
        logger.warning("evaluation failed: %s", exc)
        return None


def _evaluation_dict(result: EvalResult) -> dict[str, Any]:
    d = result.to_dict()
    path = result.gt_path_length_m
    d["ate_rmse_m"] = result.ate.rmse
    d["ate_percent_of_path"] = 100.0 * result.ate.rmse / path if path > 0 else None
    aligned = result.aligned_est.t_WC
    d["aligned_motion"] = {
        "path_length": result.aligned_est.path_length(),
        "max_distance_from_start": float(np.linalg.norm(aligned - aligned[0], axis=1).max()),
    }
    d["coverage"] = result.n_matched / max(result.n_gt, 1)  # share of ground-truth frames with an estimate
    return d


def finalize_run(
    dataset: Dataset,
    gt: Optional[Trajectory],
    system: SlamSystem,
    config: SlamConfig,
    state: RunState,
    out: Path,
    load_average: list[float],
    error: Optional[tuple[BaseException, str]],
) -> tuple[RunSummary, Optional[tuple[BaseException, str]]]:
    """Write trajectories, PLY, plot and summary.json, each on its own (a failing one is recorded in
    ``output_errors`` and never stops the others). Returns the summary and the first error (the
    loop's, or one raised by the frontend's end-of-run queries, which never prevents the writing)."""
    notes: list[str] = []
    errors: list[tuple[BaseException, str]] = [] if error is None else [error]
    frontend = system.frontend
    traj, sources = _final_trajectory(frontend, state, notes, errors)
    outputs: dict[str, str] = {}
    output_errors: dict[str, str] = {}
    if traj is not None:
        _write_output("tum", [out / TUM_FILE], lambda: write_trajectory(out / TUM_FILE, traj, "tum"),
                      outputs, output_errors)
        kitti_paths = [out / KITTI_FILE, out / KITTI_TIMES_FILE]
        if _write_output("kitti", kitti_paths, lambda: write_trajectory(kitti_paths[0], traj, "kitti", kitti_paths[1]),
                         outputs, output_errors):
            outputs["kitti_times"] = str(out / KITTI_TIMES_FILE)
    elif errors:  # without an error the summary's error says why (no_pose_reason)
        notes.append("no frame got a pose before the error: no trajectory files written")

    result = evaluation = None
    if gt is not None and traj is not None:
        try:
            result = _evaluate(gt, traj, config, notes)
            evaluation = None if result is None else _evaluation_dict(result)
        except Exception as exc:  # noqa: BLE001 - recorded; the outputs are still written
            result = evaluation = None
            notes.append(f"evaluation failed: {type(exc).__name__}: {exc}")
            logger.warning("evaluation failed: %s: %s", type(exc).__name__, exc)

    stage_s: dict[str, float] = {}
    keyframes = -1
    loop = inertial = None
    points = None
    try:
        stage_s = {k: float(v) for k, v in system.stage_times().items()}
        keyframes = int(frontend.num_keyframes())
        loop = system.loop_summary()
        inertial = inertial_summary(system.inertial_state(), float(dataset.timestamps[0]) if len(dataset) else None)
        if config.output.write_ply:
            points = frontend.keyframe_points()
            if points is None:
                notes.append(f"output.write_ply: frontend '{frontend.name}' provides no points; no PLY written")
    except Exception as exc:  # noqa: BLE001 - recorded; the summary is still written
        errors.append((exc, "in its end-of-run queries (stage_times/num_keyframes/loop_summary/keyframe_points)"))
    if points is not None:
        _write_output("ply", [out / PLY_FILE], lambda: _write_points(out / PLY_FILE, points), outputs, output_errors)
    _write_keyframe_depths(frontend, config, out, outputs, output_errors, notes)
    if config.output.write_map and traj is not None:  # no pose, no map (and no note that would blame the frontend)
        _write_map(out / MAP_FILE, dataset, frontend, config, state, outputs, output_errors, notes)
    if (config.output.save_map or config.output.extend_map) and traj is not None:
        _save_stored_map(out, traj, dataset, frontend, config, state, result, outputs, output_errors, notes)
    if config.output.plot and traj is not None:
        _write_output("plot", [out / PLOT_FILE], lambda: _plot(out / PLOT_FILE, gt, traj, result, config),
                      outputs, output_errors)
    n = state.frames_processed
    frames_with_pose = 0 if traj is None else len(traj)
    failures = {
        "tracking": len(state.failure_frames),
        "no_pose": max(n - frames_with_pose, 0),
        "skipped_corrupt": len(dataset.skipped_frames),
        "nonfinite_pose": state.nonfinite,
    }
    first_error = errors[0] if errors else None
    interrupted = error_text = None
    if first_error is not None and isinstance(first_error[0], KeyboardInterrupt):
        interrupted = signal.Signals(getattr(first_error[0], "signum", signal.SIGINT)).name
        error_text = f"interrupted by {interrupted} {first_error[1]}"
    elif first_error is not None:
        error_text = f"{first_error[1]}: {type(first_error[0]).__name__}: {first_error[0]}"
    elif traj is None:  # ran to the end without a result: an error too (batch reruns it, the exit is non-zero)
        error_text = no_pose_reason(dataset, config, state)  # the caller's error line (NoPoseError) says it
    outputs["summary"] = str(out / SUMMARY_FILE)
    summary = RunSummary(
        out_dir=str(out),
        dataset={
            "path": str(dataset.root), "format": dataset.format, "name": dataset.name,
            "resolution": [dataset.calibration.width, dataset.calibration.height],
            "rate_hz": dataset.rate, "groundtruth": gt is not None,
        },
        frontend=config.frontend,
        sensor=config.sensor,
        frames_total=len(dataset),
        frames_read=state.frames_read,
        frames_processed=n,
        frames_with_pose=frames_with_pose,
        keyframes=keyframes,
        pose_sources=dict(Counter(sources)),
        failures=failures,
        failure_frames=list(state.failure_frames),
        skipped_frames=[{"index": int(i), "reason": r} for i, r in dataset.skipped_frames],
        events=dict(state.events),
        wall_s=state.wall_s,
        cpu_s=state.cpu_s,
        fps=n / state.wall_s if state.wall_s > 0 else 0.0,
        fps_frontend=n / state.frontend_s if state.frontend_s > 0 else 0.0,
        max_frame_s=state.max_frame_s,
        read_s=state.read_s,
        stage_s=stage_s,
        stage_ms_per_frame={k: 1000.0 * v / n for k, v in stage_s.items()} if n else {},
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * BYTES_PER_KIB / BYTES_PER_MIB,
        motion=_motion(traj),
        evaluation=evaluation,
        outputs=outputs,
        config=to_dict(config),
        load_average=load_average,
        error=error_text,
        notes=notes,
        loop=loop,
        inertial=inertial,
        interrupted=interrupted,
        output_errors=output_errors,
    )
    if not _write_output("summary", [out / SUMMARY_FILE], lambda: _write_summary(out / SUMMARY_FILE, summary),
                         outputs, output_errors):
        logger.error("%s could not be written; the run summary is only on the console", out / SUMMARY_FILE)
    return summary, first_error


def _vector(value: Any) -> Optional[list[float]]:
    return None if value is None else [float(x) for x in value]


def inertial_summary(state: Optional[Mapping[str, Any]], t_first: Optional[float] = None) -> Optional[dict[str, Any]]:
    """``summary.json`` ``inertial`` from the IMU service's state mapping (``SlamSystem.inertial_state``;
    keys ``initialized``, ``init_time``, ``scale``, ``gravity_W``, ``bias_gyro``, ``bias_accel``, counters;
    missing ones are None): initialised or not, when (dataset clock and seconds after the first frame
    ``t_first``), the metric scale applied (monocular) with the last inertial-only optimisation's ``scale_sigma`` and
    how many ran, gravity and its magnitude, the bias norms."""
    if state is None:
        return None
    gravity = _vector(state.get("gravity_W"))
    bias_gyro, bias_accel = _vector(state.get("bias_gyro")), _vector(state.get("bias_accel"))
    init_time = state.get("init_time")
    out = {
        "initialized": bool(state.get("initialized", False)),
        "init_time": None if init_time is None else float(init_time),
        "init_after_s": None if init_time is None or t_first is None else float(init_time) - t_first,
        "scale": None if state.get("scale") is None else float(state["scale"]),
        "scale_sigma": None if state.get("scale_sigma") is None else float(state["scale_sigma"]),
        "inertial_only_runs": int(state.get("inertial_only_runs") or 0),
        "gravity_W": gravity,
        "gravity_norm": None if gravity is None else float(np.linalg.norm(gravity)),
        "bias_gyro": bias_gyro,
        "bias_gyro_norm": None if bias_gyro is None else float(np.linalg.norm(bias_gyro)),
        "bias_accel": bias_accel,
        "bias_accel_norm": None if bias_accel is None else float(np.linalg.norm(bias_accel)),
        "input_warnings": list(state.get("input_warnings") or []),
    }
    for key in ("links", "unlinked_intervals", "bad_intervals", "predictions"):
        if key in state:
            out[key] = state[key]
    return out


def no_pose_reason(dataset: Dataset, config: SlamConfig, state: RunState) -> str:
    """One line on why a run that ended normally gave no frame a pose: the frames the frontend saw,
    what it reported (its events by kind) and, for images larger than :data:`LARGE_IMAGE_SIDE`, the
    config keys that resize them."""
    n, skipped = state.frames_processed, len(dataset.skipped_frames)
    seen = f"{n} frame{'s' if n != 1 else ''} processed of {len(dataset)}"
    if skipped:
        seen += f", {skipped} skipped (unreadable or of the wrong size)"
    text = f"no frame got a pose: frontend '{config.frontend}' ({config.sensor}) never initialised in {seen}"
    if state.events:
        text += " (events: " + ", ".join(f"{kind} x{count}" for kind, count in state.events.most_common()) + ")"
    width, height = int(dataset.calibration.width), int(dataset.calibration.height)
    if max(width, height) > LARGE_IMAGE_SIDE:
        text += (f"; the images are {width}x{height}, too large: resize them, e.g. "
                 f"-o dataset.resize_width={SUGGESTED_RESIZE_WIDTH} (or dataset.resize_scale)")
    elif n == 0:
        text += "; no frame could be read"
    return text


def _write_map(path: Path, dataset: Dataset, frontend: Frontend, config: SlamConfig, state: RunState,
               outputs: dict[str, str], output_errors: dict[str, str], notes: list[str]) -> None:
    """``map.npz`` for ``fgslam export``: the frontend's :meth:`~Frontend.map_export` with the
    calibration of the images it saw and the run's frames (a frontend without a map: a note)."""
    from .export.map import RunMap, save_run_map

    try:
        exported = frontend.map_export()
    except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
        output_errors["map"] = f"{path.name}: map_export() failed: {type(exc).__name__}: {exc}"
        logger.error("could not export the map: %s: %s", type(exc).__name__, exc)
        return
    if exported is None:
        notes.append(f"frontend '{frontend.name}' exports no map: no {path.name} written")
        return
    c = dataset.calibration
    indices = np.array(sorted(state.frame_paths), dtype=np.int64)
    run_map = RunMap(exported, np.asarray(c.K, dtype=np.float64), int(c.width), int(c.height),
                     dataset.timestamps[indices] if indices.size else np.zeros(0), indices,
                     [state.frame_paths[int(i)] for i in indices], config.sensor)
    _write_output("map", [path], lambda: save_run_map(path, run_map), outputs, output_errors)


def _save_stored_map(out: Path, traj: Trajectory, dataset: Dataset, frontend: Frontend, config: SlamConfig,
                     state: RunState, result: Optional[EvalResult], outputs: dict[str, str],
                     output_errors: dict[str, str], notes: list[str]) -> None:
    """``--save-map``: the stored map of :mod:`fgslam.export.mapfile` (keyframes, structure, features,
    retrieval database, calibration, config and the run's alignment to its ground truth). ``--map``:
    the recording is merged into that stored map when its keyframes localise in it
    (:func:`fgslam.localize.merge_recording`): ``merge.json`` and ``merged_trajectory_tum.txt`` (the
    frames from the merge on, in the map's frame), and ``--save-map`` saves the merged map."""
    from .export.mapfile import build_stored_map, load_stored_map, save_stored_map

    save_path = Path(config.output.save_map) if config.output.save_map else None
    try:
        exported = frontend.map_export()
    except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
        output_errors["stored_map"] = f"map_export() failed: {type(exc).__name__}: {exc}"
        return
    if exported is None or exported.num_keyframes == 0:
        notes.append(f"frontend '{frontend.name}' exports no keyframes: no stored map written or extended")
        return
    alignment = None if result is None else {"align": result.align, "matrix": result.alignment.matrix().tolist()}
    try:
        recording = build_stored_map(
            exported, dataset, sensor=config.sensor, family=frontend.name, config=to_dict(config),
            features=config.output.map_features, verification=config.loop_closure.verification,
            groundtruth_alignment=alignment, frame_indices=np.array(sorted(state.frame_paths), dtype=np.int64))
    except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
        output_errors["stored_map"] = f"building the stored map failed: {type(exc).__name__}: {exc}"
        logger.error("could not build the stored map: %s: %s", type(exc).__name__, exc)
        return
    to_save = recording
    if config.output.extend_map:
        from .io.trajectory import Trajectory
        from .localize import LocalizeConfig, combine_maps, merge_recording, rigid_in_map

        try:
            stored = load_stored_map(config.output.extend_map)
            merge = merge_recording(stored, recording, LocalizeConfig(merge=config.output.map_merge))  # Sim(3) unless both metric
        except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
            output_errors["merge"] = f"--map {config.output.extend_map}: {type(exc).__name__}: {exc}"
            logger.error("could not merge the recording into %s: %s", config.output.extend_map, exc)
            return
        info = {"map": config.output.extend_map, "merged": merge is not None,
                **({} if merge is None else merge.to_dict())}
        if merge is None:
            notes.append(f"--map {config.output.extend_map}: no keyframe of the recording localised in it "
                         "consistently: not merged (the recording stays its own map)")
        else:
            keep = traj.timestamps >= merge.merge_time
            merged = Trajectory(traj.timestamps[keep], rigid_in_map(merge.S_MR, traj.T_WC[keep]))
            path = out / MERGED_TUM_FILE
            _write_output("merged_trajectory", [path], lambda: write_trajectory(path, merged, "tum"), outputs,
                          output_errors)
            to_save = combine_maps(stored, recording, merge.S_MR)
        merge_path = out / MERGE_FILE
        _write_output("merge", [merge_path],
                      lambda: merge_path.write_text(json.dumps(info, indent=2) + "\n", encoding="utf-8"),
                      outputs, output_errors)
    if save_path is not None:  # written atomically: a failure leaves an earlier file at that path as it was
        try:
            save_stored_map(save_path, to_save)
            outputs["stored_map"] = str(save_path)
        except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
            output_errors["stored_map"] = f"{save_path}: {type(exc).__name__}: {exc}"
            logger.error("could not write the stored map %s: %s", save_path, exc)


def _write_output(kind: str, paths: list[Path], write: Callable[[], Any], outputs: dict[str, str],
                  output_errors: dict[str, str]) -> bool:
    """Run ``write`` (which writes ``paths``); on any failure remove what it left (never a truncated
    file), record the reason under ``kind`` in ``output_errors`` and carry on. True when written."""
    try:
        write()
    except Exception as exc:  # noqa: BLE001 - one output's failure never costs the others
        for path in paths:
            try:
                path.unlink(missing_ok=True)
            except OSError:
                pass
        outputs.pop(kind, None)
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        output_errors[kind] = f"{paths[0].name}: {type(exc).__name__}: {why}"
        logger.error("could not write %s: %s: %s", paths[0], type(exc).__name__, why)
        return False
    outputs[kind] = str(paths[0])
    return True


def _write_summary(path: Path, summary: RunSummary) -> None:
    """summary.json, written to a temporary file and renamed: never a truncated one."""
    text = json.dumps(summary.to_dict(), indent=2, default=_json_default) + "\n"
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _json_default(obj: Any) -> Any:
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
    from .io.plot import plot_trajectories, pose_errors

    est = traj if result is None else result.aligned_est
    plane = config.output.plot_plane
    if plane == "auto":
        plane = auto_plane(gt if gt is not None else est)
    if result is not None:
        title = (f"{config.frontend} {config.sensor}: ATE {result.ate.rmse:.3f} m "
                 f"({result.align}, {result.n_matched} poses)")
    else:
        title = f"{config.frontend} {config.sensor}: estimate ({len(traj)} poses, no ground truth)"
    errors = None if result is None else {"estimate": pose_errors(result.matched_gt, result.aligned_est)}
    return plot_trajectories(path, gt, est, title=title, plane=plane, errors=errors)


def auto_plane(traj: Trajectory) -> str:
    """The plane of the two axes along which ``traj`` extends most (a top view for ground vehicles
    and hand-held sequences alike, whatever the world frame's up axis)."""
    extent = np.ptp(traj.t_WC, axis=0) if len(traj) else np.zeros(3)
    a, b = sorted(np.argsort(extent)[-2:])
    return "xyz"[a] + "xyz"[b]


def _write_keyframe_depths(frontend: Frontend, config: SlamConfig, out: Path, outputs: dict[str, str],
                           output_errors: dict[str, str], notes: list[str]) -> None:
    """``output.write_depth``: ``depth/<kf:06d>.png`` per keyframe of ``frontend.keyframe_depths()``,
    16-bit millimetres (0: no depth; depths beyond 65.535 m clipped), written as one output."""
    if not config.output.write_depth:
        return
    try:
        depths = frontend.keyframe_depths()
    except Exception as exc:  # noqa: BLE001 - recorded; the other outputs are still written
        output_errors["depth"] = f"keyframe_depths(): {type(exc).__name__}: {exc}"
        logger.error("could not get the keyframe depths: %s: %s", type(exc).__name__, exc)
        return
    if not depths:
        notes.append(f"output.write_depth: frontend '{frontend.name}' provides no keyframe depths; none written")
        return
    folder = out / DEPTH_DIR
    paths = [folder / f"{kf:06d}.png" for kf in sorted(depths)]

    def write() -> None:
        import cv2

        folder.mkdir(exist_ok=True)
        for path, kf in zip(paths, sorted(depths)):
            depth = np.nan_to_num(np.asarray(depths[kf][1], dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
            mm = np.clip(np.rint(depth * 1000.0), 0, np.iinfo(np.uint16).max).astype(np.uint16)
            if not cv2.imwrite(str(path), mm):
                raise OSError(f"cv2.imwrite failed for {path}")

    if _write_output("depth", paths, write, outputs, output_errors):
        outputs["depth"] = str(folder)


def _write_points(path: Path, points: tuple[np.ndarray, np.ndarray]) -> Path:
    """Binary little-endian PLY of the finite points ``(X_W (N, 3), colour (N, 3) uint8)``."""
    from .export.ply import write_ply

    return write_ply(path, points[0], points[1])
