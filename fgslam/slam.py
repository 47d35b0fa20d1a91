"""The SLAM runner: a dataset in, the run's system in the middle, trajectories, a summary and a plot out.

``SlamConfig`` (:mod:`fgslam.runconfig`) is the root configuration of a run (``fgslam/configs/*.yaml``
are presets of it); :func:`run_slam` builds the run's :class:`~fgslam.system.SlamSystem` (backend,
frontend, services), steps it over a :class:`~fgslam.io.datasets.Dataset` and writes
(:mod:`fgslam.outputs`), in ``out_dir``:

- ``trajectory_tum.txt``: ``t tx ty tz qx qy qz qw`` per frame with a pose (camera-to-world ``T_WC``
  in the estimate's world frame; monocular translations are in the map's arbitrary scale);
- ``trajectory_kitti.txt`` + ``trajectory_kitti_times.txt``: the same poses as 3x4 rows and their
  timestamps (seconds);
- ``summary.json``: frame counts, keyframes, frames/s overall and per stage, failures by kind,
  skipped frames, the estimate's motion extent, evaluation (ATE with the alignment used, RPE, % of
  path length) when the dataset has ground truth, loop closure counts (``loop``, when the frontend
  runs loop closure: ``SlamSystem.loop_summary()``), the full configuration used, the error when
  the run failed (``interrupted``: the signal that stopped it) and the outputs that could not be
  written (``output_errors``);
- ``trajectory.png``: top view of the (aligned) estimate against the ground truth;
- ``points.ply`` when ``output.write_ply`` (the frontend's keyframe points, when it has any);
- ``depth/<kf:06d>.png`` when ``output.write_depth`` (16-bit millimetres, from ``keyframe_depths()``).

Failure handling: tracking failures are reported by the frontend (``pose_source == "motion_model"``)
and counted; corrupt frames are skipped by the dataset and counted; a non-finite pose from the
frontend is dropped and counted. If the frontend (or the dataset) raises mid-run, everything that
exists is written first (partial trajectory from the frontend, else from the per-frame live
estimates, and a summary with the error), then a :class:`RunError` (or the dataset's own
:class:`~fgslam.errors.DataError`) is raised.

Stopping: SIGINT (Ctrl-C) and SIGTERM (batch schedulers, ``timeout``) stop the loop at once; the
partial outputs and a summary naming the signal are written, ``on_summary`` reports it, then
:class:`~fgslam.errors.Interrupted` is raised (``exit_code`` 130 / 143). A further signal (a second
Ctrl-C) arriving while the outputs are written and reported is logged ("stopping: writing outputs,
please wait") and ignored: they are completed. The handlers are installed only for the duration of
the run and the previous ones are restored.

No result: a run that ends without a pose for any frame writes its summary with the reason as its
``error`` (:func:`no_pose_reason`) and raises :class:`NoPoseError`.

Previous outputs: an ``out_dir`` that holds a previous run's outputs (:data:`RUN_OUTPUT_FILES`,
``depth/``) is refused unless ``overwrite``, which removes them before the run starts.

Outputs are never lost to one failure: the output folder is checked (created, writable, not the
dataset folder nor inside it) before any work, and every output (each trajectory format, plot, PLY,
summary) is written on its own, a file that fails (a plotting error, a full disk) is removed rather
than left truncated and its error is recorded in ``summary.json`` (``output_errors``); the summary
is written last, atomically. The caller's ``on_summary`` gets the summary in every case (the console
report), then :class:`OutputError` is raised when an output could not be written.

Alignment for evaluation (``auto_align``): Sim(3) for monocular runs (scale is unobservable),
SE(3) for stereo and RGB-D (metric).
"""

from __future__ import annotations

import logging
import math
import os
import re
import resource
import signal
import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from .config import check_ranges
from .errors import ConfigError, DataError, FGSlamError, Interrupted
from .frontends.base import FrameStatus, Frontend
from .io.datasets import Dataset, open_dataset
from .memory import check_run_memory
from .outputs import (
    DEPTH_DIR, KITTI_FILE, KITTI_TIMES_FILE, LARGE_IMAGE_SIDE, MAP_FILE, PLOT_FILE, PLY_FILE, RUN_OUTPUT_FILES,
    SUMMARY_FILE, TUM_FILE, RunState, RunSummary, clear_previous_outputs, finalize_run, no_pose_reason, outputs_text,
    prepare_output_dir, previous_run_outputs)
from .runconfig import OutputConfig, SensorName, SlamConfig, dataset_config_for, load_slam_config
from .system import SlamSystem

logger = logging.getLogger(__name__)

#: the runner's public names: the run itself, and the configuration and outputs it uses (defined in
#: :mod:`fgslam.runconfig` and :mod:`fgslam.outputs`)
__all__ = ["DEPTH_DIR", "KITTI_FILE", "KITTI_TIMES_FILE", "LARGE_IMAGE_SIDE", "MAP_FILE", "PLOT_FILE", "PLY_FILE",
           "RUN_OUTPUT_FILES", "SUMMARY_FILE", "TUM_FILE", "NoPoseError", "OutputConfig", "OutputError", "RunError",
           "RunSummary", "SensorName", "SlamConfig", "StopOnSignal", "check_image_size", "check_sensor",
           "clear_previous_outputs", "dataset_config_for", "event_kind", "load_slam_config", "no_pose_reason",
           "open_slam_dataset", "prepare_output_dir", "previous_run_outputs", "run_slam"]


MAX_LOGGED_FAILURES = 10  # tracking failures logged one by one before switching to the progress lines
_WHERE_DATASET = "while reading the dataset"  # error location of a failure inside the dataset iterator


class RunError(FGSlamError):
    """A run stopped because the frontend raised; partial outputs were written before."""


class OutputError(FGSlamError):
    """An output of a run could not be written (the others and, when possible, summary.json were)."""


class NoPoseError(FGSlamError):
    """A run that ended without a pose for any frame: no result (summary.json says why)."""


# ----------------------------------------------------------------------------------------- dataset side


def open_slam_dataset(path: str | Path, config: SlamConfig, fmt: str = "auto") -> Dataset:
    """Open the dataset at ``path`` for ``config`` and check it has what ``config.sensor`` needs,
    images of at least ``dataset.min_image_side`` pixels, and an estimated peak memory within
    ``max_memory_gib`` (:mod:`fgslam.memory`)."""
    dataset = open_dataset(path, fmt, dataset_config_for(config))
    check_sensor(dataset, config.sensor)
    check_image_size(dataset)
    check_run_memory(config, dataset)
    return dataset


def check_image_size(dataset: Dataset) -> None:
    """Raise ConfigError when the dataset's output images (after resizing and cropping) are smaller
    than ``dataset.min_image_side`` on a side, naming the resize keys and both sizes."""
    cfg = dataset.config
    width, height = int(dataset.calibration.width), int(dataset.calibration.height)
    if min(width, height) >= cfg.min_image_side:
        return
    raw = dataset.raw_calibration
    source = f" from {raw.width}x{raw.height}" if raw is not None else ""
    raise ConfigError(
        f"{cfg.resize_text()} gives {width}x{height} images{source}"
        f"{f' (after cropping to a multiple of {cfg.crop_multiple})' if cfg.crop_multiple > 1 else ''}; "
        f"both sides must be at least dataset.min_image_side={cfg.min_image_side} pixels"
    )


def check_sensor(dataset: Dataset, sensor: str) -> None:
    """Raise ConfigError when ``dataset`` lacks the images ``sensor`` needs (stereo: right images,
    rgbd: depth maps)."""
    where = f"{dataset.root} ({dataset.format})"
    if sensor == "stereo" and not dataset.has_stereo:
        why = "dataset.load_right is false" if not dataset.config.load_right else "it has no right camera images"
        raise ConfigError(
            f"sensor 'stereo' needs right camera images but {where}: {why}; use sensor=mono or a stereo dataset"
        )
    if sensor == "rgbd" and not dataset.has_depth:
        why = "dataset.load_depth is false" if not dataset.config.load_depth else "it has no depth maps"
        raise ConfigError(f"sensor 'rgbd' needs depth maps but {where}: {why}; use sensor=mono or an RGB-D dataset")
    if sensor not in ("mono", "stereo", "rgbd"):
        raise ConfigError(f"unknown sensor {sensor!r} (expected mono, stereo or rgbd)")


# ----------------------------------------------------------------------------------------- summary


# ----------------------------------------------------------------------------------------- the run


class _Progress:
    """A progress bar (tqdm) on stderr when it is a terminal, else progress lines on the module
    logger at most every ``every_frames`` frames or ``every_s`` s."""

    def __init__(self, total: int, every_frames: int, every_s: float, enabled: bool) -> None:
        self.total, self.every_frames, self.every_s, self.enabled = total, every_frames, every_s, enabled
        self.t0 = time.perf_counter()
        self.last_t, self.last_n = self.t0, 0
        self.bar = _progress_bar(total, "frames") if enabled else None

    def update(self, n: int, keyframes: int, failures: int, force: bool = False) -> None:
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(n - self.bar.n)
            self.bar.set_postfix(keyframes=keyframes, failures=failures, refresh=False)
            if force:
                self.bar.close()
            return
        now = time.perf_counter()
        if not force and n - self.last_n < self.every_frames and now - self.last_t < self.every_s:
            return
        self.last_t, self.last_n = now, n
        elapsed = now - self.t0
        fps = n / elapsed if elapsed > 0 else 0.0
        eta = (self.total - n) / fps if fps > 0 else math.inf
        eta_txt = f"{eta:.0f} s" if math.isfinite(eta) else "?"
        logger.info(
            "frame %d/%d (%.0f%%)  %.1f frames/s  %d keyframes  %d failures  ETA %s",
            n, self.total, 100.0 * n / max(self.total, 1), fps, keyframes, failures, eta_txt,
        )


def _progress_bar(total: int, unit: str):
    """A tqdm bar on stderr when stderr is a terminal (None otherwise: log lines instead)."""
    import sys

    if not (hasattr(sys.stderr, "isatty") and sys.stderr.isatty()):
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, file=sys.stderr, dynamic_ncols=True, leave=True)


def _cpu_seconds() -> float:
    """User + system CPU time of this process so far (all threads)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_slam(
    dataset: Dataset,
    config: SlamConfig,
    out_dir: str | Path,
    progress: bool = True,
    frontend: Optional[Frontend] = None,
    on_summary: Optional[Callable[[RunSummary], None]] = None,
    rerun: Optional[str] = None,
    overwrite: bool = False,
) -> RunSummary:
    """Run SLAM over ``dataset`` with ``config`` and write the outputs into ``out_dir``.

    Args:
        dataset: an opened dataset (see :func:`open_slam_dataset`); checked against ``config.sensor``.
        config: the run configuration.
        out_dir: output folder (created; checked writable and outside the dataset before any work).
        progress: log a progress line every ``config.log_interval_frames`` frames / ``log_interval_s`` s.
        frontend: use this frontend instead of building ``config.frontend`` (tests, custom frontends).
        on_summary: called with the summary once the outputs are written, also when the run then
            raises (the command line prints its report there).
        rerun: log the run to rerun: a ``.rrd`` file, or ``live`` for a running viewer
            (:mod:`fgslam.export.rerun`; the rerun SDK is an optional extra).
        overwrite: replace the outputs of a previous run in ``out_dir`` (removed before the run
            starts); without it such a folder is a ConfigError (:func:`clear_previous_outputs`).

    Returns:
        The :class:`RunSummary` also written to ``summary.json``.

    Raises:
        ConfigError: the dataset lacks what the sensor mode needs, the frontend is not available, or
            the output folder is the dataset folder or inside it, or holds a previous run's outputs
            (without ``overwrite``).
        RunError: the frontend raised (partial outputs and a summary with the error were written).
        DataError: the dataset failed mid-run (too many corrupt frames; partial outputs written), or
            the output folder cannot be created or written.
        Interrupted: SIGINT or SIGTERM stopped the run (partial outputs and summary written).
        OutputError: an output could not be written (every other one was).
        NoPoseError: the run ended without a pose for any frame (no result; the summary says why).
    """
    config.validate()
    check_ranges(config)
    check_sensor(dataset, config.sensor)
    check_image_size(dataset)
    check_run_memory(config, dataset)
    out = prepare_output_dir(out_dir, dataset.root)
    clear_previous_outputs(out, overwrite)  # refused, or removed before the run starts
    imu_input_warnings: list[str] = []
    if config.imu.enabled and dataset.imu is not None:  # units, axes, clock: a named mistake before any work
        from .services.imu_checks import check_imu_stream

        imu_input_warnings = check_imu_stream(dataset.imu, dataset.timestamps, config.imu.checks, config.imu.gravity,
                                              where=str(dataset.root), T_BC=getattr(dataset.calibration, "T_BC", None))
    system = SlamSystem.build(config, dataset.calibration, frontend=frontend, timestamps=dataset.timestamps,
                              has_imu=dataset.has_imu, imu_noise=getattr(dataset, "imu_noise", None),
                              where=str(dataset.root), rerun=rerun)
    system.imu_input_warnings = imu_input_warnings
    load_average = [round(v, 2) for v in os.getloadavg()]
    gt = dataset.groundtruth  # loaded (and cached by the dataset) before the timed loop
    state = RunState()
    with StopOnSignal((signal.SIGTERM, signal.SIGINT)) as stopper:
        t_start, cpu_start = time.perf_counter(), _cpu_seconds()
        saved_threads = _set_threads(config.threads)
        try:
            error = _loop(dataset, system, config, state, progress)
            if error is not None:
                _abort(system)
        finally:
            stopper.finishing = True  # from here on a signal is logged and the outputs and report are completed
            _restore_threads(saved_threads)
        state.wall_s, state.cpu_s = time.perf_counter() - t_start, _cpu_seconds() - cpu_start
        summary, error = finalize_run(dataset, gt, system, config, state, out, load_average, error)
        if on_summary is not None:  # still under the handlers: a second Ctrl-C never cuts the report
            try:
                on_summary(summary)
            except Exception:  # noqa: BLE001 - a failing report (closed pipe...) never hides the run's own outcome
                logger.exception("reporting the run summary failed")
    written = outputs_text(out, summary)
    if error is not None:
        exc, where = error
        if isinstance(exc, KeyboardInterrupt):
            signum = getattr(exc, "signum", signal.SIGINT)
            raise Interrupted(f"interrupted by {signal.Signals(signum).name} {where} ({state.frames_processed} of "
                              f"{len(dataset)} frames processed; {written})", signum) from exc
        if isinstance(exc, FGSlamError) and where == _WHERE_DATASET:
            raise exc
        if where == _WHERE_DATASET:
            raise DataError(f"{dataset.root}: reading the dataset failed: {type(exc).__name__}: {exc} "
                            f"({written})") from exc
        raise RunError(f"frontend '{config.frontend}' failed {where}: {type(exc).__name__}: {exc} ({written})") from exc
    if summary.frames_with_pose == 0:
        raise NoPoseError(f"{summary.error} ({written})")
    if summary.output_errors:
        raise OutputError(f"the run finished but {written}")
    return summary


def _abort(system: SlamSystem) -> None:
    """Stop the run's background work without waiting for it (a stopped or failed run); a failure
    there is logged, never raised: the outputs are written next."""
    try:
        system.abort()
    except (Exception, KeyboardInterrupt):  # noqa: BLE001 - the run's own outcome is reported
        logger.exception("stopping the background work failed")


class StopOnSignal:
    """While active (a ``with`` block in the main thread), the given signals raise
    :class:`~fgslam.errors.Interrupted` (a ``KeyboardInterrupt``); once ``finishing`` is set (the
    loop has stopped: the outputs and the report are being written), a further one, a second
    Ctrl-C included, is logged and ignored so that they are completed. The previous handlers are
    restored on exit (none is installed outside the main thread, where Python cannot)."""

    def __init__(self, signums: tuple[int, ...]) -> None:
        self.signums = signums
        self.finishing = False
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> "StopOnSignal":
        if threading.current_thread() is not threading.main_thread():
            logger.debug("not in the main thread: no handler for %s", [signal.Signals(s).name for s in self.signums])
            return self
        for signum in self.signums:
            self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        if self.finishing:
            logger.warning("%s received again: still stopping: writing outputs, please wait", name)
            return
        self.finishing = True  # set before raising: a second signal, however soon, never cuts the stop short
        logger.warning("%s received: stopping: writing outputs, please wait", name)
        raise Interrupted(name, signum)

    def __exit__(self, *exc_info: Any) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, signal.SIG_DFL if previous is None else previous)
        self._previous.clear()


def _loop(
    dataset: Dataset, system: SlamSystem, config: SlamConfig, state: RunState, progress: bool
) -> Optional[tuple[BaseException, str]]:
    """Iterate the dataset through the system's frame skeleton; returns ``(exception, where)`` instead of raising
    (an exception anywhere, an interrupt included, stops the loop and is returned with its place)."""
    meter = _Progress(len(dataset), config.log_interval_frames, config.log_interval_s, progress)
    frames = iter(dataset)
    where = _WHERE_DATASET
    t_frontend = None  # start of the current frontend call (its time is counted even when it raises)
    try:
        while True:
            where = _WHERE_DATASET
            t0 = time.perf_counter()
            try:
                frame = next(frames)
            except StopIteration:
                break
            t_frontend = time.perf_counter()
            state.read_s += t_frontend - t0
            state.frames_read += 1
            state.frame_paths[frame.index] = "" if frame.path is None else str(frame.path)
            where = f"at frame {frame.index}" + (f" ({frame.path})" if frame.path is not None else "")
            status = system.step(frame)
            frame_s = time.perf_counter() - t_frontend
            state.frontend_s += frame_s
            state.max_frame_s = max(state.max_frame_s, frame_s)
            t_frontend = None
            state.frames_processed += 1
            where = f"after frame {frame.index}"
            _record(status, frame.timestamp, state)
            meter.update(state.frames_processed, system.frontend.num_keyframes(), len(state.failure_frames))
        where = "in finish() after the last frame"
        t_frontend = time.perf_counter()
        system.finish()
        state.frontend_s += time.perf_counter() - t_frontend
        t_frontend = None
        meter.update(state.frames_processed, system.frontend.num_keyframes(), len(state.failure_frames), force=True)
    except (Exception, KeyboardInterrupt) as exc:  # noqa: BLE001 - reported with partial outputs
        if t_frontend is not None:
            state.frontend_s += time.perf_counter() - t_frontend
        return exc, where
    return None


#: What varies inside one kind of event: numbers (ids, counts, values) and parentheses holding one.
_EVENT_VARYING = re.compile(r"\([^()]*\d[^()]*\)|[-+]?\d+(?:\.\d+)?\s*%?")


def event_kind(event: str) -> str:
    """The kind of a frontend event, the key it is counted under in ``summary.json`` ``events``: the
    text before the first ``:`` without the numbers in it (``"keyframe 12 removed"`` and
    ``"keyframe removed: 12"`` -> ``"keyframe removed"``, ``"waiting for parallax (1.2 px)"`` ->
    ``"waiting for parallax"``)."""
    kind = " ".join(_EVENT_VARYING.sub(" ", event.split(":", 1)[0]).split())
    return kind or "event"


def _record(status: FrameStatus, timestamp: float, state: RunState) -> None:
    for event in status.events:
        state.events[event_kind(event)] += 1
        logger.debug("frame %d: %s", status.index, event)
    if status.pose_source == "motion_model":
        state.failure_frames.append(status.index)
        n = len(state.failure_frames)
        if n <= MAX_LOGGED_FAILURES:
            logger.warning(
                "frame %d: tracking failed (%d valid measurements), pose from the motion model%s",
                status.index, status.num_valid,
                "" if n < MAX_LOGGED_FAILURES else " (further failures: progress lines)",
            )
    if status.T_WC is None:
        return
    T_WC = np.asarray(status.T_WC, dtype=np.float64)
    if T_WC.shape != (4, 4) or not np.all(np.isfinite(T_WC)):
        state.nonfinite += 1
        logger.warning("frame %d: the frontend returned a non-finite or malformed pose; dropped", status.index)
        return
    state.live_t.append(float(timestamp))
    state.live_T.append(T_WC)
    state.live_source.append(status.pose_source)


# ----------------------------------------------------------------------------------------- threads


def _set_threads(threads: int) -> Optional[tuple[int, int]]:
    if threads <= 0:
        return None
    import cv2
    import torch

    saved = (torch.get_num_threads(), cv2.getNumThreads())
    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    return saved


def _restore_threads(saved: Optional[tuple[int, int]]) -> None:
    if saved is None:
        return
    import cv2
    import torch

    torch.set_num_threads(saved[0])
    cv2.setNumThreads(saved[1])


