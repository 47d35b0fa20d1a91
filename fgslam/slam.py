"""The SLAM runner: a dataset in, a frontend in the middle, trajectories, a summary and a plot out.

``SlamConfig`` is the root configuration of a run (``fgslam/configs/patch_*.yaml`` are presets of it);
:func:`run_slam` drives any :class:`~fgslam.frontends.base.Frontend` over a
:class:`~fgslam.io.datasets.Dataset` and writes, in ``out_dir``:

- ``trajectory_tum.txt``: ``t tx ty tz qx qy qz qw`` per frame with a pose (camera-to-world ``T_WC``
  in the estimate's world frame; monocular translations are in the map's arbitrary scale);
- ``trajectory_kitti.txt`` + ``trajectory_kitti_times.txt``: the same poses as 3x4 rows and their
  timestamps (seconds);
- ``summary.json``: frame counts, keyframes, frames/s overall and per stage, failures by kind,
  skipped frames, the estimate's motion extent, evaluation (ATE with the alignment used, RPE, % of
  path length) when the dataset has ground truth, loop closure counts (``loop``, when the frontend
  runs loop closure: ``Frontend.loop_summary()``), the full configuration used, the error when
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

import json
import logging
import math
import os
import re
import resource
import shutil
import signal
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Literal, Optional

import numpy as np

from .backend.config import BackendConfig
from .services.imu_samples import ImuServiceConfig
from .config import MAX_FRAMES, MAX_MEMORY_MIB, MAX_SCALAR, MAX_THREADS, check_ranges, ranged, to_dict, with_sections
from .errors import ConfigError, DataError, EvaluationError, FGSlamError, Interrupted
from .eval import EvalConfig, EvalResult, evaluate
from .export.rerun import RerunConfig
from .frontends import FRONTEND_NAMES, family_config_classes
from .frontends.base import FrameStatus, Frontend
from .system import SlamSystem
from .io.datasets import Dataset, DatasetConfig, open_dataset
from .io.trajectory import Trajectory, write_trajectory
from .loop.records import LoopClosureConfig
from .memory import check_run_memory

logger = logging.getLogger(__name__)

SensorName = Literal["mono", "stereo", "rgbd"]

# Output file names (stable: tools and tests read them).
TUM_FILE = "trajectory_tum.txt"
KITTI_FILE = "trajectory_kitti.txt"
KITTI_TIMES_FILE = "trajectory_kitti_times.txt"
SUMMARY_FILE = "summary.json"
PLOT_FILE = "trajectory.png"
PLY_FILE = "points.ply"
MAP_FILE = "map.npz"  # fgslam.export.map.MAP_FILE
DEPTH_DIR = "depth"  # depth/<kf:06d>.png per keyframe (output.write_depth)
#: What a run writes into its output folder (a previous run's outputs: refused, or removed with overwrite).
RUN_OUTPUT_FILES = (TUM_FILE, KITTI_FILE, KITTI_TIMES_FILE, SUMMARY_FILE, SUMMARY_FILE + ".tmp", PLOT_FILE, PLY_FILE,
                    MAP_FILE)
#: Images with a side above this many pixels are named as the likely reason when no frame got a
#: pose (the frontends are tuned for VGA to KITTI-width images; resize with dataset.resize_width).
LARGE_IMAGE_SIDE = 4096
SUGGESTED_RESIZE_WIDTH = 640  # the dataset.resize_width that hint suggests (VGA width)

BYTES_PER_KIB = 1024  # ru_maxrss is in KiB on Linux
BYTES_PER_MIB = 1024 * 1024
MAX_LOGGED_FAILURES = 10  # tracking failures logged one by one before switching to the progress lines
_WHERE_DATASET = "while reading the dataset"  # error location of a failure inside the dataset iterator


class RunError(FGSlamError):
    """A run stopped because the frontend raised; partial outputs were written before."""


class OutputError(FGSlamError):
    """An output of a run could not be written (the others and, when possible, summary.json were)."""


class NoPoseError(FGSlamError):
    """A run that ended without a pose for any frame: no result (summary.json says why)."""


@dataclass
class OutputConfig:
    """What a run writes besides trajectories and summary."""

    plot: bool = True  # write trajectory.png (top view of estimate vs ground truth)
    # plot plane; auto: the two axes of largest ground-truth (else estimate) extent
    plot_plane: Literal["auto", "xy", "xz", "yz"] = "auto"
    write_ply: bool = False  # write points.ply from the frontend's keyframe points (when it provides them)
    write_depth: bool = False  # write depth/<kf:06d>.png per keyframe (16-bit, millimetres; frontends with keyframe_depths(): dense)
    write_map: bool = True  # write map.npz (keyframes, points, tracks, calibration, frames) for `fgslam export`
    rerun: RerunConfig = field(default_factory=RerunConfig)  # what `fgslam run --rerun out.rrd` logs (fgslam/export/rerun.py)


@dataclass
@with_sections(family_config_classes, after="dataset")
class SlamConfig:
    """Root configuration of ``fgslam run`` (presets: ``fgslam/configs/patch_*.yaml``).

    Besides the fields below it has one section per frontend family that has a config class, named
    after the family and placed after ``dataset`` (``patch: PatchConfig``): they come from the
    registry :data:`fgslam.frontends.FAMILIES`, so a new family needs no edit here."""

    frontend: Literal[FRONTEND_NAMES] = "patch"  # frontend family: patch, dense or pointmap
    sensor: SensorName = "mono"  # mono | stereo (needs right images) | rgbd (needs depth)
    threads: int = ranged(0, ge=0, le=MAX_THREADS)  # torch and OpenCV threads for the run (0: leave the library defaults); stages may set their own
    log_interval_frames: int = ranged(100, ge=1, le=MAX_FRAMES)  # a progress line at least every this many frames
    log_interval_s: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # ... or every this many seconds, whichever comes first
    auto_align: bool = True  # evaluation alignment from the sensor (sim3 mono, se3 stereo/rgbd); false: eval.align
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    # (here: one section per frontend family, e.g. patch: PatchConfig, from the frontend registry)
    map: BackendConfig = field(default_factory=BackendConfig)  # the run's backend (fgslam/backend)
    imu: ImuServiceConfig = field(default_factory=ImuServiceConfig)  # IMU fusion (fgslam/services/imu.py; inertial presets)
    eval: EvalConfig = field(default_factory=EvalConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    # loop closure (mode off | proximity | classical | both); off by default
    loop_closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    max_memory_gib: float = ranged(16.0, gt=0, le=MAX_MEMORY_MIB / 1024)  # a run whose estimated peak memory (fgslam/memory.py) exceeds this is refused before any work
    # user factor plugins, [{class: "package.module:ClassName", options: {...}}] (fgslam/services/plugins.py)
    factors: list[dict[str, Any]] = field(default_factory=list)

    def validate(self) -> None:
        from .services.plugins import validate_factor_entries

        self.loop_closure.validate()
        validate_factor_entries(self.factors)

    def family_section(self, name: str | None = None) -> Any:
        """The config section of frontend family ``name`` (default: ``frontend``); None for a family
        without one (planned families)."""
        return getattr(self, name or self.frontend, None)

    def alignment(self) -> str:
        """Alignment used for the ATE: the sensor's (auto) or ``eval.align``."""
        if not self.auto_align:
            return self.eval.align
        return "sim3" if self.sensor == "mono" else "se3"


# ----------------------------------------------------------------------------------------- dataset side


def dataset_config_for(config: SlamConfig) -> DatasetConfig:
    """``config.dataset`` with only the streams the run needs switched on (right images for stereo,
    depth for RGB-D, colour only for PLY colours); a stream the config switched off stays off."""
    ds = config.dataset
    return replace(
        ds,
        load_right=ds.load_right and config.sensor == "stereo",
        load_depth=ds.load_depth and config.sensor == "rgbd",
        load_rgb=ds.load_rgb and config.output.write_ply,
    )


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


@dataclass
class _RunState:
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
    system = SlamSystem.build(config, dataset.calibration, frontend=frontend, timestamps=dataset.timestamps,
                              has_imu=dataset.has_imu, imu_noise=getattr(dataset, "imu_noise", None),
                              where=str(dataset.root), rerun=rerun)
    load_average = [round(v, 2) for v in os.getloadavg()]
    gt = dataset.groundtruth  # loaded (and cached by the dataset) before the timed loop
    state = _RunState()
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
        summary, error = _finalize(dataset, gt, system, config, state, out, load_average, error)
        if on_summary is not None:  # still under the handlers: a second Ctrl-C never cuts the report
            try:
                on_summary(summary)
            except Exception:  # noqa: BLE001 - a failing report (closed pipe...) never hides the run's own outcome
                logger.exception("reporting the run summary failed")
    written = _outputs_text(out, summary)
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


def _outputs_text(out: Path, summary: RunSummary) -> str:
    """Where the outputs went, and which could not be written (for error messages)."""
    errors = summary.output_errors
    if not errors:
        return f"partial outputs written to {out}, see {SUMMARY_FILE}" if summary.error else f"outputs in {out}"
    failed = "; ".join(f"{kind}: {why}" for kind, why in errors.items())
    kept = ", ".join(sorted(summary.outputs)) or "none"
    see = "" if "summary" in errors else f", see {SUMMARY_FILE}"
    return f"could not write {len(errors)} output(s) in {out} ({failed}); written: {kept}{see}"


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
    dataset: Dataset, system: SlamSystem, config: SlamConfig, state: _RunState, progress: bool
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


def _record(status: FrameStatus, timestamp: float, state: _RunState) -> None:
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


def _final_trajectory(
    frontend: Frontend, state: _RunState, notes: list[str], errors: list[tuple[BaseException, str]]
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


def _finalize(
    dataset: Dataset,
    gt: Optional[Trajectory],
    system: SlamSystem,
    config: SlamConfig,
    state: _RunState,
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
    loop = None
    points = None
    try:
        stage_s = {k: float(v) for k, v in system.stage_times().items()}
        keyframes = int(frontend.num_keyframes())
        loop = system.loop_summary()
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
        interrupted=interrupted,
        output_errors=output_errors,
    )
    if not _write_output("summary", [out / SUMMARY_FILE], lambda: _write_summary(out / SUMMARY_FILE, summary),
                         outputs, output_errors):
        logger.error("%s could not be written; the run summary is only on the console", out / SUMMARY_FILE)
    return summary, first_error


def no_pose_reason(dataset: Dataset, config: SlamConfig, state: _RunState) -> str:
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


def _write_map(path: Path, dataset: Dataset, frontend: Frontend, config: SlamConfig, state: _RunState,
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
        plane = _auto_plane(gt if gt is not None else est)
    if result is not None:
        title = (f"{config.frontend} {config.sensor}: ATE {result.ate.rmse:.3f} m "
                 f"({result.align}, {result.n_matched} poses)")
    else:
        title = f"{config.frontend} {config.sensor}: estimate ({len(traj)} poses, no ground truth)"
    errors = None if result is None else {"estimate": pose_errors(result.matched_gt, result.aligned_est)}
    return plot_trajectories(path, gt, est, title=title, plane=plane, errors=errors)


def _auto_plane(traj: Trajectory) -> str:
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


def load_slam_config(name_or_path: str | Path | None, overrides: list[str] | tuple[str, ...] = ()) -> SlamConfig:
    """SlamConfig from a YAML path or preset name (None: defaults) with ``key=value`` overrides."""
    from .config import load_config
    from .presets import resolve_preset

    path = None if name_or_path is None else resolve_preset(name_or_path)
    return load_config(SlamConfig, path, overrides)
