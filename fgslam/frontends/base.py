"""The contract between the system (:class:`fgslam.run.system.SlamSystem`) and a frontend family.

A frontend only measures: it consumes :class:`fgslam.io.frame.Frame` objects one at a time, owns
its measurement source and its slice of the map (patches, depth maps, pointmaps), decides keyframes
and sets its measurement blocks on the run's backend, which the system hands it. It constructs no
backend and no service. The system owns the backend and the services (loop closure, IMU, plugins,
live view) and runs the per-frame skeleton around :meth:`Frontend.process`; the frontend reaches
loop closure only through the narrow :class:`LoopPort` the system connects (:meth:`Frontend.connect`),
and the services reach the frontend only through :mod:`fgslam.contracts.contributor`.

At the end the system asks for the poses of every input frame with :meth:`Frontend.trajectory`.
"""

from __future__ import annotations

import abc
import contextlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Literal, Optional, Protocol

import numpy as np

from ..core.errors import ConfigError

if TYPE_CHECKING:
    from ..backend import Backend
    from ..contracts.contributor import ProximityGates

#: How a frame's pose was obtained.
PoseSource = Literal["initializing", "tracked", "motion_model", "relocalized", "imu"]

SensorMode = Literal["mono", "stereo", "rgbd"]


@dataclass
class FrameStatus:
    """What :meth:`Frontend.process` reports for one frame.

    Attributes:
        index: the frame's ``Frame.index``.
        timestamp: seconds.
        T_WC: current camera-to-world estimate (4x4 float64; for monocular the scale is the map's),
            or None while the system is initialising and has no pose yet.
        pose_source: ``initializing`` (waiting for parallax), ``tracked`` (visual measurements),
            ``motion_model`` (tracking failed; pose predicted - counted as a failure),
            ``relocalized``, ``imu`` (visual tracking failed; pose from the IMU prediction of the
            run's IMU service - bridged, not counted as a failure).
        is_keyframe: whether the frame is currently kept as a keyframe.
        num_valid: number of valid measurements (patches / pixels / matches) used for this frame.
        events: human-readable notes (initialised, tracking lost, keyframe removed, ...).
        new_map: the frontend started a new map at this frame (after a lost track): its keyframes from
            here on are not tied to the earlier ones (a stored map keeps them as a session of their own).
    """

    index: int
    timestamp: float
    T_WC: np.ndarray | None
    pose_source: PoseSource
    is_keyframe: bool = False
    num_valid: int = 0
    events: list[str] = field(default_factory=list)
    new_map: bool = False


class LoopPort(Protocol):
    """What a frontend may ask of loop closure while it measures a frame (the system's
    :class:`fgslam.services.loops.LoopService` implements it; :data:`NO_LOOPS` until connected)."""

    @property
    def enabled(self) -> bool: ...  # classical or proximity loops run

    @property
    def classical(self) -> bool: ...  # the classical closer (retrieval, relocalisation) runs

    @property
    def relocalizes(self) -> bool: ...  # a lost frame can be relocalised (the closer's database or a loaded map): keyframes wanted

    @property
    def proximity(self) -> Optional[ProximityGates]: ...  # the proximity gates, None when proximity loops are off

    def add_keyframe(self, kf_id: int, neighbours: Sequence[int] = ()) -> bool: ...

    def update_poses(self, T_WC_by_id: dict) -> None: ...

    def relocalize(self, image: np.ndarray, K: np.ndarray, before: int | None = None) -> tuple[int, np.ndarray] | None: ...

    def map_reset(self) -> None: ...

    def move_map(self, correction, T_WC_by_id: dict) -> bool: ...  # a correction of the frontend's own (rejoin); False: not applied

    def keyframe_settled(self, kf_id: int) -> None: ...

    def search(self, query: int) -> None: ...

    @property
    def runs_global_ba(self) -> bool: ...  # start_global_ba can run a global BA in the background

    @property
    def busy(self) -> bool: ...  # a global BA runs (or waits to be applied)

    def prepare_global_ba(self) -> None: ...  # start the background worker ahead of the first global BA

    def start_global_ba(self) -> bool: ...  # a global BA without loop edges in the background (False: busy)

    def verified_loops(self) -> list: ...  # the classical closer's verified loops so far


class NoLoops:
    """The :class:`LoopPort` of a frontend without loop closure: every request is a no-op."""

    enabled = False
    classical = False
    relocalizes = False
    proximity = None
    runs_global_ba = False
    busy = False

    def add_keyframe(self, kf_id: int, neighbours: Sequence[int] = ()) -> bool:
        return False

    def update_poses(self, T_WC_by_id: dict) -> None:
        return None

    def relocalize(self, image: np.ndarray, K: np.ndarray, before: int | None = None) -> tuple[int, np.ndarray] | None:
        return None

    def map_reset(self) -> None:
        return None

    def move_map(self, correction, T_WC_by_id: dict) -> bool:
        return False

    def keyframe_settled(self, kf_id: int) -> None:
        return None

    def search(self, query: int) -> None:
        return None

    def prepare_global_ba(self) -> None:
        return None

    def start_global_ba(self) -> bool:
        return False

    def verified_loops(self) -> list:
        return []


#: the loop port of every frontend until the system connects its loop service
NO_LOOPS = NoLoops()

#: a motion prior: ``T_WC`` (4x4) predicted at a timestamp, or None (the IMU service's ``predict``)
MotionPrior = Callable[[float], Optional[np.ndarray]]


class Frontend(abc.ABC):
    """A frontend family, built by the system (:func:`fgslam.frontends.make_frontend`) with its
    config section, the calibration, the sensor mode and the run's backend.

    The system calls, in this order: :meth:`connect` once; per frame, when :attr:`map_started`,
    the loop service's safe point and then :meth:`corrections_applied`, then :meth:`process`; at the
    end :meth:`finish` (hand over the last keyframes), the loop service's last correction, then
    :meth:`finish_map` (final optimisation)."""

    #: registry name (``dense``, ``patch``, ``pointmap``)
    name: str = ""
    #: the map has a metric scale (stereo / RGB-D): loop corrections are SE(3)
    metric_scale: bool = False
    #: the proximity-loop gates of the family (None: the family closes no proximity loops)
    proximity_gates: Optional[ProximityGates] = None
    #: the family hands global optimisations to the loop service's background worker, so the system
    #: connects a loop service (inert but for them) even with loop closure off
    background_global_ba: bool = False
    #: the family hands its keyframes to the loop port for relocalisation without the classical closer
    #: (``LoopPort.relocalizes``), so a loaded map (``fgslam run --map``) can relocalise its lost frames
    relocalizes_in_loaded_map: bool = False
    #: the loop-closure port (:meth:`connect`)
    loops: LoopPort = NO_LOOPS
    #: the run's backend the frontend feeds (None: a frontend that feeds none, e.g. a test's stand-in)
    backend: Optional["Backend"] = None

    @property
    def uses_compiled_kernels(self) -> bool:
        """The family calls compiled kernels (:mod:`fgslam.core.jit`) on its frames: the run loads
        numba's machine-code target before the first frame (:func:`fgslam.core.jit.warm_up`)."""
        return False

    @property
    def contributor(self):
        """What the services talk to (:mod:`fgslam.contracts.contributor`: keyframe images and poses,
        corrections, long-range edges): a family's collaborator set as ``_contributor``, else the
        frontend itself."""
        return self.__dict__.get("_contributor", self)

    def connect(self, loops: LoopPort | None = None, motion_prior: MotionPrior | None = None) -> None:
        """Take the run's loop-closure port (the system calls it once, before the first frame). A
        family that predicts poses overrides it to take ``motion_prior`` too (the patch family's
        motion model); the others have no use for it."""
        self.loops = loops if loops is not None else NO_LOOPS

    @property
    def map_started(self) -> bool:
        """Whether the frontend has a map, so that the system runs the services' safe point before
        the next frame (default: after the first frame)."""
        return False

    def corrections_applied(self) -> None:
        """Called right after the loop service's safe point (corrections applied), before the frame."""

    def frame_indices(self) -> dict[int, int]:
        """Frame id -> dataset index of every input frame (the loop summary reports indices)."""
        return {}

    def add_loop_counts(self, summary: dict) -> None:
        """Add the family's own loop counts to the loop service's ``summary`` (default: none)."""

    @abc.abstractmethod
    def process(self, frame) -> FrameStatus:
        """Consume one frame (in order) and return its status. Never raises on a tracking failure:
        a failure is reported as ``pose_source="motion_model"`` with an event."""

    @abc.abstractmethod
    def trajectory(self) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Final poses of every processed frame: ``(timestamps (N,), T_WC (N, 4, 4), pose_sources)``
        after the last optimisation (non-keyframes from their stored pose relative to a keyframe).
        Frames that never got a pose (initialisation never succeeded) are omitted."""

    @abc.abstractmethod
    def num_keyframes(self) -> int:
        """Keyframes currently in the map."""

    def finish(self) -> None:
        """Called once after the last frame: hand the last keyframes to the loop port (the system
        then applies the loop service's last correction and calls :meth:`finish_map`)."""

    def finish_map(self) -> None:
        """Called once after the last loop correction (final optimisation, the closing log line)."""

    def abort(self) -> None:
        """Called instead of the end (a stopped or failed run): stop the frontend's own background
        work at once without applying it (default: none)."""

    def stage_times(self) -> dict[str, float]:
        """Accumulated wall time in seconds per stage (e.g. ``flow``, ``ba``, ``bookkeeping``)."""
        return {}

    def keyframe_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Optional map points ``(X_W (M, 3) float, colour (M, 3) uint8)`` for PLY export."""
        return None

    def keyframe_depths(self) -> dict[int, tuple[float, np.ndarray, np.ndarray | None]] | None:
        """Optional dense depth per keyframe: kf id -> ``(timestamp, depth (H, W) float32 in the map's
        units at image resolution (0: none), confidence (H, W) in [0, 1] or None)``; the runner writes
        them as 16-bit PNGs with ``output.write_depth``."""
        return None

    def map_export(self):
        """The map a run saves for ``fgslam export`` (:class:`fgslam.core.mapdata.MapExport`: keyframe
        ids, timestamps, rigid ``T_WC``, points with colour and tracks), or None.

        Default: the points of :meth:`keyframe_points` without tracks, and the keyframes of the
        frontend's backend (``self.backend``) when it has one; None without points. Frontends that
        know which keyframe pixels observe each point override it (the patch frontend: its patches)."""
        points = self.keyframe_points()
        if points is None:
            return None
        from ..core.mapdata import MapExport, rigid_poses  # deferred: torch (fgslam.core.mapdata; base is on the CLI's light path)

        backend = self.backend
        kf_ids = [] if backend is None else sorted(backend.keyframe_ids)
        T_WC = rigid_poses(np.stack([backend.pose_matrix(k) for k in kf_ids])) if kf_ids else np.zeros((0, 4, 4))
        stamps = [backend.timestamp(k) for k in kf_ids]
        return MapExport(kf_ids, stamps, T_WC, points[0], points[1])


#: the sensor modes a frontend family may be built for
SENSOR_MODES: tuple[str, ...] = ("mono", "stereo", "rgbd")


class BackendFrontend(Frontend):
    """Plumbing shared by the families that feed the run's backend (patch, dense, pointmap): the checks
    of their constructor and the per-input-frame bookkeeping of :meth:`process` (``_fid``, ``_inputs``,
    ``_records``). The families' own work stays in their classes."""

    def _attach(self, config, sensor_mode: str, backend) -> None:
        """Validate ``config``, check ``sensor_mode`` and take the run's ``backend``. Sets ``config``,
        ``sensor_mode``, ``backend`` and the empty input bookkeeping."""
        config.validate()
        if sensor_mode not in SENSOR_MODES:
            raise ConfigError(f"sensor mode must be {', '.join(SENSOR_MODES[:-1])} or {SENSOR_MODES[-1]}, "
                              f"got {sensor_mode!r}")
        if backend is None:
            raise ConfigError(f"frontend '{self.name}' needs the run's backend (built by fgslam.run.system.SlamSystem, "
                              "or fgslam.backend.Backend(config) in a test)")
        self.config = config
        self.sensor_mode = sensor_mode
        self.metric_scale = sensor_mode != "mono"
        self.backend = backend
        self._records: dict = {}  # fid -> pose record (fgslam.frontends.records), None while it has no pose
        self._inputs: list[tuple[int, float, int]] = []  # (fid, timestamp, index) per input frame
        self._sources: dict[int, str] = {}  # fid -> pose source reported for it (default: tracked)
        self._fid = 0

    def frame_indices(self) -> dict[int, int]:
        return {fid: idx for fid, _, idx in self._inputs}

    # ------------------------------------------------------------------ the per-frame skeleton
    #: the exceptions of numerical trouble (gtsam/torch/numpy...) that fail one frame, never the run
    _numerical_errors: tuple[type[BaseException], ...] = (RuntimeError, np.linalg.LinAlgError)

    def process(self, frame) -> FrameStatus:
        """The one per-frame skeleton of the families: the calibration from the first frame when none
        was given, the frame checked (``_check_frame``) and registered, then the family's measurement
        (``_measure_frame``) under its numerical guard: numerical trouble (``_numerical_errors``) fails the
        frame (``_recover``: the motion model, counted as a failure), never the run; then
        ``_after_frame``."""
        if not self._has_calibration():
            self._set_calibration(frame.calibration)
        self._check_frame(frame)
        fid = self._register_input(frame)
        try:
            with self._measuring():
                status = self._measure_frame(fid, frame)
        except self._numerical_errors as exc:
            status = self._recover(fid, frame, exc)
        self._sources[fid] = status.pose_source
        self._after_frame(fid, frame, status)
        return status

    def _has_calibration(self) -> bool:
        return self.calibration is not None

    def _measuring(self):
        """The context of one frame's measurement (the families: their torch thread count)."""
        return contextlib.nullcontext()

    def _after_frame(self, fid: int, frame, status: FrameStatus) -> None:
        """After the frame's status is known (outside the numerical guard); default nothing."""

    def _register_input(self, frame) -> int:
        """A new frame id for ``frame``, recorded as an input without a pose yet."""
        fid = self._fid
        self._fid += 1
        self._inputs.append((fid, float(frame.timestamp), int(frame.index)))
        self._records[fid] = None
        return fid

    #: trajectory(): leave out frames whose resolved pose is not finite (else they are reported as they are)
    _skip_nonfinite_poses: bool = False

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Every input frame's pose from its record (keyframes read through ``_keyframe_T_WC``, which
        the family defines), as a rigid ``T_WC``; frames without a pose are left out."""
        from .records import resolve_pose, rigid  # deferred: torch (via fgslam.loop.records; CLI's light path)

        stamps, poses, sources = [], [], []
        cache: dict = {}
        for fid, stamp, _ in self._inputs:
            T = resolve_pose(fid, self._records, self._keyframe_T_WC, cache)
            if T is None or (self._skip_nonfinite_poses and not np.isfinite(T).all()):
                continue
            stamps.append(stamp)
            poses.append(rigid(T))
            sources.append(self._sources.get(fid, "tracked"))
        if not poses:
            return np.zeros(0), np.zeros((0, 4, 4)), []
        return np.array(stamps), np.stack(poses), sources

    def stage_times(self) -> dict[str, float]:
        """The frontend's own stage times (``_times``)."""
        return dict(self._times)
