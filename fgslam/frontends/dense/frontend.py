"""The dense frontend (DROID-SLAM family): frame graph, dense bundle adjustment of 1/8-resolution
inverse depth through the backend, global optimisation, loop closure through the shared service.

Per frame (DROID-SLAM section 3.4, with the built-in DIS flow source of :mod:`.source`):

1. **tracking and motion filter**: the frame's pose is predicted (damped constant velocity) and
   optimised motion-only against the newest keyframe (its inverse-depth map held: the dense block's
   per-pixel damping set very high, so nothing flows into the depths), from the flow measured warm-
   started at the prediction; a frame whose share of confident grid pixels is below
   ``tracking.min_confident`` is a tracking failure (predicted pose, counted, never raised; after
   ``tracking.max_lost`` in a row the map restarts, relocalised through the loop service when it can);
2. when the mean measured flow exceeds ``graph.motion_filter_flow`` the frame becomes a keyframe:
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

The frontend owns the state and the per-frame steps; the work is in collaborators: step 1 in
:mod:`.tracking`, steps 2, 4 and the retirement of 5 in :mod:`.keyframes`, steps 3 and 5's global
optimisation in :mod:`.ba`, the initialisation and map restart in :mod:`.lifecycle`, the loop hand-over
and contributor contract in :mod:`.contributor`, depth and point export in :mod:`.export`.
"""

from __future__ import annotations

import logging
import time

import cv2
import numpy as np

from ...backend.graph import Backend
from ...errors import ConfigError, OptimizationError
from ...factors.reprojection import ReprojectionConfig
from ...factors.schur import torch_threads
from ..base import BackendFrontend, FrameStatus, SensorMode
from ..depth_tracking import DepthTracking
from ..records import per_frame_motion
from ..records import RelativePose, resolve_pose, rigid, sim3_power
from .config import DenseConfig
from .graph import DenseKeyframeState, FrameGraph
from ..flow import grid_intrinsics
from .source import make_dense_source
from .ba import DenseBA
from .contributor import DenseLoopContributor
from .export import keyframe_depths, keyframe_points
from .keyframes import DenseKeyframes
from .lifecycle import DenseMapStarts
from .tracking import DenseTracker
from .weights import textured_share

logger = logging.getLogger(__name__)


class DenseFrontend(BackendFrontend):
    """DROID-SLAM-style dense frontend (module docstring); builder of the ``dense`` family.

    Args as :class:`fgslam.frontends.patch.PatchFrontend`: ``config`` the ``dense`` section,
    ``calibration`` (None: the first frame's), ``sensor_mode`` mono | stereo | rgbd, ``backend`` (the
    run's backend; every keyframe pose lives there). Loop closure reaches it through the loop port the
    system connects (the frontend is the loop service's contributor).

    The frontend owns the state (graph, source, calibration, pose records, motion model, counts, stage
    times) and runs the per-frame steps; its collaborators read and write that state through it:
    ``tracker`` (:class:`.tracking.DenseTracker`), ``keyframes`` (:class:`.keyframes.DenseKeyframes`),
    ``ba`` (:class:`.ba.DenseBA`), ``starts`` (:class:`.lifecycle.DenseMapStarts`) and
    ``loop_contributor`` (:class:`.contributor.DenseLoopContributor`).
    """

    name = "dense"
    _skip_nonfinite_poses = True  # a diverged motion-only solve leaves no pose (not a non-finite one)

    def __init__(self, config: DenseConfig | None = None, calibration=None, sensor_mode: SensorMode = "mono",
                 backend: Backend | None = None):
        self._attach(config or DenseConfig(), sensor_mode, backend)
        self.source = make_dense_source(self.config.source)
        self.stride = int(self.config.source.stride)
        self._reproj = ReprojectionConfig(min_depth=self.config.ba.min_depth)
        self.depth = DepthTracking(self.config.depth_align, self.backend, active=sensor_mode == "rgbd")
        self.calibration = None
        self.graph: FrameGraph | None = None
        if calibration is not None:
            self._set_calibration(calibration)
        self._final: dict[int, DenseKeyframeState] = {}  # keyframes of earlier maps (after a restart)
        self._initialized = False
        self._last_fid: int | None = None
        self._velocity = np.eye(4)
        self._motion_prior = None  # the IMU service's prediction (connect): tracking prior and bridge
        self._lost = 0
        self._failures = 0
        self._counts = {"keyframes_added": 0, "keyframes_removed": 0, "tracking_failures": 0, "map_restarts": 0,
                        "global_runs": 0, "low_confidence_frames": 0, "low_texture_frames": 0,
                        "edges_kept": 0}
        self._new_since_global = 0
        self._loop_edges: set[tuple[int, int]] = set()  # proximity loop edges kept by a global optimisation (re-measured in every later one)
        self.proximity_gates = self.config.proximity
        self.background_global_ba = self.config.global_ba.background and self.config.global_ba.every > 0
        self._times = {"flow": 0.0, "tracking": 0.0, "ba": 0.0, "global": 0.0, "bookkeeping": 0.0}
        if self.depth.enabled:
            self._times["depth"] = 0.0  # surfaces and depth-only tracking of frames
            self._counts["depth_tracked"] = 0
        self._pending_origin: np.ndarray | None = None  # pose of the next map's first keyframe after a restart
        self._init_frames: dict[int, tuple[int, np.ndarray]] = {}  # monocular, before initialisation: fid -> (keyframe, image)
        self.tracker = DenseTracker(self)
        self.keyframes = DenseKeyframes(self)
        self.ba = DenseBA(self)
        self.starts = DenseMapStarts(self)
        self._contributor = DenseLoopContributor(self)

    # ------------------------------------------------------------------ calibration
    def _set_calibration(self, calibration) -> None:
        self.calibration = calibration
        self.K = np.asarray(calibration.K, dtype=np.float64)
        self.depth.set_intrinsics(self.K)
        self.width, self.height = int(calibration.width), int(calibration.height)
        s = self.stride
        if self.width < s or self.height < s:
            raise ConfigError(f"dense frontend: image size {self.width}x{self.height} is smaller than the grid stride {s}")
        # the grid covers the largest top-left region whose sides are multiples of the stride (same
        # intrinsics; the presets crop to multiples of 8 already, dataset.crop_multiple)
        self.crop = ((self.height // s) * s, (self.width // s) * s)
        if self.crop != (self.height, self.width):
            logger.info("dense frontend: %dx%d images; the grid covers the top-left %dx%d (dataset.crop_multiple: %d "
                        "avoids this)", self.width, self.height, self.crop[1], self.crop[0], s)
        self.K_grid = np.asarray(grid_intrinsics(self.K, s))
        self.T_CRCL = None
        self.K_right_grid = None
        if self.sensor_mode == "stereo":
            if calibration.right is None or calibration.T_CLCR is None:
                raise ConfigError("sensor mode stereo needs a calibration with a right camera and T_CLCR")
            self.T_CRCL = np.linalg.inv(np.asarray(calibration.T_CLCR, dtype=np.float64))
            self.K_right_grid = np.asarray(grid_intrinsics(np.asarray(calibration.right.K, dtype=np.float64), s))
        self.graph = FrameGraph(self.K_grid, (self.height // s, self.width // s), s, self._reproj, self._keyframe_T_WC)

    def _cropped(self, image: np.ndarray | None) -> np.ndarray | None:
        """The part of an image (or depth map) the grid covers."""
        if image is None:
            return None
        H, W = self.crop
        return image if image.shape[:2] == (H, W) else np.ascontiguousarray(image[:H, :W])

    def _source_image(self, frame, right: bool = False) -> np.ndarray:
        """The cropped image the source is fed: colour (RGB) for a source that takes it, else grey."""
        if self.source.colour:
            return self._cropped(frame.colour_or_grey(right))
        return self._cropped(frame.image_right if right else frame.image)

    # ------------------------------------------------------------------ Frontend API
    def num_keyframes(self) -> int:
        return (0 if self.graph is None else len(self.graph.keyframes)) + len(self._final)

    @property
    def num_failures(self) -> int:
        return self._failures

    @property
    def counts(self) -> dict[str, int]:
        return dict(self._counts)

    _numerical_errors = (OptimizationError, RuntimeError, np.linalg.LinAlgError, cv2.error)

    def _measuring(self):
        return torch_threads(self.config.threads)

    def _recover(self, fid: int, frame, exc: BaseException) -> FrameStatus:
        logger.warning("frame %d: dense frontend failed (%s); using the motion model", frame.index, exc)
        return self._fail(fid, frame, f"optimisation failed: {exc}")

    @property
    def map_started(self) -> bool:
        return self._initialized

    def finish(self) -> None:
        if self._initialized and self.config.global_ba.final and len(self.graph.keyframes) >= 3:
            self.ba.global_ba()
        self.contributor.feed(all_keyframes=True)

    def finish_map(self) -> None:
        logger.info("dense frontend: %d frames, %d keyframes, %d tracking failures, counts %s",
                    len(self._inputs), self.num_keyframes(), self._failures, self._counts)

    def keyframe_depths(self) -> dict[int, tuple[float, np.ndarray, np.ndarray | None]] | None:
        """Keyframe id -> (timestamp, depth (H, W) float32 in map units, confidence (H, W) in [0, 1])
        (:func:`.export.keyframe_depths`; pixels below ``point_confidence``: 0)."""
        kfs = self._all_keyframes()
        if not kfs:
            return None
        return keyframe_depths(kfs, self._keyframe_T_WC, (self.width, self.height), self.crop,
                               self.config.point_confidence)

    def keyframe_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Confidence-filtered grid points of every keyframe in the world frame, with their colours."""
        K_grid = self.K_grid if self.graph is not None else (1, 1, 0, 0)
        return keyframe_points(self._all_keyframes(), self._keyframe_T_WC, K_grid, self.config.point_confidence)

    # ------------------------------------------------------------------ frames and poses
    def _check_frame(self, frame) -> None:
        if frame.image.shape != (self.height, self.width):
            raise ConfigError(f"frame {frame.index}: image {frame.image.shape} does not match the calibration "
                              f"{self.width}x{self.height}")
        if self.sensor_mode == "stereo" and frame.image_right is None:
            raise ConfigError(f"frame {frame.index}: sensor mode stereo but the frame has no right image")
        if self.sensor_mode == "rgbd" and frame.depth is None:
            raise ConfigError(f"frame {frame.index}: sensor mode rgbd but the frame has no depth")

    def _all_keyframes(self) -> list[DenseKeyframeState]:
        return list(self._final.values()) + ([] if self.graph is None else list(self.graph.keyframes.values()))

    def _keyframe_T_WC(self, fid: int) -> np.ndarray:
        return self.backend.pose_matrix(fid)

    def _pose_of(self, fid: int) -> np.ndarray | None:
        return resolve_pose(fid, self._records, self._keyframe_T_WC, {})

    def _status(self, fid, frame, source, is_keyframe=False, num_valid=0, events=None) -> FrameStatus:
        T = self._pose_of(fid) if self._initialized else None
        return FrameStatus(index=int(frame.index), timestamp=float(frame.timestamp),
                           T_WC=None if T is None else rigid(T), pose_source=source, is_keyframe=is_keyframe,
                           num_valid=int(num_valid), events=list(events or []))

    def connect(self, loops=None, motion_prior=None) -> None:
        """Take the loop port and the motion prior (the IMU service's ``predict``): the prior is the
        tracking prediction when it gives a pose, and the pose of a frame the flow loses (``imu``)."""
        super().connect(loops)
        self._motion_prior = motion_prior

    def _prior_pose(self, timestamp: float | None) -> np.ndarray | None:
        """The motion prior's ``T_WC`` at ``timestamp`` once the map is initialised (rigid for a metric
        map, whose keyframes are at scale 1 as the constant-velocity prediction's), else None."""
        if self._motion_prior is None or timestamp is None or not self._initialized:
            return None
        T_WC = self._motion_prior(float(timestamp))
        if T_WC is None:
            return None
        return rigid(T_WC) if self.metric_scale else T_WC

    def _predict(self, timestamp: float | None = None) -> np.ndarray:
        """The motion prior's pose at ``timestamp`` when it gives one, else the damped constant velocity."""
        T_WC_prior = self._prior_pose(timestamp)
        if T_WC_prior is not None:
            return T_WC_prior
        T_WC_last = self._pose_of(self._last_fid) if self._last_fid is not None else None
        if T_WC_last is None:
            return np.eye(4) if self._pending_origin is None else self._pending_origin
        return T_WC_last @ sim3_power(self._velocity, self.config.tracking.motion_damping)

    def _update_velocity(self, fid: int) -> None:
        if self._last_fid is not None:
            T_WC_prev, T_WC_new = self._pose_of(self._last_fid), self._pose_of(fid)
            if T_WC_prev is not None and T_WC_new is not None:
                self._velocity = per_frame_motion(T_WC_prev, T_WC_new, fid - self._last_fid)
        self._last_fid = fid

    # ------------------------------------------------------------------ per frame
    def _surface(self, frame):
        """The frame's depth surface (RGB-D depth alignment; None when off), made once per frame."""
        if not self.depth.enabled:
            return None
        t0 = time.perf_counter()
        surface = self.depth.surface(self._cropped(frame.depth))
        self._times["depth"] += time.perf_counter() - t0
        return surface

    def _measure_frame(self, fid: int, frame) -> FrameStatus:
        g = self.graph
        surface = self._surface(frame)
        if not g.keyframes:  # the first keyframe of a map
            T_WC0 = self._pending_origin if self._pending_origin is not None else np.eye(4)
            self._pending_origin = None
            self.keyframes.add(fid, frame, T_WC0, surface=surface)
            self._velocity = np.eye(4)
            self._last_fid = fid
            if self.sensor_mode != "mono":
                self._initialized = True
                return self._status(fid, frame, "tracked", is_keyframe=True, events=["initialised"])
            return self._status(fid, frame, "initializing", is_keyframe=True)
        t0 = time.perf_counter()
        kf_fid = g.active[-1]
        T_WC_pred = self._predict(frame.timestamp)
        events = []
        added = False
        textured = textured_share(self._cropped(frame.image), self.stride, self.config.tracking.texture_gradient)
        if textured < self.config.tracking.min_textured:
            held = self.tracker.by_depth(kf_fid, fid, T_WC_pred, surface, with_image=False)
            if held is None:
                self._counts["low_texture_frames"] += 1
                return self._fail(fid, frame, f"tracking lost: no texture ({100 * textured:.1f} % of the grid textured)", T_WC_pred)
            (T_WC, flow), n_conf = held, 0
            events.append(f"tracked by depth alone (no texture: {100 * textured:.1f} % of the grid textured)")
        else:
            flow0 = self._times["flow"]
            self.source.add_frame(fid, self._source_image(frame))
            added = True
            T_WC, flow, n_conf, ok = self.tracker.track(kf_fid, fid, T_WC_pred, surface)
            self._times["tracking"] += time.perf_counter() - t0 - (self._times["flow"] - flow0)
            n_pix = g.shape[0] * g.shape[1]
            if not ok or n_conf < self.config.tracking.min_confident * n_pix:
                held = self.tracker.by_depth(kf_fid, fid, T_WC_pred, surface, with_image=True)
                if held is None:
                    self.source.remove_frame(fid)
                    self._counts["low_confidence_frames"] += 1
                    return self._fail(fid, frame, f"tracking lost: {n_conf} of {n_pix} grid pixels confident", T_WC_pred)
                T_WC, flow = held
                events.append(f"tracked by depth ({n_conf} of {n_pix} grid pixels confident)")
        if events:
            self._counts["depth_tracked"] += 1
        self._lost = 0
        if flow <= self.config.graph.motion_filter_flow:
            if added:
                self.source.remove_frame(fid)
            self._records[fid] = RelativePose(kf_fid, np.linalg.inv(self._keyframe_T_WC(kf_fid)) @ T_WC)
            if not self._initialized:  # tracked against a provisional depth map: re-tracked after the initialisation
                self._init_frames[fid] = (kf_fid, self._source_image(frame))
            self._update_velocity(fid)
            source = "tracked" if self._initialized else "initializing"
            return self._status(fid, frame, source, num_valid=n_conf, events=events)
        self.keyframes.add(fid, frame, T_WC, source_added=added, surface=surface)
        if not self._initialized:
            if len(g.keyframes) >= self.config.graph.init_keyframes:
                self.starts.initialize()
                events.append("initialised")
            self._update_velocity(fid)
            return self._status(fid, frame, "tracked" if self._initialized else "initializing", True, n_conf, events)
        self.ba.local(fid)
        removed = self.keyframes.remove_redundant()
        if removed is not None:
            events.append(f"keyframe removed: {removed}")
        elif self.config.ba.kept_rounds:  # DROID-SLAM: more update iterations when the keyframe stays
            self.ba.local(fid, self.config.ba.kept_rounds)
        self.keyframes.retire()
        self._update_velocity(fid)
        self._new_since_global += 1
        every = self.config.global_ba.every
        if every and self._new_since_global >= every:
            self.ba.global_ba(background=True)
        return self._status(fid, frame, "tracked", fid in g.keyframes, n_conf, events)

    def _fail(self, fid: int, frame, reason: str, T_WC_pred: np.ndarray | None = None) -> FrameStatus:
        """Tracking failure: the motion prior's pose when it gives one (bridged by the IMU: ``imu``, not a
        failure), else the predicted pose relative to the newest keyframe, counted; a map restart after
        ``tracking.max_lost`` in a row."""
        g = self.graph
        T_WC_imu = self._prior_pose(frame.timestamp)
        if T_WC_imu is not None and g is not None and g.active and self._last_fid is not None:
            ref = g.active[-1]
            self._records[fid] = RelativePose(ref, np.linalg.inv(self._keyframe_T_WC(ref)) @ T_WC_imu)
            self._last_fid = fid
            logger.info("frame %d: %s; pose from the IMU", frame.index, reason)
            return self._status(fid, frame, "imu", events=[reason, "imu bridge"])
        self._failures += 1
        self._counts["tracking_failures"] += 1
        self._lost += 1
        events = [reason]
        if g is not None and g.active and self._last_fid is not None:
            if T_WC_pred is None:
                T_WC_pred = self._predict()
            ref = g.active[-1]
            self._records[fid] = RelativePose(ref, np.linalg.inv(self._keyframe_T_WC(ref)) @ T_WC_pred)
            self._last_fid = fid
        logger.info("frame %d: %s", frame.index, reason)
        if self._lost >= self.config.tracking.max_lost and g is not None and g.keyframes:
            events.append(self.starts.restart(fid, frame))
        return self._status(fid, frame, "motion_model", events=events)
