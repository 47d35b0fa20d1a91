"""The per-frame path of every run: :class:`Slam`, the public object a script drives one frame at a time
(``import fgslam``), and the object the runner (``fgslam run``) steps over a dataset, so that a script
and the command line go the same way and give the same bytes.

A :class:`Slam` holds the run's :class:`~fgslam.run.system.SlamSystem` (backend, frontend, services)
and the record of the frames it saw (:class:`~fgslam.run.results.RunState`). :meth:`Slam.track` takes
an image as the camera gave it (undistorted, rectified and resized here with the config's
``dataset.*`` keys, as a loader does) and :meth:`Slam.track_frame` a frame a loader made; both return
a :class:`TrackResult`. The final trajectory (:meth:`Slam.finish`) is the frontend's, after its last
optimisation, the same one ``fgslam run`` writes.

Frames and units: ``T_WC`` is the 4x4 camera-to-world transform of the (output) left camera, metres
(monocular runs: the map's own scale); times are seconds.
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Callable, Mapping, Optional, Sequence

import numpy as np

from ..core.errors import ConfigError, DataError
from ..core.tracking import Keyframes, TrackResult
from ..frontends.base import FrameStatus, Frontend
from ..io.calibration import Calibration
from ..io.camera import Camera
from ..io.datasets import Dataset
from ..io.datasets.common import clean_depth, make_undistorter
from ..io.datasets.files import to_grey_and_rgb
from ..io.frame import Frame, ImuSamples
from ..io.trajectory import Trajectory
from ..localize.localizer import LocalizeConfig, Localizer
from .config import SlamConfig, load_slam_config
from .prepare import check_config, check_output_size, open_slam_dataset
from .results import RunResults, RunState, final_trajectory
from .system import SlamSystem

logger = logging.getLogger(__name__)

#: the reason given with a frame that has no pose, or a pose that is a prediction
_REASONS = {
    "initializing": "initialising: waiting for enough parallax or measurements to start the map",
    "motion_model": "tracking failed: the pose is the motion model's prediction",
    "imu": "visual tracking failed: the pose is the IMU's prediction",
}
#: frames whose images are kept for :meth:`Slam.save_map` besides the current keyframes' (the newest ones,
#: which may still become keyframes); the memory is pruned to the keyframes every this many frames
KEPT_RECENT_FRAMES = 64


@dataclass
class _KeptFrames:
    """The frames a stored map re-reads (``build_stored_map``): a dataset-like view (positions 0..n-1) of
    the keyframes' frames and the newest ones, pruned every ``KEPT_RECENT_FRAMES`` frames to the frames
    whose times are keyframe times (``keyframe_times``: None keeps every frame)."""

    calibration: Calibration
    keyframe_times: Optional[Callable[[], set[float]]]
    frames: list[Frame] = field(default_factory=list)
    added: int = 0

    @property
    def timestamps(self) -> np.ndarray:
        return np.array([f.timestamp for f in self.frames], dtype=np.float64)

    def __getitem__(self, position: int) -> Frame:
        return self.frames[int(position)]

    def __len__(self) -> int:
        return len(self.frames)

    def add(self, frame: Frame) -> None:
        """Keep a copy of the frame's grey image and depth (a caller may reuse its buffers)."""
        self.frames.append(Frame(frame.index, frame.source_index, frame.timestamp, frame.image.copy(),
                                 frame.calibration, depth=None if frame.depth is None else frame.depth.copy()))
        self.added += 1
        if self.keyframe_times is None or self.added % KEPT_RECENT_FRAMES:
            return
        keep = self.keyframe_times()
        newest = len(self.frames) - KEPT_RECENT_FRAMES
        self.frames = [f for k, f in enumerate(self.frames) if k >= newest or f.timestamp in keep]

    def indices(self) -> np.ndarray:
        return np.arange(len(self.frames), dtype=np.int64)


def _override_strings(overrides: Mapping[str, Any] | Sequence[str] | None) -> list[str]:
    """``{"dataset.end": 100}`` or ``["dataset.end=100"]`` as the command line's ``key=value`` texts."""
    if overrides is None:
        return []
    if isinstance(overrides, Mapping):
        return [f"{key}={json.dumps(value)}" for key, value in overrides.items()]
    return [str(o) for o in overrides]


class Slam:
    """One SLAM run driven frame by frame (module docstring).

    Args:
        config: the run configuration (:meth:`from_preset`, :meth:`from_config`).
        camera: the camera of the images given to :meth:`track` (a :class:`~fgslam.io.camera.Camera`;
            ``camera.prepared`` for frames a loader made).
        imu_noise: IMU noise densities (EuRoC ``sensor.yaml`` keys), used where the config's
            ``imu.*_noise_density`` and ``imu.*_random_walk`` keys are unset.
        has_imu: IMU samples will come (:meth:`add_imu`; default: ``imu.enabled`` of the config).
        timestamps: the run's frame times when known ahead (factor plugins check them; None: unknown).
        frontend: a frontend built by hand instead of the config's family (tests, custom frontends).
        rerun: log the run to rerun (a ``.rrd`` file, or ``live``); needs ``fgslam[rerun]``.
        keep_frames: keep the keyframes' images (and the newest frames') for :meth:`save_map` (the command
            line re-reads its dataset instead).
        where: what the frames come from, named in errors.

    Raises:
        ConfigError: a config value is out of range, the images would be too small or too large, or the
            sensor needs what the camera lacks.
        DataError: the camera's calibration is invalid.
    """

    def __init__(self, config: SlamConfig, camera: Camera | Calibration, *, imu_noise: Optional[dict] = None,
                 has_imu: Optional[bool] = None, timestamps: Optional[np.ndarray] = None,
                 frontend: Optional[Frontend] = None, rerun: Optional[str] = None, keep_frames: bool = True,
                 where: str = "fgslam.Slam") -> None:
        check_config(config)
        self.config = config
        prepared = isinstance(camera, Calibration) or camera.prepared
        raw = camera if isinstance(camera, Calibration) else camera.calibration()
        self._undistorter = None if prepared else make_undistorter(raw, config.dataset, where)
        self.calibration: Calibration = raw if self._undistorter is None else self._undistorter.calibration
        if not prepared:
            check_output_size(config.dataset, self.calibration, raw)
        if config.sensor == "stereo" and self.calibration.right is None:
            raise ConfigError("sensor 'stereo' needs a stereo camera: give the camera a baseline, or right and T_CLCR")
        self.system = SlamSystem.build(config, self.calibration, frontend=frontend, timestamps=timestamps,
                                       has_imu=config.imu.enabled if has_imu is None else has_imu,
                                       imu_noise=imu_noise, where=where, rerun=rerun)
        if self.system.frontend.uses_compiled_kernels:
            from ..core.jit import warm_up  # deferred: numba

            try:
                warm_up()
            except BaseException:  # Ctrl-C (or a broken numba) while loading: the built system stops too
                self.system.abort()
                raise
        self.state = RunState(load_average=[round(v, 2) for v in os.getloadavg()])
        backend = self.system.backend
        kf_times = None if backend is None else lambda: {backend.timestamp(k) for k in backend.keyframe_ids}
        self._kept = _KeptFrames(self.calibration, kf_times) if keep_frames else None
        self._imu: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._t_last: Optional[float] = None
        self._finished = False  # finish_run() ran to its end, or abort() stopped the run
        self._aborted = False  # abort() stopped it, or finishing failed: only the live estimates are valid
        self._results: Optional[RunResults] = None

    # ------------------------------------------------------------------ building
    @classmethod
    def from_preset(cls, name: str | Path, camera: Camera, overrides: Mapping[str, Any] | Sequence[str] | None = None,
                    **kwargs: Any) -> "Slam":
        """A run of a preset (``fgslam run``'s CONFIG: a name such as ``handheld_rgbd`` or a YAML file) with
        ``overrides`` (``{"patch.ba.iterations": 3}`` or ``["patch.ba.iterations=3"]``); ``kwargs``: :class:`Slam`'s.

        Raises:
            ConfigError: an unknown preset, key or value (naming it).
        """
        return cls(load_slam_config(name, _override_strings(overrides)), camera, **kwargs)

    from_config = from_preset  # a YAML file is a preset of its own

    @staticmethod
    def localize_in(map_path: str | Path, overrides: Mapping[str, Any] | Sequence[str] | None = None) -> Localizer:
        """A :class:`~fgslam.localize.localizer.Localizer` in the stored map ``map_path`` (``overrides``: keys of
        ``fgslam localize``'s config, ``fgslam/configs/localize.yaml``). Raises DataError for a missing or
        damaged map, ConfigError for a bad key."""
        from ..core.config import load_config

        return Localizer.open(map_path, load_config(LocalizeConfig, None, _override_strings(overrides)))

    # ------------------------------------------------------------------ frames in
    def add_imu(self, t: float, accel: Sequence[float], gyro: Sequence[float]) -> None:
        """One IMU sample at time ``t`` (seconds, the camera's clock): specific force ``accel`` (m/s^2) and
        angular rate ``gyro`` (rad/s), in the IMU (body) frame; it goes with the first frame at or after ``t``.

        Raises:
            ConfigError: the run has no IMU service (a config without ``imu.enabled``: use an inertial preset).
        """
        if self.system.imu is None:
            raise ConfigError("add_imu: this run has no IMU service (imu.enabled is false): use an inertial preset")
        self._imu.append((float(t), np.asarray(accel, dtype=np.float64).reshape(3),
                          np.asarray(gyro, dtype=np.float64).reshape(3)))

    def track(self, image: np.ndarray, t: float, depth: Optional[np.ndarray] = None,
              right: Optional[np.ndarray] = None) -> TrackResult:
        """Track one frame.

        Args:
            image: the left image as the camera gave it: grey ``(H, W)`` uint8, or colour ``(H, W, 3)`` uint8
                in OpenCV's BGR order.
            t: its time in seconds (increasing).
            depth: RGB-D: ``(H, W)`` depth in metres (0, NaN or negative: no depth), aligned with ``image``.
            right: stereo: the right image, as ``image``.

        Raises:
            DataError: an image of the wrong size, a time not after the previous frame's.
        """
        t = float(t)
        if self._t_last is not None and not t > self._t_last:
            raise DataError(f"frame time {t} is not after the previous frame's ({self._t_last})")
        calib = self.calibration if self._undistorter is None else self._undistorter.raw
        grey, rgb = self._image(image, calib, "image")
        frame = Frame(index=self.state.frames_processed, source_index=self.state.frames_processed, timestamp=t,
                      image=grey, calibration=self.calibration, rgb=rgb if self.config.needs_colour() else None)
        if right is not None:
            frame.image_right = self._image(right, calib.right or calib, "right")[0]
        if depth is not None:
            depth = np.asarray(depth)
            if depth.ndim != 2:
                raise DataError(f"depth: expected one channel (H, W), got shape {depth.shape}")
            calib.check_image_size(depth.shape[1], depth.shape[0], "depth")
            depth = clean_depth(depth)
        und = self._undistorter
        if und is not None:
            frame.image = und.left(frame.image)
            frame.rgb = None if frame.rgb is None else und.left(frame.rgb)
            frame.image_right = None if frame.image_right is None else und.right(frame.image_right)
            depth = None if depth is None else und.depth(depth)
        frame.depth = depth
        return self.track_frame(frame)

    @staticmethod
    def _image(image: np.ndarray, calib: Calibration, what: str) -> tuple[np.ndarray, Optional[np.ndarray]]:
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.ndim not in (2, 3):
            raise DataError(f"{what}: expected a uint8 (H, W) or (H, W, 3) image, got {image.dtype} {image.shape}")
        calib.check_image_size(image.shape[1], image.shape[0], what)
        return to_grey_and_rgb(image, image.ndim == 3, None)

    def track_frame(self, frame: Frame) -> TrackResult:
        """Track a frame a loader made (:func:`open_dataset`; its ``imu`` as the loader gives it, else the
        samples of :meth:`add_imu` since the previous frame)."""
        if self._finished or self._aborted:
            raise ConfigError("this Slam has finished: build a new one for another run")
        if frame.imu is None and self.system.imu is not None:
            frame.imu = self._imu_block(frame.timestamp)
        state = self.state
        t0 = time.perf_counter()
        try:
            status = self.system.step(frame)
        finally:  # counted also when the frame raises
            process_s = time.perf_counter() - t0
            state.frontend_s += process_s
            state.max_frame_s = max(state.max_frame_s, process_s)
        state.frames_processed += 1
        self._t_last = frame.timestamp
        T_WC = _record(status, frame.timestamp, state)
        if self._kept is not None:
            self._kept.add(frame)
        reason = _REASONS.get(status.pose_source) if T_WC is not None or status.pose_source != "tracked" else \
            "the frontend returned a non-finite pose"
        if T_WC is None and reason is None:
            reason = "no pose"
        return TrackResult(frame.index, frame.timestamp, T_WC, status.pose_source, bool(status.is_keyframe),
                           int(status.num_valid), reason, tuple(status.events), process_s, new_map=bool(status.new_map))

    def _imu_block(self, t: float) -> ImuSamples:
        """The samples of :meth:`add_imu` with ``t_prev < t_i <= t`` (the first frame: none, as a loader's)."""
        first = self._t_last is None
        take = [s for s in self._imu if s[0] <= t]
        self._imu = [s for s in self._imu if s[0] > t]
        if first or not take:
            return ImuSamples(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
        return ImuSamples(np.array([s[0] for s in take]), np.array([s[2] for s in take]),
                          np.array([s[1] for s in take]))

    # ------------------------------------------------------------------ the end
    def finish(self) -> Trajectory:
        """The last optimisation, background work joined; returns the final trajectory (the one
        ``fgslam run`` writes). Calling it again returns the same trajectory.

        Raises:
            DataError: no frame got a pose.
            ConfigError: the run was aborted, or failed while finishing (:meth:`trajectory` has the live
                estimates).
        """
        if self._aborted:
            raise ConfigError("this run was aborted or failed while finishing: no final trajectory "
                              "(trajectory() has the per-frame estimates)")
        self.finish_run()
        traj = self.final_results().traj
        if traj is None:
            raise DataError(f"no pose for any of the {self.state.frames_processed} frames: no trajectory")
        return traj

    def finish_run(self) -> None:
        """The end of the run without asking for its trajectory (the runner collects it with the outputs):
        the system's last optimisation and background work joined, once; its time is counted."""
        if self._finished:
            return
        t0 = time.perf_counter()
        try:
            self.system.finish()
        except BaseException:
            self._aborted = True
            try:  # the background work stops now (a script may not call abort(); calling it again is harmless)
                self.system.abort()
            except Exception:  # noqa: BLE001 - the finishing error is the one raised
                logger.exception("stopping the background work after a failed finish failed")
            raise
        finally:
            self.state.frontend_s += time.perf_counter() - t0
        self._finished = True

    def final_results(self, error: Optional[tuple[BaseException, str]] = None,
                      gt: Optional[Trajectory] = None) -> RunResults:
        """The run's results once it stopped (its final trajectory first; computed once)."""
        if self._results is None:
            self._results = final_trajectory(self.system, self.state, gt, error)
        return self._results

    def abort(self) -> None:
        """Stop the background work at once without applying it (a stopped or failed run); the per-frame
        estimates stay (:meth:`trajectory`)."""
        self._finished = self._aborted = True
        self.system.abort()

    def __enter__(self) -> "Slam":
        return self

    def __exit__(self, exc_type: Optional[type[BaseException]], exc: Optional[BaseException],
                 tb: Optional[TracebackType]) -> None:
        if exc_type is None:
            self.finish_run()
        elif not self._finished or self._aborted:
            self.abort()

    # ------------------------------------------------------------------ what it knows
    def trajectory(self) -> Trajectory:
        """The poses so far: the final trajectory once finished, else (also after :meth:`abort`) every frame's
        live estimate (``timestamps (N,)`` seconds, ``T_WC (N, 4, 4)`` camera-to-world). DataError: finished
        without a pose for any frame."""
        if self._finished and not self._aborted:
            return self.finish()
        s = self.state
        return Trajectory(np.asarray(s.live_t, dtype=np.float64), np.asarray(s.live_T, dtype=np.float64).reshape(-1, 4, 4))

    def keyframes(self) -> Keyframes:
        """The keyframes the frontend keeps now, with their optimised poses."""
        exported = self.system.frontend.map_export()
        if exported is None:
            return Keyframes(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 4, 4)))
        order = np.argsort(exported.kf_ids, kind="stable")
        return Keyframes(np.asarray(exported.kf_ids)[order], np.asarray(exported.kf_timestamps, np.float64)[order],
                         np.asarray(exported.T_WC, np.float64)[order])

    def map_points(self) -> tuple[np.ndarray, np.ndarray]:
        """The map's points ``X_W (M, 3)`` (world frame, metres or the map's scale) and colours ``(M, 3)``
        uint8 (empty for a frontend without points)."""
        points = self.system.frontend.keyframe_points()
        if points is None:
            return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        return np.asarray(points[0]), np.asarray(points[1])

    def save_map(self, path: str | Path) -> Path:
        """Save the stored map (``fgslam run --save-map``) for :meth:`localize_in` and ``fgslam localize``.
        After :meth:`finish` it holds every frame's pose too (before it, the keyframes alone).

        Raises:
            ConfigError: the frames were not kept (``keep_frames=False``) or there are no keyframes.
        """
        from ..core.config import to_dict
        from ..export.mapfile import build_stored_map, save_stored_map  # deferred: OpenCV, the vocabulary

        if self._kept is None:
            raise ConfigError("save_map needs the keyframes' images: build the Slam with keep_frames=True")
        exported = self.system.frontend.map_export()
        if exported is None or exported.num_keyframes == 0:
            raise ConfigError(f"frontend '{self.system.frontend.name}' has no keyframes to save")
        config = self.config
        traj = None if self._results is None else self._results.traj  # the frames: once finished
        stored = build_stored_map(exported, self._kept, sensor=config.sensor, family=self.system.frontend.name,
                                  config=to_dict(config), features=config.output.map_features,
                                  verification=config.loop_closure.verification, frame_indices=self._kept.indices(),
                                  trajectory=None if traj is None else (traj.timestamps, traj.T_WC),
                                  map_starts=np.asarray(self.state.map_starts))
        save_stored_map(path, stored)
        return Path(path)


#: tracking failures logged one by one before the progress lines take over
MAX_LOGGED_FAILURES = 10
#: What varies inside one kind of event: numbers (ids, counts, values) and parentheses holding one.
_EVENT_VARYING = re.compile(r"\([^()]*\d[^()]*\)|[-+]?\d+(?:\.\d+)?\s*%?")


def event_kind(event: str) -> str:
    """The kind of a frontend event, the key it is counted under in ``summary.json`` ``events``: the
    text before the first ``:`` without the numbers in it (``"keyframe 12 removed"`` and
    ``"keyframe removed: 12"`` -> ``"keyframe removed"``, ``"waiting for parallax (1.2 px)"`` ->
    ``"waiting for parallax"``)."""
    kind = " ".join(_EVENT_VARYING.sub(" ", event.split(":", 1)[0]).split())
    return kind or "event"


def _record(status: FrameStatus, timestamp: float, state: RunState) -> Optional[np.ndarray]:
    """One frame's status into the run's record (events, failures, the live pose); its valid pose or None."""
    for event in status.events:
        state.events[event_kind(event)] += 1
        logger.debug("frame %d: %s", status.index, event)
    if status.new_map:
        state.map_starts.append(float(timestamp))
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
        state.unposed_t.append(float(timestamp))
        return None
    T_WC = np.asarray(status.T_WC, dtype=np.float64)
    if T_WC.shape != (4, 4) or not np.all(np.isfinite(T_WC)):
        state.nonfinite += 1
        logger.warning("frame %d: the frontend returned a non-finite or malformed pose; dropped", status.index)
        return None
    state.live_t.append(float(timestamp))
    state.live_T.append(T_WC)
    state.live_source.append(status.pose_source)
    return T_WC


def open_dataset(path: str | Path, config: str | Path | SlamConfig | None = None, fmt: str = "auto",
                 overrides: Mapping[str, Any] | Sequence[str] | None = None) -> Dataset:
    """Open a sequence (any layout ``fgslam run --data`` reads, or ``camera:SPEC``) for a script's own loop;
    iterate it for :class:`~fgslam.io.frame.Frame` objects (``image`` grey uint8, ``depth`` metres,
    ``image_right``, ``imu``, ``timestamp`` seconds, ``T_WC_gt`` camera-to-world ground truth) already
    undistorted and resized, in the camera ``dataset.camera`` (for :class:`Slam`).

    Args:
        path: the sequence folder, video file or capture.
        config: a preset name, YAML file or config: the streams its sensor needs and its image sizes
            (``Slam.from_preset(name, dataset.camera)`` then gets what ``fgslam run`` gets); None: every
            stream the data has, at the loaders' default sizes.
        fmt: the loader (``auto``: detected from the layout).
        overrides: config keys, as for :meth:`Slam.from_preset` (``{"dataset.end": 100}``).

    Raises:
        ConfigError / DataError: the preset, the path or the data (one line naming it).
    """
    if config is None:
        from ..io.datasets import open_dataset as open_loader

        return open_loader(path, fmt, load_slam_config(None, _override_strings(overrides)).dataset)
    if isinstance(config, SlamConfig):
        if overrides:
            raise ConfigError("open_dataset: give overrides with a preset name, or set them in the SlamConfig")
    else:
        config = load_slam_config(config, _override_strings(overrides))
    return open_slam_dataset(path, config, fmt)
