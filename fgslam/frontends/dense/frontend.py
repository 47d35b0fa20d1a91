"""The dense frontend (DROID-SLAM family): frame graph, dense bundle adjustment of 1/8-resolution
inverse depth through the backend, global optimisation, loop closure through the shared service.

Per frame (DROID-SLAM section 3.4, with the built-in DIS flow source of :mod:`.source`):

1. **tracking and motion filter**: the frame's pose is predicted (damped constant velocity) and
   optimised motion-only against the newest keyframe (its inverse-depth map held: the dense block's
   per-pixel damping set very high, so nothing flows into the depths), from the flow measured warm-
   started at the prediction; a frame whose share of confident grid pixels is below
   ``tracking.min_confident`` is a tracking failure (predicted pose, counted, never raised; after
   ``tracking.max_lost`` in a row the map restarts, relocalised through the loop service when it can, and
   a restart that was not tries to rejoin the maps before it, :mod:`..rejoin`);
2. when the mean measured flow exceeds ``graph.motion_filter_flow``, or its confident grid pixels are
   fewer than ``graph.keyframe_min_confident`` of its textured ones, the frame becomes a keyframe:
   backend keyframe at the tracked pose, inverse depths splatted from the previous keyframe
   (RGB-D: the sensor's; stereo: from the left-right flow), edges both ways to the
   ``graph.temporal_radius`` previous keyframes and the ``graph.neighbours`` nearest ones by flow
   distance; else it keeps its pose relative to the newest keyframe (the **trajectory filler**:
   the motion-only optimisation above, stored as a :class:`~fgslam.frontends.records.RelativePose`);
3. **local dense BA**: ``ba.rounds`` rounds of measuring the edges (all edges of the window in the
   first round, those touching the new keyframe later) from the field the current estimate induces
   (Huber-weighted by the revision's size), then ``backend.optimize_window`` over the newest
   ``ba.window`` keyframes with one :class:`~fgslam.factors.dense.DenseBlock` (per-pixel inverse
   depths Schur-eliminated with DROID's damping eta, eq. 5; RGB-D depth prior; stereo left-right
   rows through the fixed calibrated ``T_CRCL``); the rest of the active graph is held fixed;
4. **redundant keyframes**: the second newest keyframe is removed when its flow distance to the one
   before is below ``graph.remove_threshold`` (pose kept relative to it);
5. keyframes beyond ``graph.active_keyframes`` leave the active graph (to the loop closer); settled
   keyframes are proximity-loop queries (``dense.proximity``, with ``loop_closure.mode`` proximity or
   both); every ``global_ba.every`` keyframes (in the loop service's worker, applied at its safe point)
   and at the end (at once) a **global optimisation** rebuilds the edges from the N x N flow-distance
   matrix (:func:`.graph.select_global_edges`), measures them and optimises every keyframe of the map
   on a snapshot through the backend (:func:`.ba.solve_dense_global`; older maps stay as they are).

Initialisation: monocular collects ``graph.init_keyframes`` keyframes (tracked against a constant
depth map), connects them and optimises them all (first keyframe anchored, the distance between
the first and last the world scale); stereo and RGB-D start with metric depth at the first frame.

The frontend owns the shared state (:class:`~.state.DenseState`: graph, source, cameras, pose records,
motion model, counts, stage times) and runs the per-frame steps; the work is in collaborators that each
take that state and the collaborators they call (none holds the frontend): step 1 in :mod:`.tracking`,
steps 2, 4 and the retirement of 5 in :mod:`.keyframes`, step 3 and 5's global snapshot, solve and
hand-over in :mod:`.ba`, the initialisation and map restart in :mod:`.lifecycle`, the loop hand-over, the
contributor contract and the running of 5's global optimisation in :mod:`.contributor`, depth and point
export in :mod:`.export`.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from ...backend.graph import Backend
from ...core.errors import ConfigError
from ...factors.schur import torch_threads
from ..base import NO_LOOPS, BackendFrontend, FrameStatus, MotionPrior, SensorMode
from ..records import RelativePose, rigid
from ..rejoin import MapRejoin, RejoinSettings
from .ba import DenseBA
from .config import DenseConfig
from .contributor import DenseLoopContributor
from .export import keyframe_depths, keyframe_points
from .keyframes import DenseKeyframes
from .lifecycle import DenseMapStarts
from .state import DenseState
from .tracking import NUMERICAL_ERRORS, DenseTracker
from .weights import textured_share

logger = logging.getLogger(__name__)


class DenseFrontend(BackendFrontend):
    """DROID-SLAM-style dense frontend (module docstring); builder of the ``dense`` family.

    Args as :class:`fgslam.frontends.patch.PatchFrontend`: ``config`` the ``dense`` section,
    ``calibration`` (None: the first frame's), ``sensor_mode`` mono | stereo | rgbd, ``backend`` (the
    run's backend; every keyframe pose lives there). Loop closure reaches it through the loop port the
    system connects (the frontend is the loop service's contributor).

    The frontend owns the shared state ``state`` (:class:`.state.DenseState`: graph, source,
    calibration, pose records, motion model, counts, stage times; ``_times`` is its ``times``) and runs
    the per-frame steps; its collaborators each take that state: ``tracker``
    (:class:`.tracking.DenseTracker`), ``keyframes`` (:class:`.keyframes.DenseKeyframes`), ``ba``
    (:class:`.ba.DenseBA`), ``starts`` (:class:`.lifecycle.DenseMapStarts`) and the loop contributor
    (``contributor``, :class:`.contributor.DenseLoopContributor`).
    """

    name = "dense"
    relocalizes_in_loaded_map = True  # keyframes and a restart's lost frame go to the loop port without the closer
    _skip_nonfinite_poses = True  # a diverged motion-only solve leaves no pose (not a non-finite one)

    def __init__(self, config: DenseConfig | None = None, calibration=None, sensor_mode: SensorMode = "mono",
                 backend: Backend | None = None):
        self._attach(config or DenseConfig(), sensor_mode, backend)
        self.state = state = DenseState(self.config, sensor_mode, self.backend, self._records, self._inputs)
        if calibration is not None:
            self._set_calibration(calibration)
        self._times = state.times
        self.proximity_gates = self.config.proximity
        self.background_global_ba = state.background_global_ba
        self.tracker = DenseTracker(state)
        self.ba = DenseBA(state, self.name)
        self._contributor = DenseLoopContributor(state, self.ba, self.name)
        self.keyframes = DenseKeyframes(state, self._contributor)
        self.starts = DenseMapStarts(state, self.keyframes, self.ba, self.tracker, self._contributor)
        self.rejoin = self._map_rejoin(NO_LOOPS)

    # ------------------------------------------------------------------ calibration
    @property
    def calibration(self):
        """The frames' calibration (None until the first frame's when none was given)."""
        return self.state.calibration

    def _set_calibration(self, calibration) -> None:
        self.state.set_calibration(calibration)

    # ------------------------------------------------------------------ Frontend API
    @property
    def uses_compiled_kernels(self) -> bool:
        """The reprojection residual of every block and of the tracking is a compiled kernel."""
        return True

    def num_keyframes(self) -> int:
        st = self.state
        return (0 if st.graph is None else len(st.graph.keyframes)) + len(st.final)

    @property
    def num_failures(self) -> int:
        return self.state.failures

    @property
    def counts(self) -> dict[str, int]:
        return dict(self.state.counts)

    _numerical_errors = NUMERICAL_ERRORS

    def _measuring(self):
        return torch_threads(self.config.threads)

    def _recover(self, fid: int, frame, exc: BaseException) -> FrameStatus:
        logger.warning("frame %d: dense frontend failed (%s); using the motion model", frame.index, exc)
        return self._fail(fid, frame, f"optimisation failed: {exc}")

    @property
    def map_started(self) -> bool:
        return self.state.initialized

    def finish(self) -> None:
        st = self.state
        if self.starts.pending:  # the sequence ended during the initialisation: its rounds left
            self.starts.advance(all_left=True)
        if st.initialized:
            self.starts.retrack_pending(all_left=True)
        if st.initialized and self.config.global_ba.final and len(st.graph.keyframes) >= 3:
            self.contributor.global_ba()
        self.contributor.feed(all_keyframes=True)

    def finish_map(self) -> None:
        logger.info("dense frontend: %d frames, %d keyframes, %d tracking failures, counts %s",
                    len(self._inputs), self.num_keyframes(), self.state.failures, self.state.counts)

    def keyframe_depths(self) -> dict[int, tuple[float, np.ndarray, np.ndarray | None]] | None:
        """Keyframe id -> (timestamp, depth (H, W) float32 in map units, confidence (H, W) in [0, 1])
        (:func:`.export.keyframe_depths`; pixels below ``point_confidence``: 0)."""
        st = self.state
        kfs = st.all_keyframes()
        if not kfs:
            return None
        return keyframe_depths(kfs, st.keyframe_T_WC, (st.width, st.height), st.crop, self.config.point_confidence)

    def keyframe_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Confidence-filtered grid points of every keyframe in the world frame, with their colours."""
        st = self.state
        K_grid = st.K_grid if st.graph is not None else (1, 1, 0, 0)
        return keyframe_points(st.all_keyframes(), st.keyframe_T_WC, K_grid, self.config.point_confidence)

    # ------------------------------------------------------------------ frames and poses
    def _check_frame(self, frame) -> None:
        st = self.state
        if frame.image.shape != (st.height, st.width):
            raise ConfigError(f"frame {frame.index}: image {frame.image.shape} does not match the calibration "
                              f"{st.width}x{st.height}")
        if self.sensor_mode == "stereo" and frame.image_right is None:
            raise ConfigError(f"frame {frame.index}: sensor mode stereo but the frame has no right image")
        if self.sensor_mode == "rgbd" and frame.depth is None:
            raise ConfigError(f"frame {frame.index}: sensor mode rgbd but the frame has no depth")

    def _keyframe_T_WC(self, fid: int) -> np.ndarray:
        return self.state.keyframe_T_WC(fid)

    def connect(self, loops=None, motion_prior: MotionPrior | None = None) -> None:
        """Take the loop port and the motion prior (the IMU service's ``predict``): the prior is the
        tracking prediction when it gives a pose, and the pose of a frame the flow loses (``imu``)."""
        super().connect(loops)
        self.state.loops = self.loops
        self.state.motion_prior = motion_prior
        self.rejoin = self._map_rejoin(self.loops)

    def _map_rejoin(self, loops) -> MapRejoin:
        st = self.state
        return MapRejoin(RejoinSettings.of(self.config.tracking), loops, metric=st.metric_scale,
                         keyframe_poses=lambda: {kf.fid: st.keyframe_T_WC(kf.fid) for kf in st.all_keyframes()
                                                 if st.backend.has_keyframe(kf.fid)})

    def _after_frame(self, fid: int, frame, status: FrameStatus) -> None:
        """A restarted map's tracked frames try to rejoin the maps before it (:mod:`..rejoin`)."""
        st = self.state
        if self.rejoin.waiting and st.initialized and status.pose_source == "tracked":
            rejoined = self.rejoin.step(fid, frame, st.K, st.pose_of)
            if rejoined is not None:
                status.events.append(rejoined)
                status.T_WC = rigid(st.pose_of(fid))

    # ------------------------------------------------------------------ per frame
    def _surface(self, frame):
        """The frame's depth surface (RGB-D depth alignment; None when off), made once per frame."""
        st = self.state
        if not st.depth.enabled:
            return None
        t0 = time.perf_counter()
        surface = st.depth.surface(st.cropped(frame.depth))
        st.times["depth"] += time.perf_counter() - t0
        return surface

    def _measure_frame(self, fid: int, frame) -> FrameStatus:
        st = self.state
        g = st.graph
        surface = self._surface(frame)
        if not g.keyframes:  # the first keyframe of a map
            T_WC0 = st.pending_origin if st.pending_origin is not None else np.eye(4)
            st.pending_origin = None
            self.keyframes.add(fid, frame, T_WC0, surface=surface)
            st.velocity = np.eye(4)
            st.last_fid = fid
            if self.sensor_mode != "mono":
                st.initialized = True
                return st.status(fid, frame, "tracked", is_keyframe=True, events=["initialised"])
            return st.status(fid, frame, "initializing", is_keyframe=True)
        if st.initialized and st.init_frames:  # re-tracking of the frames before the initialisation, spread
            self.starts.retrack_pending()
        t0 = time.perf_counter()
        kf_fid = g.active[-1]
        T_WC_pred = st.predict(frame.timestamp)
        events = []
        added = False
        textured = textured_share(st.cropped(frame.image), st.stride, self.config.tracking.texture_gradient)
        if textured < self.config.tracking.min_textured:
            held = self.tracker.by_depth(kf_fid, fid, T_WC_pred, surface, with_image=False)
            if held is None:
                st.counts["low_texture_frames"] += 1
                return self._fail(fid, frame, f"tracking lost: no texture ({100 * textured:.1f} % of the grid textured)", T_WC_pred)
            (T_WC, flow), n_conf = held, 0
            events.append(f"tracked by depth alone (no texture: {100 * textured:.1f} % of the grid textured)")
        else:
            flow0 = st.times["flow"]
            st.source.add_frame(fid, st.source_image(frame))
            added = True
            T_WC, flow, n_conf, ok = self.tracker.track(kf_fid, fid, T_WC_pred, surface)
            st.times["tracking"] += time.perf_counter() - t0 - (st.times["flow"] - flow0)
            n_pix = g.shape[0] * g.shape[1]
            if not ok or n_conf < self.config.tracking.min_confident * n_pix:
                held = self.tracker.by_depth(kf_fid, fid, T_WC_pred, surface, with_image=True)
                if held is None:
                    st.source.remove_frame(fid)
                    st.counts["low_confidence_frames"] += 1
                    return self._fail(fid, frame, f"tracking lost: {n_conf} of {n_pix} grid pixels confident", T_WC_pred)
                T_WC, flow = held
                events.append(f"tracked by depth ({n_conf} of {n_pix} grid pixels confident)")
        if events:
            st.counts["depth_tracked"] += 1
        st.lost = 0
        moved = flow > self.config.graph.motion_filter_flow
        # the tracking's support fades: few of the textured grid blocks confidently tracked
        fading = not events and n_conf < self.config.graph.keyframe_min_confident * textured * g.shape[0] * g.shape[1]
        if not moved and not fading:
            if added:
                st.source.remove_frame(fid)
            st.records[fid] = RelativePose(kf_fid, np.linalg.inv(st.keyframe_T_WC(kf_fid)) @ T_WC)
            if not st.initialized:  # tracked against a provisional depth map: re-tracked after the initialisation
                st.init_frames[fid] = (kf_fid, st.source_image(frame))
            if self.starts.pending and self.starts.advance():
                events.append("initialised")
            st.update_velocity(fid)
            source = "tracked" if st.initialized else "initializing"
            return st.status(fid, frame, source, num_valid=n_conf, events=events)
        if not moved:  # a keyframe because its support faded
            st.counts["fading_keyframes"] += 1
            events.append("keyframe: the confident share faded")
        self.keyframes.add(fid, frame, T_WC, source_added=added, surface=surface)
        if not st.initialized:
            if self.starts.pending:  # a keyframe collected during the initialisation joins its next rounds
                done = self.starts.advance()
            else:
                done = len(g.keyframes) >= self.config.graph.init_keyframes and self.starts.initialize()
            if done:
                events.append("initialised")
            st.update_velocity(fid)
            return st.status(fid, frame, "tracked" if st.initialized else "initializing", True, n_conf, events)
        self.ba.local(fid)
        removed = self.keyframes.remove_redundant()
        if removed is not None:
            events.append(f"keyframe removed: {removed}")
        elif self.config.ba.kept_rounds:  # DROID-SLAM: more update iterations when the keyframe stays
            self.ba.local(fid, self.config.ba.kept_rounds)
        self.keyframes.retire()
        st.update_velocity(fid)
        st.new_since_global += 1
        every = self.config.global_ba.every
        if every and st.new_since_global >= every:
            self.contributor.global_ba(background=True)
        return st.status(fid, frame, "tracked", fid in g.keyframes, n_conf, events)

    def _fail(self, fid: int, frame, reason: str, T_WC_pred: np.ndarray | None = None) -> FrameStatus:
        """Tracking failure: the motion prior's pose when it gives one (bridged by the IMU: ``imu``, not a
        failure), else the predicted pose relative to the newest keyframe, counted; a map restart after
        ``tracking.max_lost`` in a row."""
        st = self.state
        g = st.graph
        T_WC_imu = st.prior_pose(frame.timestamp)
        if T_WC_imu is not None and g is not None and g.active and st.last_fid is not None and g.active[-1] != fid:
            ref = g.active[-1]
            st.records[fid] = RelativePose(ref, np.linalg.inv(st.keyframe_T_WC(ref)) @ T_WC_imu)
            st.last_fid = fid
            logger.info("frame %d: %s; pose from the IMU", frame.index, reason)
            return st.status(fid, frame, "imu", events=[reason, "imu bridge"])
        st.failures += 1
        st.counts["tracking_failures"] += 1
        st.lost += 1
        events = [reason]
        is_keyframe = g is not None and bool(g.active) and g.active[-1] == fid
        if is_keyframe:  # failed after it became a keyframe: its pose is the keyframe's
            st.last_fid = fid
        elif g is not None and g.active and st.last_fid is not None:
            if T_WC_pred is None:
                T_WC_pred = st.predict()
            ref = g.active[-1]
            st.records[fid] = RelativePose(ref, np.linalg.inv(st.keyframe_T_WC(ref)) @ T_WC_pred)
            st.last_fid = fid
        logger.info("frame %d: %s", frame.index, reason)
        restart = st.lost >= self.config.tracking.max_lost and g is not None and bool(g.keyframes)
        if restart:
            event, relocalised = self.starts.restart(fid, frame, before=self.rejoin.reference_before)
            events.append(event)
            # not relocalised: the new map's frames try to rejoin (frontends/rejoin.py); its keyframes come after
            # this frame (which may be the old map's last keyframe)
            self.rejoin.restarted(fid + 1, relocalised)
        return st.status(fid, frame, "motion_model", is_keyframe=is_keyframe and not restart, events=events,
                         new_map=restart)
