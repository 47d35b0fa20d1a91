"""The SLAM runner: a dataset in, the run's system in the middle, trajectories, a summary and a plot out.

``SlamConfig`` (:mod:`fgslam.run.config`) is the root configuration of a run (``fgslam/configs/*.yaml``
are presets of it). A run is prepared first (:mod:`fgslam.run.prepare`: every check before any work,
once), then :func:`run_prepared` trusts its inputs: it builds the run's
:class:`~fgslam.run.system.SlamSystem` (backend, frontend, services), steps it over the
:class:`~fgslam.io.datasets.Dataset`, has the results collected (:mod:`fgslam.run.results`) and
written (:mod:`fgslam.run.outputs`; the stored map: :mod:`fgslam.run.mapstore`), in the output folder:

- ``trajectory_tum.txt``: ``t tx ty tz qx qy qz qw`` per frame with a pose (camera-to-world ``T_WC``
  in the estimate's world frame; monocular translations are in the map's arbitrary scale);
- ``trajectory_kitti.txt`` + ``trajectory_kitti_times.txt``: the same poses as 3x4 rows and their
  timestamps (seconds);
- ``summary.json``: frame counts, keyframes, frames/s overall and per stage, failures by kind,
  skipped frames, the estimate's motion extent, evaluation (ATE with the alignment used, RPE, % of
  path length) when the dataset has ground truth, loop closure counts (``loop``, when the frontend
  runs loop closure: ``SlamSystem.loop_summary()``), the full configuration used, the error when
  the run failed (``interrupted``: the signal that stopped it), the outputs that could not be
  written (``output_errors``) and, for a live run, the frames dropped and the latency (``live``, else null);
- ``trajectory.png``: top view of the (aligned) estimate against the ground truth;
- ``points.ply`` when ``output.write_ply`` (the frontend's keyframe points, when it has any);
- ``depth/<kf:06d>.png`` when ``output.write_depth`` (16-bit millimetres, from ``keyframe_depths()``).

Failure handling: tracking failures are reported by the frontend (``pose_source == "motion_model"``)
and counted; corrupt frames are skipped by the dataset and counted; a non-finite pose from the
frontend is dropped and counted. If the frontend (or the dataset) raises mid-run, everything that
exists is written first (partial trajectory from the frontend, else from the per-frame live
estimates, and a summary with the error), then a :class:`RunError` (or the dataset's own
:class:`~fgslam.core.errors.DataError`) is raised.

Stopping: SIGINT (Ctrl-C) and SIGTERM (batch schedulers, ``timeout``) stop the loop at once; the
partial outputs and a summary naming the signal are written, ``on_summary`` reports it, then
:class:`~fgslam.core.errors.Interrupted` is raised (``exit_code`` 130 / 143). A further signal (a second
Ctrl-C) arriving while the outputs are written and reported is logged ("stopping: writing outputs,
please wait") and ignored: they are completed. The handlers are installed only for the duration of
the run and the previous ones are restored.

No result: a run that ends without a pose for any frame writes its summary with the reason as its
``error`` (:func:`fgslam.run.results.no_pose_reason`) and raises :class:`NoPoseError`.

Previous outputs: an ``out_dir`` that holds a previous run's outputs
(:data:`fgslam.run.files.RUN_OUTPUT_FILES`, ``depth/``) is refused unless ``overwrite``, which
removes them when the run starts (its system built: a run refused before that leaves them).

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
import resource
import signal
import sys
import time
from pathlib import Path
from typing import Callable, Optional

from tqdm import tqdm

from ..core.config import MS_PER_S
from ..core.errors import DataError, FGSlamError, Interrupted
from ..frontends.base import Frontend
from ..io.datasets import Dataset
from ..io.live import LiveConfig, LiveFrames, ReadAhead
from ..io.trajectory import Trajectory
from .config import SlamConfig
from .mapstore import store_map
from .outputs import (OutputWriter, write_keyframe_depths, write_map, write_plot, write_points, write_summary,
                      write_trajectories)
from .prepare import PreparedRun, prepare_opened, remove_created_folder, remove_previous_outputs
from .results import ErrorAt, RunSummary, collect_results, outputs_text, summarize
from .session import Slam
from .signals import StopOnSignal

logger = logging.getLogger(__name__)

_WHERE_DATASET = "while reading the dataset"  # error location of a failure inside the dataset iterator


class RunError(FGSlamError):
    """A run stopped because the frontend raised; partial outputs were written before."""


class OutputError(FGSlamError):
    """An output of a run could not be written (the others and, when possible, summary.json were)."""


class NoPoseError(FGSlamError):
    """A run that ended without a pose for any frame: no result (summary.json says why)."""


# ----------------------------------------------------------------------------------------- the run


class _Progress:
    """A progress bar (tqdm) on stderr when it is a terminal, else progress lines on the module
    logger at most every ``every_frames`` frames or ``every_s`` s."""

    def __init__(self, total: int, every_frames: int, every_s: float, enabled: bool) -> None:
        self.total, self.every_frames, self.every_s, self.enabled = total, every_frames, every_s, enabled
        self.t0 = time.perf_counter()
        self.last_t, self.last_n = self.t0, 0
        self.bar = _progress_bar(total, "frames") if enabled else None
        self.live: Optional[tuple[float, int]] = None  # live runs: the last result's latency (s) and the drops so far

    def update(self, n: int, keyframes: int, failures: int, force: bool = False) -> None:
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(n - self.bar.n)
            live = {} if self.live is None else {"latency_ms": f"{MS_PER_S * self.live[0]:.0f}", "dropped": self.live[1]}
            self.bar.set_postfix(keyframes=keyframes, failures=failures, **live, refresh=False)
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
        live = "" if self.live is None else f"  latency {MS_PER_S * self.live[0]:.0f} ms  {self.live[1]} dropped"
        logger.info(
            "frame %d/%d (%.0f%%)  %.1f frames/s  %d keyframes  %d failures  ETA %s%s",
            n, self.total, 100.0 * n / max(self.total, 1), fps, keyframes, failures, eta_txt, live,
        )


def _progress_bar(total: int, unit: str) -> Optional[tqdm]:
    """A tqdm bar on stderr when stderr is a terminal (None otherwise: log lines instead)."""
    if not (hasattr(sys.stderr, "isatty") and sys.stderr.isatty()):
        return None
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
    """Run SLAM over ``dataset`` with ``config`` and write the outputs into ``out_dir``: the run is
    prepared (:func:`fgslam.run.prepare.prepare_opened`: every check before any work) and run
    (:func:`run_prepared`).

    Args:
        dataset: an opened dataset (see :func:`fgslam.run.prepare.open_slam_dataset`); checked against ``config``.
        config: the run configuration.
        out_dir: output folder (created; checked writable and outside the dataset before any work).
        progress: log a progress line every ``config.log_interval_frames`` frames / ``log_interval_s`` s.
        frontend: use this frontend instead of building ``config.frontend`` (tests, custom frontends).
        on_summary: called with the summary once the outputs are written, also when the run then
            raises (the command line prints its report there).
        rerun: log the run to rerun: a ``.rrd`` file, or ``live`` for a running viewer
            (:mod:`fgslam.export.rerun`; the rerun SDK is an optional extra).
        overwrite: replace the outputs of a previous run in ``out_dir`` (removed once the run's system
            is built, as the run starts: a refused run leaves them); without it such a folder is a
            ConfigError (:func:`fgslam.run.prepare.check_previous_outputs`).

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
    run = prepare_opened(dataset, config, out_dir, overwrite=overwrite, rerun=rerun)
    return run_prepared(run, progress=progress, frontend=frontend, on_summary=on_summary)


def run_prepared(run: PreparedRun, progress: bool = True, frontend: Optional[Frontend] = None,
                 on_summary: Optional[Callable[[RunSummary], None]] = None) -> RunSummary:
    """Run SLAM on a prepared run (:mod:`fgslam.run.prepare`: its inputs are trusted) and write the
    outputs into ``run.out``; the arguments, the result and the errors raised are :func:`run_slam`'s."""
    dataset, config, out = run.dataset, run.config, run.out
    # the per-frame path of a script (fgslam.Slam): the same object, fed the dataset's frames
    try:
        slam = Slam(config, dataset.calibration, frontend=frontend, timestamps=dataset.timestamps,
                    has_imu=dataset.has_imu, imu_noise=dataset.imu_noise, where=str(dataset.root), rerun=run.rerun,
                    keep_frames=False)
    except BaseException:  # refused before any output (e.g. a frontend that cannot be built): the previous run's
        remove_created_folder(run.created)  # outputs are still there, and no folder is left behind
        raise
    if run.overwrite:  # the run can start: a previous run's outputs go now, never for a refused run
        try:
            remove_previous_outputs(out)
        except BaseException:
            _abort(slam)
            raise
    slam.system.imu_input_warnings = list(run.imu_warnings)
    state = slam.state
    gt = dataset.groundtruth  # loaded (and cached by the dataset) before the timed loop
    with StopOnSignal((signal.SIGTERM, signal.SIGINT)) as stopper:
        t_start, cpu_start = time.perf_counter(), _cpu_seconds()
        saved_threads = _set_threads(config.threads)
        try:
            error = _loop(dataset, slam, config, progress, run.live)
            if error is not None:
                _abort(slam)
        finally:
            stopper.finishing = True  # from here on a signal is logged and the outputs and report are completed
            _restore_threads(saved_threads)
        state.wall_s, state.cpu_s = time.perf_counter() - t_start, _cpu_seconds() - cpu_start
        summary, error = _write_outputs(run, slam, gt, error)
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


def _write_outputs(run: PreparedRun, slam: Slam, gt: Optional[Trajectory],
                   error: Optional[ErrorAt]) -> tuple[RunSummary, Optional[ErrorAt]]:
    """Once the loop stopped (with ``error``, the loop's, or None): the results collected, then the
    outputs written, each on its own (a failing one is recorded in ``output_errors`` and never stops
    the others), ``summary.json`` last. Returns the summary and the first error (the loop's, or one
    raised by the frontend's end-of-run queries, which never prevents the writing)."""
    config, system, state = run.config, slam.system, slam.state
    frontend = system.frontend
    results = slam.final_results(error, gt)
    writer = OutputWriter(run.out)
    traj = results.traj
    if traj is not None:  # first: a run killed in its end-of-run work keeps its trajectory
        write_trajectories(writer, traj)
    collect_results(run, system, results)
    if results.points is not None:
        write_points(writer, results.points, traj, config.output.ply)
    if config.output.write_depth:
        write_keyframe_depths(writer, frontend, results.notes)
    if config.output.write_map and traj is not None:  # no pose, no map (and no note that would blame the frontend)
        write_map(writer, run.dataset, frontend, config.sensor, state, results.notes)
    if (config.output.save_map or config.output.extend_map) and traj is not None:
        store_map(writer, run, frontend, state, results)
    if config.output.plot and traj is not None:
        write_plot(writer, gt, traj, results.eval_result, config)
    summary = summarize(run, state, results, writer.written, writer.errors)
    write_summary(writer, summary)
    return summary, results.first_error


def _abort(slam: Slam) -> None:
    """Stop the run's background work without waiting for it (a stopped or failed run); a failure
    there is logged, never raised: the outputs are written next."""
    try:
        slam.abort()
    except (Exception, KeyboardInterrupt):  # noqa: BLE001 - the run's own outcome is reported
        logger.exception("stopping the background work failed")


def _loop(dataset: Dataset, slam: Slam, config: SlamConfig, progress: bool,
          live_config: Optional[LiveConfig] = None) -> Optional[ErrorAt]:
    """Iterate the dataset through the run's :class:`~fgslam.run.session.Slam` (the system's frame skeleton);
    returns ``(exception, where)`` instead of raising (an exception anywhere, an interrupt included, stops
    the loop and is returned with its place). Live (``live_config``): the frames come through
    :class:`~fgslam.io.live.LiveFrames` at their own pace; each result's latency and the drops are recorded.
    Otherwise a reader thread decodes the next frame while this one is tracked (:class:`~fgslam.io.live.ReadAhead`)."""
    state, system = slam.state, slam.system
    meter = _Progress(len(dataset), config.log_interval_frames, config.log_interval_s, progress)
    live = None if live_config is None else LiveFrames(dataset, live_config)
    reader = ReadAhead(dataset) if live is None else live
    frames = iter(reader)
    where = _WHERE_DATASET
    stop: Optional[ErrorAt] = None
    try:
        while True:
            where = _WHERE_DATASET
            t0 = time.perf_counter()
            try:
                frame = next(frames)
            except StopIteration:
                break
            state.read_s += time.perf_counter() - t0
            state.frames_read += 1
            state.frame_paths[frame.index] = "" if frame.path is None else str(frame.path)
            where = f"at frame {frame.index}" + (f" ({frame.path})" if frame.path is not None else "")
            slam.track_frame(frame)  # counts its time (also when it raises), the frame and its status
            where = f"after frame {frame.index}"
            if live is not None:
                state.latency_s.append(time.perf_counter() - live.arrival_s[frame.index])
                state.live_dropped = live.dropped
                meter.live = (state.latency_s[-1], live.dropped)
            meter.update(state.frames_processed, system.frontend.num_keyframes(), len(state.failure_frames))
        where = "in finish() after the last frame"
        slam.finish_run()  # counts its own time
        meter.update(state.frames_processed, system.frontend.num_keyframes(), len(state.failure_frames), force=True)
    except (Exception, KeyboardInterrupt) as exc:  # noqa: BLE001 - reported with partial outputs
        stop = (exc, where)
    finally:
        try:
            reader.close()  # the frames' iterator closed it already unless the loop stopped early
        except KeyboardInterrupt as exc:  # a stop signal while the reader ends: reported as one in the loop
            stop = stop or (exc, where)
        state.read_cpu_s = reader.cpu_s
        if live is not None:
            state.live_dropped = live.dropped
    return stop


# ----------------------------------------------------------------------------------------- threads


def _set_threads(threads: int) -> Optional[tuple[int, int]]:
    if threads <= 0:
        return None
    import cv2  # deferred: cv2
    import torch  # deferred: torch

    saved = (torch.get_num_threads(), cv2.getNumThreads())
    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    return saved


def _restore_threads(saved: Optional[tuple[int, int]]) -> None:
    if saved is None:
        return
    import cv2  # deferred: cv2
    import torch  # deferred: torch

    torch.set_num_threads(saved[0])
    cv2.setNumThreads(saved[1])
