"""The patch frontend (DPVO / DPV-SLAM family): :class:`PatchFrontend` owns the shared state and
delegates to its collaborators.

- :mod:`.state`: the shared state (:class:`~.state.PatchState`: patch graph, source, cameras, pose
  records, finalised keyframes) and :class:`~.state.BackendFrame`, a graph frame whose pose lives in
  the backend;
- :mod:`.patches`: patch selection, new graph frames, edge measurement;
- :mod:`.window`: the local BA (measure / optimise rounds, one :class:`~.ba.PatchBlock` over the
  optimisation window through :meth:`fgslam.backend.Backend.optimize_window`);
- :mod:`.keyframes`: backend membership, redundant-keyframe removal, retirement and finalisation;
- :mod:`.motion`: the damped constant-velocity model and the motion prior;
- :mod:`.initialisation`: monocular two-view, stereo and RGB-D initialisation;
- :mod:`.tracking`: per-frame tracking (motion filter, BA rounds, implausible-motion check);
- :mod:`.contributor`: the loop service's hooks and the contributor contract (proximity, global BA);
- :mod:`.map_export`: points and the exported map.

Per frame the frontend initialises (until a map exists) or tracks; a tracking failure gives the frame
the predicted pose (``pose_source = "motion_model"``, counted, never raised), or the IMU's when the run
has a motion prior (``imu``: bridged); after ``max_motion_model_frames`` failures in a row the map is
finalised and a new one initialises (anchored at a relocalised pose when loop closure finds one).

Poses are Sim(3) ``T_WC`` with the scale held at its initial value 1, so the output trajectory is
the rigid part ``[R | t]``; RGB-D poses are written back rigid after each BA. Every input frame gets a
pose once the map exists (keyframes from the map, removed frames relative to a neighbour, frames
buffered during initialisation interpolated; typed records, :mod:`..records`); frames before a
successful initialisation are omitted.
"""

from __future__ import annotations

import logging

import numpy as np

from ...core.errors import ConfigError, OptimizationError
from ...factors.schur import torch_threads
from ...backend.graph import Backend
from ..base import NO_LOOPS, BackendFrontend, FrameStatus, SensorMode
from ..records import RelativePose, rigid
from ..rejoin import MapRejoin, RejoinSettings
from .config import PatchConfig
from .contributor import PatchContributor
from .initialisation import Initialiser
from .keyframes import Keyframes
from .map_export import export_map, keyframe_points
from .patches import PatchMeasurer
from .motion import MotionModel
from .state import PatchState
from .tracking import Tracker, TrackingFailure
from .window import LocalBA

logger = logging.getLogger(__name__)


class PatchFrontend(BackendFrontend):
    """DPVO / DPV-SLAM-style patch frontend (see module docstring).

    Args:
        config: the ``patch`` section (:class:`PatchConfig`; default values when None).
        calibration: the frames' :class:`fgslam.io.calibration.Calibration` (undistorted pinhole;
            a right camera and ``T_CLCR`` for stereo); None: taken from the first frame.
        sensor_mode: ``mono``, ``stereo`` (needs right images) or ``rgbd`` (needs depth).
        backend: the run's :class:`fgslam.backend.Backend` (the system builds it from ``map``).

    Loop closure reaches it through the loop port the system connects (:meth:`connect`); the
    contributor contract is :class:`~.contributor.PatchContributor`'s.

    Keyframes: every graph frame is a backend keyframe from when it enters the graph (added with its
    timestamp) until it leaves as redundant or rejected (removed); finalised frames stay. The local
    BA sets this contributor's block (``backend.set_blocks("patch", [block])``), chooses the gauge
    keyframes (``set_gauge``) and runs ``backend.optimize_window(window, ba.iterations)``; the
    solver, gauge sigmas, tolerances and window damping are the backend's (``map``). The backend is
    the only store of keyframe poses (:class:`~.state.BackendFrame`).

    Attributes ``graph`` (the patch graph) and ``_final`` (finalised keyframes by fid) are the shared
    state's (``state``).
    """

    name = "patch"
    relocalizes_in_loaded_map = True  # keyframes and lost frames go to the loop port without the closer (frontends/rejoin.py)

    def __init__(self, config: PatchConfig | None = None, calibration=None, sensor_mode: SensorMode = "mono",
                 backend: Backend | None = None):
        self._attach(config or PatchConfig(), sensor_mode, backend)
        self.proximity_gates = self.config.proximity
        self.state = state = PatchState(self.config, sensor_mode, self.backend, self._records, self._inputs)
        self.graph = state.graph
        self._final = state.final
        self._times = state.times
        self.measurer = PatchMeasurer(state)
        self.keyframes = Keyframes(state)
        self.window = LocalBA(state, self.measurer, self.keyframes, self.name)
        self.motion = MotionModel(state)
        self.initialiser = Initialiser(state, self.window, self.motion)
        self.tracker = Tracker(state, self.window, self.motion)
        self._contributor = PatchContributor(state, self.motion)
        self.rejoin = self._map_rejoin(NO_LOOPS)
        self.calibration = None
        if calibration is not None:
            self._set_calibration(calibration)

    def _set_calibration(self, calibration) -> None:
        self.calibration = calibration
        self.state.set_calibration(calibration)

    @property
    def uses_compiled_kernels(self) -> bool:
        """The reprojection residual of the window and of the tracking is a compiled kernel (as are the
        Lucas-Kanade source's track checks and the RGB-D depth alignment)."""
        return True

    @property
    def source(self):
        """The measurement source (:mod:`.source`); assignable (tests swap it)."""
        return self.state.source

    @source.setter
    def source(self, source) -> None:
        self.state.source = source

    @property
    def _prox_store(self):
        """Settled keyframes' packed source features (proximity loops), or None."""
        return self.contributor.store

    def connect(self, loops=None, motion_prior=None) -> None:
        """Take the loop port and the motion prior (the IMU service's ``predict``: the motion model's
        prior, :class:`~.motion.MotionModel`); with proximity loops on, keep settled keyframes'
        packed source features for long-range edges."""
        super().connect(loops)
        if motion_prior is not None:
            self.motion.prior = motion_prior
        self.contributor.connect(self.loops)
        self.rejoin = self._map_rejoin(self.loops)

    def _map_rejoin(self, loops) -> MapRejoin:
        st = self.state
        return MapRejoin(RejoinSettings.of(st.config.tracking), loops, metric=st.sensor_mode != "mono",
                         keyframe_poses=lambda: {f.fid: f.T_WC for f in list(st.graph.frames) + list(st.final.values())})

    # ------------------------------------------------------------------ Frontend API
    def num_keyframes(self) -> int:
        return len(self.graph) + self.state.finalised

    @property
    def num_failures(self) -> int:
        """Frames whose pose came from the motion model (tracking failures)."""
        return self.state.failures

    @property
    def map_started(self) -> bool:
        return self.state.initialized

    _numerical_errors = (OptimizationError, RuntimeError, np.linalg.LinAlgError)

    def _measuring(self):
        return torch_threads(self.config.threads)

    def _check_frame(self, frame) -> None:
        st = self.state
        if frame.image.shape != (st.height, st.width):
            raise ConfigError(f"frame {frame.index}: image {frame.image.shape} does not match the calibration {st.width}x{st.height}")
        if self.sensor_mode == "stereo" and frame.image_right is None:
            raise ConfigError(f"frame {frame.index}: sensor mode stereo but the frame has no right image")
        if self.sensor_mode == "rgbd" and frame.depth is None:
            raise ConfigError(f"frame {frame.index}: sensor mode rgbd but the frame has no depth")

    def _measure_frame(self, fid: int, frame) -> FrameStatus:
        if not self.state.initialized:
            return self.initialiser.initialize(fid, frame)
        tracked = self.tracker.track(fid, frame)
        if isinstance(tracked, TrackingFailure):
            return self._fail(fid, frame, tracked.reason, tracked.T_WC_pred, tracked.num_valid)
        return tracked

    def _recover(self, fid: int, frame, exc: BaseException) -> FrameStatus:
        logger.warning("frame %d: optimisation failed (%s); using the motion model", frame.index, exc)
        if not self.state.initialized:
            self.initialiser.abandon()
            self.tracker.clear_stationary()
        elif self.graph.frames and self.graph.frames[-1].fid == fid:
            self.keyframes.leave(self.graph.remove_frame(fid))
        return self._fail(fid, frame, f"optimisation failed: {exc}")

    def _after_frame(self, fid: int, frame, status: FrameStatus) -> None:
        self.contributor.keep_image(fid, frame, self.initialiser.buffered_fids())
        self.contributor.feed_keyframes()
        if self.state.initialized and status.pose_source == "tracked":
            self.contributor.proximity_step()
            rejoined = None
            if self.rejoin.waiting and self.graph.frames[-1].fid == fid:  # not a stationary frame (the keyframe's view)
                rejoined = self.rejoin.step(fid, frame, self.state.K.numpy(), self.state.pose_of)
            if rejoined is not None:
                status.events.append(rejoined)
                status.T_WC = rigid(self.state.pose_of(fid))

    def _keyframe_T_WC(self, fid: int) -> np.ndarray:
        return self.state.keyframe_T_WC(fid)

    def _fail(self, fid: int, frame, reason: str, T_WC_pred: np.ndarray | None = None,
              num_valid: int = 0) -> FrameStatus:
        """Frame ``fid`` could not be tracked (``num_valid`` valid image measurements): the IMU's pose when
        the motion prior gives one (bridged), else the predicted pose ``T_WC_pred`` (None: the motion
        model's), counted as a failure; too many in a row finalise the map and start a new initialisation
        (:meth:`_reset`)."""
        st, motion = self.state, self.motion
        self.tracker.clear_stationary()  # stationary frames keep their keyframe's pose
        T_WC_prior = motion.prior(float(frame.timestamp)) if motion.prior is not None and st.initialized else None
        if T_WC_prior is not None and motion.last_fid is not None:  # bridged by the IMU: no failure, no reset
            self._records[fid] = RelativePose(motion.last_fid, np.linalg.inv(st.pose_of(motion.last_fid)) @ T_WC_prior)
            motion.last_fid = fid
            logger.info("frame %d: %s; pose from the IMU", frame.index, reason)
            return st.status(fid, frame, "imu", num_valid=num_valid, events=[reason, "imu bridge"])
        st.failures += 1
        st.lost += 1
        events = [reason]
        if motion.last_fid is None or not st.initialized:
            self._records[fid] = None
            return st.status(fid, frame, "initializing", num_valid=num_valid, events=events)
        if T_WC_pred is None:
            T_WC_pred = motion.predict()
        ref = motion.last_fid
        self._records[fid] = RelativePose(ref, np.linalg.inv(st.pose_of(ref)) @ T_WC_pred)
        # keep the velocity; the next prediction continues from this frame
        motion.last_fid = fid
        source = "motion_model"
        restart = st.lost > self.config.tracking.max_motion_model_frames
        if restart:
            self.contributor.feed_keyframes(all_frames=True)  # the lost map's newest keyframes can relocalise it too
            # the anchor of the re-initialisation, in the reference frame (a map waiting to rejoin is not)
            relocalised = self.contributor.relocalize(fid, frame, before=self.rejoin.reference_before) is not None
            if relocalised:
                events.append("relocalised")
                source = "relocalized"
            self.rejoin.restarted(fid, relocalised)  # not relocalised: the new map's frames try to rejoin (frontends/rejoin.py)
            events.append("re-initialising")
            self._reset()
        logger.info("frame %d: %s", frame.index, reason)
        return st.status(fid, frame, source, num_valid=num_valid, events=events, new_map=restart)

    def _reset(self) -> None:
        """Finalise the graph and start a new initialisation anchored at the last predicted pose (the graph's
        keyframes were handed to the loop port before the lost frame's relocalisation, :meth:`_fail`)."""
        st = self.state
        for f in self.graph.clear():
            self.keyframes.finalise(f)
        self.loops.map_reset()
        st.initialized = False
        self.initialiser.pending = None
        st.lost = 0
        self.tracker.clear_stationary()
        self.motion.reference = None

    def finish(self) -> None:
        self.contributor.feed_keyframes(all_frames=True)

    def finish_map(self) -> None:
        logger.info("patch frontend: %d frames, %d keyframes, %d tracking failures",
                    len(self._inputs), self.num_keyframes(), self.state.failures)

    def keyframe_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        return keyframe_points(self.state)

    def map_export(self):
        """Keyframes and one point per patch with its track (:func:`.map_export.export_map`)."""
        return export_map(self.state)

    def inactive_edges(self) -> dict:
        """The bounded store of inactive edges (see :class:`~.graph.InactiveEdges`)."""
        return self.graph.inactive.arrays()

    # ------------------------------------------------------------------ loop counts (the contract itself: self.contributor)
    def add_loop_counts(self, summary: dict) -> None:
        self.contributor.add_loop_counts(summary)

