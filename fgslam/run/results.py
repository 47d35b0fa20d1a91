"""What a run ended with and its summary: the record the loop fills (:class:`RunState`), the results
gathered once it stopped (:class:`RunResults`: the final trajectory, :func:`final_trajectory`, written
first; the evaluation, the frontend's and the services' end-of-run figures, :func:`collect_results`) and ``summary.json``'s content
(:class:`RunSummary`, :func:`summarize`; the file itself: :func:`fgslam.run.outputs.write_summary`)."""

from __future__ import annotations

import logging
import resource
import signal
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np

from ..core.config import MS_PER_S, to_dict
from ..core.errors import DataError, EvaluationError
from ..eval.trajectory import EvalResult, evaluate
from ..frontends.base import Frontend
from ..io.datasets import Dataset
from ..io.datasets.common import same_frame_stamps
from ..io.run_files import SUMMARY_FILE
from ..io.trajectory import Trajectory
from .config import SlamConfig
from .prepare import PreparedRun
from .system import SlamSystem

logger = logging.getLogger(__name__)

#: Images with a side above this many pixels are named as the likely reason when no frame got a
#: pose (the frontends are tuned for VGA to KITTI-width images; resize with dataset.resize_width).
LARGE_IMAGE_SIDE = 4096


SUGGESTED_RESIZE_WIDTH = 640  # the dataset.resize_width that hint suggests (VGA width)


BYTES_PER_KIB = 1024  # ru_maxrss is in KiB on Linux


BYTES_PER_MIB = 1024 * 1024

#: an exception of the run and where it happened ("at frame 12 (path)", "in trajectory()", ...)
ErrorAt = tuple[BaseException, str]


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
    read_s: float  # time the loop waited for the next frame (a recorded run reads ahead in a thread: mostly 0)
    read_cpu_s: float  # CPU time of the reader thread alone (decoding; not OpenCV's pool threads): part of cpu_s; 0 when the reader had not ended
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
    live: Optional[dict[str, Any]] = None  # live_summary(): frames dropped, latency (None: not a live run)

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
    """What the loop accumulates (kept small: one 4x4 pose per frame), and the load before it."""

    frames_read: int = 0
    frames_processed: int = 0
    live_t: list[float] = field(default_factory=list)
    live_T: list[np.ndarray] = field(default_factory=list)
    live_source: list[str] = field(default_factory=list)
    unposed_t: list[float] = field(default_factory=list)  # times of the frames the frontend gave no pose when processed
    failure_frames: list[int] = field(default_factory=list)
    nonfinite: int = 0
    events: Counter = field(default_factory=Counter)
    read_s: float = 0.0
    read_cpu_s: float = 0.0  # the reader thread's CPU time (decoding), part of cpu_s
    frontend_s: float = 0.0
    max_frame_s: float = 0.0  # longest frontend.process() call
    wall_s: float = 0.0
    cpu_s: float = 0.0
    frame_paths: dict[int, str] = field(default_factory=dict)  # dataset index -> image path (map.npz)
    load_average: list[float] = field(default_factory=list)  # os.getloadavg() at the start (shared machines)
    latency_s: list[float] = field(default_factory=list)  # live runs: each frame's arrival to its result, seconds
    live_dropped: int = 0  # live runs: frames dropped because the system was behind
    map_starts: list[float] = field(default_factory=list)  # times of the frames where the frontend started a new map


@dataclass
class RunResults:
    """What a run ended with, gathered once its loop stopped (:func:`collect_results`): the final
    trajectory (None: no frame got a pose) and its pose sources, the ground truth and the evaluation
    against it, the frontend's and the services' end-of-run figures, the keyframe points for the PLY
    (``output.write_ply``), the notes for the summary and the errors so far (the loop's first)."""

    traj: Optional[Trajectory]
    sources: list[str]
    gt: Optional[Trajectory]
    notes: list[str] = field(default_factory=list)
    errors: list[ErrorAt] = field(default_factory=list)
    eval_result: Optional[EvalResult] = None
    evaluation: Optional[dict[str, Any]] = None  # summary.json "evaluation" (None: not evaluated)
    stage_s: dict[str, float] = field(default_factory=dict)
    keyframes: int = -1
    loop: Optional[dict[str, Any]] = None  # SlamSystem.loop_summary()
    inertial: Optional[dict[str, Any]] = None  # inertial_summary()
    points: Optional[tuple[np.ndarray, np.ndarray]] = None  # keyframe points (X_W (N, 3), colour (N, 3) uint8)

    @property
    def first_error(self) -> Optional[ErrorAt]:
        """The loop's error, else the first one of the end of the run (None: the run ran to its end)."""
        return self.errors[0] if self.errors else None


def final_trajectory(system: SlamSystem, state: RunState, gt: Optional[Trajectory],
                     error: Optional[ErrorAt]) -> RunResults:
    """The first results of a run whose loop stopped (with ``error``, the loop's, or None): its final
    trajectory (:func:`_final_trajectory`), written before anything else is asked of the run."""
    notes: list[str] = []
    errors: list[ErrorAt] = [] if error is None else [error]
    traj, sources = _final_trajectory(system.frontend, state, notes, errors)
    if traj is None and errors:  # without an error the summary's error says why (no_pose_reason)
        notes.append("no frame got a pose before the error: no trajectory files written")
    return RunResults(traj, sources, gt, notes, errors)


def collect_results(run: PreparedRun, system: SlamSystem, results: RunResults) -> None:
    """The rest of the results (into ``results``, from :func:`final_trajectory`): the trajectory's
    evaluation against the ground truth, and the frontend's and the services' end-of-run queries; an
    error of those queries is recorded (after the loop's), never raised: the outputs are written next."""
    config, dataset, frontend = run.config, run.dataset, system.frontend
    traj, gt, notes, errors = results.traj, results.gt, results.notes, results.errors
    if gt is not None and traj is not None:
        try:
            results.eval_result = _evaluate(gt, traj, config, notes)
            results.evaluation = None if results.eval_result is None else _evaluation_dict(results.eval_result)
        except Exception as exc:  # noqa: BLE001 - recorded; the outputs are still written
            results.eval_result = results.evaluation = None
            notes.append(f"evaluation failed: {type(exc).__name__}: {exc}")
            logger.warning("evaluation failed: %s: %s", type(exc).__name__, exc)
    try:
        results.stage_s = {k: float(v) for k, v in system.stage_times().items()}
        results.keyframes = int(frontend.num_keyframes())
        results.loop = system.loop_summary()
        results.inertial = inertial_summary(system.inertial_state(),
                                            float(dataset.timestamps[0]) if len(dataset) else None)
        if config.output.write_ply:
            results.points = frontend.keyframe_points()
            if results.points is None:
                notes.append(f"output.write_ply: frontend '{frontend.name}' provides no points; no PLY written")
    except Exception as exc:  # noqa: BLE001 - recorded; the summary is still written
        errors.append((exc, "in its end-of-run queries (stage_times/num_keyframes/loop_summary/keyframe_points)"))


def summarize(run: PreparedRun, state: RunState, results: RunResults, written: dict[str, str],
              output_errors: dict[str, str]) -> RunSummary:
    """The summary of a run (``summary.json``'s content) from its results and what its writers wrote
    (``written``: kind -> path) and could not (``output_errors``: kind -> why); both mappings are
    the summary's own (the summary's writer adds itself to them)."""
    dataset, config = run.dataset, run.config
    traj, gt = results.traj, results.gt
    n = state.frames_processed
    frames_with_pose = 0 if traj is None else len(traj)
    failures = {
        "tracking": len(state.failure_frames),
        "no_pose": max(n - frames_with_pose, 0),
        "skipped_corrupt": len(dataset.skipped_frames),
        "nonfinite_pose": state.nonfinite,
    }
    first_error = results.first_error
    interrupted = error_text = None
    if first_error is not None and isinstance(first_error[0], KeyboardInterrupt):
        interrupted = signal.Signals(getattr(first_error[0], "signum", signal.SIGINT)).name
        error_text = f"interrupted by {interrupted} {first_error[1]}"
    elif first_error is not None:
        error_text = f"{first_error[1]}: {type(first_error[0]).__name__}: {first_error[0]}"
    elif traj is None:  # ran to the end without a result: an error too (batch reruns it, the exit is non-zero)
        error_text = no_pose_reason(dataset, config, state)  # the caller's error line (NoPoseError) says it
    stage_s = results.stage_s
    return RunSummary(
        out_dir=str(run.out),
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
        keyframes=results.keyframes,
        pose_sources=dict(Counter(results.sources)),
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
        read_cpu_s=state.read_cpu_s,
        stage_s=stage_s,
        stage_ms_per_frame={k: MS_PER_S * v / n for k, v in stage_s.items()} if n else {},
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * BYTES_PER_KIB / BYTES_PER_MIB,
        motion=_motion(traj),
        evaluation=results.evaluation,
        outputs=written,
        config=to_dict(config),
        load_average=state.load_average,
        error=error_text,
        notes=results.notes,
        loop=results.loop,
        inertial=results.inertial,
        interrupted=interrupted,
        output_errors=output_errors,
        live=live_summary(run, state),
    )


#: the latency percentiles a live run reports
LATENCY_PERCENTILES = (50, 99)


def live_summary(run: PreparedRun, state: RunState) -> Optional[dict[str, Any]]:
    """``summary.json`` ``live``: frames dropped (the system was behind), delivered, and the latency of the
    results (a frame's arrival to its pose) in milliseconds: percentiles and the largest; None when not live."""
    if run.live is None:
        return None
    lat = np.asarray(state.latency_s, dtype=np.float64) * MS_PER_S
    out: dict[str, Any] = {"speed": run.live.speed if run.live.paced else None, "queue": run.live.queue,
                           "dropped": state.live_dropped, "delivered": int(lat.size)}
    for q in LATENCY_PERCENTILES:
        out[f"latency_ms_p{q}"] = float(np.percentile(lat, q)) if lat.size else None
    out["latency_ms_max"] = float(lat.max()) if lat.size else None
    return out


def _final_trajectory(
    frontend: Frontend, state: RunState, notes: list[str], errors: list[ErrorAt]
) -> tuple[Optional[Trajectory], list[str]]:
    """The frontend's final trajectory (non-finite poses dropped). After an error, or when the
    frontend cannot give a valid one (then recorded in ``errors``), the live per-frame estimates
    (after the loop's error completed with the frames posed later, :func:`_with_later_poses`)."""
    if errors:  # the loop stopped: the live estimates, and the frontend's poses of the frames still without one
        t, T_WC, sources = _with_later_poses(frontend, state, *_live_estimates(state, notes), notes)
    else:
        try:
            t, T_WC, sources = _frontend_trajectory(frontend)
        except Exception as exc:  # noqa: BLE001 - recorded; the live estimates are written instead (as they are:
            errors.append((exc, "in trajectory()"))  # the frontend is not asked again for what just failed)
            t, T_WC, sources = _live_estimates(state, notes)
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


def _frontend_trajectory(frontend: Frontend) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """``frontend.trajectory()`` as float arrays ``(N,)``, ``(N, 4, 4)`` and N pose sources; DataError when
    the three lengths differ (anything the frontend raises is passed on)."""
    t, T_WC, sources = frontend.trajectory()
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    T_WC = np.asarray(T_WC, dtype=np.float64).reshape(-1, 4, 4)
    sources = [str(s) for s in sources]
    if not (t.shape[0] == T_WC.shape[0] == len(sources)):
        raise DataError(f"{t.shape[0]} timestamps, {T_WC.shape[0]} poses, {len(sources)} pose sources")
    return t, T_WC, sources


def _live_estimates(state: RunState, notes: list[str]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The live per-frame estimates of a run without its final trajectory (said in ``notes``)."""
    notes.append("the trajectory holds the live per-frame estimates (the run stopped before the final one)")
    return (np.asarray(state.live_t, dtype=np.float64), np.asarray(state.live_T, dtype=np.float64).reshape(-1, 4, 4),
            list(state.live_source))


def _with_later_poses(frontend: Frontend, state: RunState, t: np.ndarray, T_WC: np.ndarray, sources: list[str],
                      notes: list[str]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The live estimates ``t, T_WC, sources`` of a stopped run completed with the frontend's poses of the
    processed frames that had none when they were processed but got one afterwards (a monocular
    initialisation poses the frames it buffered), so that the partial trajectory holds every frame with a
    pose; only those frames are taken from the frontend, matched by timestamp
    (:func:`~fgslam.io.datasets.common.same_frame_stamps`;
    a failure to ask it is a note, never raised)."""
    if not state.unposed_t:
        return t, T_WC, sources
    try:
        f_t, f_T, f_sources = _frontend_trajectory(frontend)
    except Exception as exc:  # noqa: BLE001 - the live estimates are written as they are
        notes.append(f"the frames without a live pose could not be taken from the frontend's trajectory: "
                     f"{type(exc).__name__}: {exc}")
        return t, T_WC, sources
    take = np.flatnonzero(same_frame_stamps(f_t, state.unposed_t) & np.all(np.isfinite(f_T), axis=(1, 2)))
    if take.size == 0:
        return t, T_WC, sources
    notes.append(f"{take.size} frame(s) that got their pose after they were processed (initialisation) are "
                 "taken from the frontend's trajectory")
    t = np.concatenate([t, f_t[take]])
    T_WC = np.concatenate([T_WC, f_T[take]])
    sources = sources + [f_sources[k] for k in take]
    order = np.argsort(t, kind="stable")
    return t[order], T_WC[order], [sources[k] for k in order]


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


def _vector(value: Optional[np.ndarray | list[float]]) -> Optional[list[float]]:
    return None if value is None else [float(x) for x in value]


def inertial_summary(state: Optional[Mapping[str, Any]], t_first: Optional[float] = None) -> Optional[dict[str, Any]]:
    """``summary.json`` ``inertial`` from the IMU service's state mapping (:meth:`fgslam.run.system.SlamSystem.inertial_state`;
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


def outputs_text(out: Path, summary: RunSummary) -> str:
    """Where the outputs went, and which could not be written (for error messages)."""
    errors = summary.output_errors
    if not errors:
        return f"partial outputs written to {out}, see {SUMMARY_FILE}" if summary.error else f"outputs in {out}"
    failed = "; ".join(f"{kind}: {why}" for kind, why in errors.items())
    kept = ", ".join(sorted(summary.outputs)) or "none"
    see = "" if "summary" in errors else f", see {SUMMARY_FILE}"
    return f"could not write {len(errors)} output(s) in {out} ({failed}); written: {kept}{see}"
