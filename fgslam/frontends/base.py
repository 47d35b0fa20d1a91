"""The contract between the SLAM runner and a frontend family (dense, patch, pointmap).

A frontend consumes :class:`fgslam.io.frame.Frame` objects one at a time, owns its measurement
source and its slice of the map, and reports per-frame status. The runner (``fgslam.slam``) is
frontend-agnostic: it iterates a dataset, calls :meth:`Frontend.process`, and at the end asks for
the poses of every input frame with :meth:`Frontend.trajectory`.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

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
    """

    index: int
    timestamp: float
    T_WC: np.ndarray | None
    pose_source: PoseSource
    is_keyframe: bool = False
    num_valid: int = 0
    events: list[str] = field(default_factory=list)


class Frontend(abc.ABC):
    """A frontend family. Constructed by the runner with its config section and the sensor mode."""

    #: registry name (``dense``, ``patch``, ``pointmap``)
    name: str = ""

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
        """Called once after the last frame (final global optimisation, flush background work)."""

    def abort(self) -> None:
        """Stop background work at once, without applying it (an interrupted or failed run: its
        outputs are written from what the frontend holds now). Default: nothing runs in the background."""

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

    def loop_summary(self) -> dict | None:
        """Optional loop-closure counts for ``summary.json`` (loops verified / accepted, corrections
        applied, relocalisations, ...); None when the frontend runs no loop closure."""
        return None

    def map_export(self):
        """The map a run saves for ``fgslam export`` (:class:`fgslam.export.map.MapExport`: keyframe
        ids, timestamps, rigid ``T_WC``, points with colour and tracks), or None.

        Default: the points of :meth:`keyframe_points` without tracks, and the keyframes of the
        frontend's backend (``self.backend``) when it has one; None without points. Frontends that
        know which keyframe pixels observe each point override it (the patch frontend: its patches)."""
        points = self.keyframe_points()
        if points is None:
            return None
        from ..export.map import MapExport, rigid_poses

        backend = getattr(self, "backend", None)
        kf_ids = [] if backend is None else sorted(backend.keyframe_ids)
        T_WC = rigid_poses(np.stack([backend.pose_matrix(k) for k in kf_ids])) if kf_ids else np.zeros((0, 4, 4))
        stamps = [backend.timestamp(k) for k in kf_ids]
        return MapExport(kf_ids, stamps, T_WC, points[0], points[1])


#: the sensor modes a frontend family may be built for
SENSOR_MODES: tuple[str, ...] = ("mono", "stereo", "rgbd")


class BackendFrontend(Frontend):
    """Plumbing shared by the families that feed the run's backend (patch, dense, pointmap): the checks
    and services of their constructor, the per-input-frame bookkeeping of :meth:`process` (``_fid``,
    ``_inputs``, ``_records``) and the stage times with the loop service's share. The families' own
    work stays in their classes."""

    def _attach(self, config, sensor_mode: str, map_config=None, backend=None) -> None:
        """Validate ``config``, check ``sensor_mode`` and take the run's ``backend`` (a new one from
        ``map_config`` when the frontend is built alone, as in tests). Sets ``config``, ``sensor_mode``,
        ``backend`` and the empty input bookkeeping."""
        from ..backend import Backend
        from ..backend.config import BackendConfig
        from ..errors import ConfigError

        config.validate()
        if sensor_mode not in SENSOR_MODES:
            raise ConfigError(f"sensor mode must be {', '.join(SENSOR_MODES[:-1])} or {SENSOR_MODES[-1]}, "
                              f"got {sensor_mode!r}")
        self.config = config
        self.sensor_mode = sensor_mode
        self.backend = backend if backend is not None else Backend(map_config or BackendConfig())
        self._records: dict = {}  # fid -> pose record (fgslam.frontends.records), None while it has no pose
        self._inputs: list[tuple[int, float, int]] = []  # (fid, timestamp, index) per input frame
        self._sources: dict[int, str] = {}  # fid -> pose source reported for it (default: tracked)
        self._fid = 0

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
        from .records import resolve_pose, rigid

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

    def abort(self) -> None:
        """Stop the loop service's background work (a running global BA's worker process, the
        closer's thread) without applying it."""
        self.loops.cancel()

    def stage_times(self) -> dict[str, float]:
        """The frontend's own stage times (``_times``) plus the loop service's share in this thread."""
        out = dict(self._times)
        for stage, seconds in self.loops.stage_times().items():
            out[stage] = out.get(stage, 0.0) + seconds
        return out
