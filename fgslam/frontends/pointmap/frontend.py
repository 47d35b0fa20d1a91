"""The pointmap frontend (MASt3R-SLAM family): two-view pointmaps, projective matching, ray-error tracking,
pointmap fusion, Sim(3) keyframe graph through the run's backend, relocalisation.

Per frame (frames resized to ``image_width``; ``K`` scaled alike):

1. the source caches the frame (:mod:`.source`: RGB-D depth, stereo SGBM, or the monocular two-view
   reconstruction) and predicts the pair (current keyframe k, frame f): ``X_f^f`` and ``X_f^k``. Metric
   sources move ``X_f^f`` by the previous frame's relative pose (the warm start); the two-view source
   predicts the pair in its own arbitrary scale, aligned to k's canonical pointmap by the median ratio
   of the two pointmaps of k (``T_CkCf`` then carries that scale);
2. iterative projective matching (:mod:`.matching`, section 3.2) of every ``query_stride``-th pixel of f
   into k's canonical ray image, warm started from the previous frame's matches (the projection of the
   query points after a keyframe change), with descriptor refinement;
3. tracking (:mod:`.tracking`, section 3.3): ``T_CkCf`` by Gauss-Newton IRLS on the residuals of
   ``block.mode`` (ray + distance, eqs. 7-8; or calibrated pixel + log depth, section 3.7), Huber and the
   confidence weighting of eq. 6; SE(3) for metric sources, Sim(3) otherwise (``tracking.scale``);
4. fusion (eq. 9): the matched points of f, moved into k, update k's canonical pointmap;
5. when the valid matches fall below ``keyframe.new_fraction`` of f's valid points, f becomes a keyframe
   (its own pointmap is its canonical one, its pose ``T_WCk T_CkCf``) with an edge to k made of the
   tracking's inlier matches (at most ``graph.max_edge_matches``);
6. each new keyframe goes to the backend (``add_keyframe``), the family's blocks are replaced by one
   :class:`~fgslam.factors.pointmap_block.PointmapBlock` over every edge (``set_blocks("pointmap", ...)``:
   per edge one 14 x 14 piece, the compressed block of section 3.5), the first keyframe carries the 7-dof
   anchor (``set_gauge``: no range, the scale is real; for Sim(3) tracking the backend's per-keyframe
   scale priors are switched off) and ``optimize_window`` runs at most ``graph.iterations`` LM iterations
   over the newest ``graph.window`` keyframes (0: all, the global optimisation);
7. tracking failure (too few valid matches or inliers, no two-view pose): relocalisation (section 3.6)
   against the loop service's retrieval (when loop closure is on) and the newest keyframes; an accepted
   candidate becomes the current keyframe (``relocalized``); otherwise the frame keeps the pose predicted
   from the last tracked one (``motion_model``, counted, logged, never raised).

Monocular frames (``features.mode: features``, the default; issue 28) are posed by :mod:`.features`:
the keyframe's corners tracked by KLT and PnP against k's canonical pointmap, their triangulations fused
into it; only a new keyframe runs steps 1-5 (its pair triangulated with the measured pose); a frame the
corners cannot pose is tried with the two-view pair, then relocalised, else reported lost. With
``features.mode: two_view``, monocular frames without enough parallax for a two-view pointmap (the source
logs it) are tracked by PnP on the source's dense flow against k's canonical pointmap (pose only, no
fusion, never a keyframe). The
monocular map starts when a pair (first frame, later frame) has ``tracking.init_min_confident`` of its
pixels confident; frames before it get no pose.

Loop closure is the shared :class:`~fgslam.services.loops.LoopService` (classical: BoW retrieval,
verification, Sim(3) pose graph, corrections through :meth:`apply_correction`); each loop it accepts is
measured as a pointmap edge (:func:`.keyframes.measure_edge`, accepted with ``graph.min_edge_matches``)
and joins the global optimisation. Non-keyframe poses are :mod:`fgslam.frontends.records` relative to
their keyframe.

The frontend owns the shared state (:class:`~.state.PointmapState`) and runs the per-frame steps (the
frame's inputs, the map's start, the dispatch to the tracking of the frame, the motion model's pose of a
lost frame); the work is in collaborators, each given the state and the collaborators it calls: steps
1-3 against one keyframe in :mod:`.tracker` (the source's frames in :mod:`.cache`), the frame's tracking
by the pair of pointmaps (with the look-back keyframe and the PnP and depth fallbacks) in
:mod:`.pair_tracking`, the monocular features' pose in :mod:`.feature_tracking`, step 4, 5 and the map
start in :mod:`.mapping`, step 6 and the loop edges in :mod:`.edges`, step 7 in :mod:`.relocalization`,
the contributor contract in :mod:`.contributor`, the outputs in :mod:`.export`, the working resolution
in :mod:`.camera`.
"""

from __future__ import annotations

import contextlib
import logging
import time

import numpy as np
import torch

from ...backend.graph import Backend
from ...core.errors import ConfigError, DataError, OptimizationError
from ...factors.schur import torch_threads
from ..base import BackendFrontend, FrameStatus, LoopPort, MotionPrior, SensorMode
from ..records import RelativePose
from .cache import SourceCache
from .config import PointmapConfig
from .contributor import PointmapLoopContributor
from .edges import PointmapGraph
from .export import keyframe_depths, keyframe_points
from .feature_tracking import FeatureTracking
from .mapping import PointmapKeyframing
from .pair_tracking import PairTracking
from .source import PointmapPair
from .state import PointmapState
from .tracker import PointmapTracker, TrackingLost

logger = logging.getLogger(__name__)

__all__ = ["PointmapFrontend"]


class PointmapFrontend(BackendFrontend):
    """MASt3R-SLAM-style pointmap frontend (module docstring); a contributor of the run's backend.

    Args:
        config: the ``pointmap`` section (defaults when None).
        calibration: the frames' calibration (None: from the first frame).
        sensor_mode: ``mono``, ``stereo`` or ``rgbd`` (``source.kind: auto`` follows it).
        backend: the run's backend (as for every family; loop closure reaches it through the loop
            port the system connects).

    The frontend owns the shared state ``state`` (:class:`~.state.PointmapState`: keyframes, the current
    keyframe and the last tracked ``T_CkCf``, pose records, counts, stage times) and runs the per-frame
    steps; its collaborators each take that state: ``source_cache`` (:class:`.cache.SourceCache`),
    ``tracker`` (:class:`.tracker.PointmapTracker`), ``graph`` (:class:`.edges.PointmapGraph`),
    ``keyframing`` (:class:`.mapping.PointmapKeyframing`), ``pair_tracking``
    (:class:`.pair_tracking.PairTracking`), ``feature_tracking``
    (:class:`.feature_tracking.FeatureTracking`) and ``contributor``
    (:class:`.contributor.PointmapLoopContributor`, what the services talk to).
    """

    name = "pointmap"

    def __init__(self, config: PointmapConfig | None = None, calibration=None, sensor_mode: SensorMode = "mono",
                 backend: Backend | None = None):
        self._attach(config or PointmapConfig(), sensor_mode, backend)
        self.state = st = PointmapState(self.config, sensor_mode, self.backend, self._records, self._inputs,
                                        self._sources)
        self.metric_scale = st.fixed_scale  # loop corrections are SE(3) on a fixed-scale map
        self._times = st.times  # the base class's stage times
        self.source_cache = SourceCache(st)
        self.tracker = PointmapTracker(st, self.source_cache)
        self.graph = PointmapGraph(st, self.name)
        self.keyframing = PointmapKeyframing(st, self.source_cache, self.graph)
        self.pair_tracking = PairTracking(st, self.tracker, self.keyframing)
        self.feature_tracking = FeatureTracking(st, self.source_cache, self.tracker, self.keyframing, self.graph)
        self._contributor = PointmapLoopContributor(st, self.graph, self.name)
        if calibration is not None:
            self._set_calibration(calibration)

    # ------------------------------------------------------------------ setup
    def _set_calibration(self, calibration) -> None:
        self.calibration = calibration
        self.state.set_calibration(calibration)

    def _has_calibration(self) -> bool:
        return self.state.cam is not None

    @property
    def uses_compiled_kernels(self) -> bool:
        """Projective matching (every source kind) is a compiled kernel."""
        return True

    def connect(self, loops: LoopPort | None = None, motion_prior: MotionPrior | None = None) -> None:
        """Take the loop port and the motion prior (the IMU service's ``predict``): the prediction of a
        metric frame the image cannot measure, and the pose of a frame tracking loses (``imu``)."""
        super().connect(loops)
        self.state.loops = self.loops
        self.state.motion_prior = motion_prior

    # ------------------------------------------------------------------ Frontend API
    def num_keyframes(self) -> int:
        return len(self.state.kfs)

    @property
    def num_failures(self) -> int:
        return self.state.failures

    @property
    def map_started(self) -> bool:
        return self.state.kf is not None

    def corrections_applied(self) -> None:
        self.graph.loop_edges()

    def finish_map(self) -> None:
        self.graph.loop_edges()
        self.graph.final_optimize()
        logger.info("pointmap frontend: %d frames, %d keyframes, %d edges, %d tracking failures, %s",
                    len(self._inputs), len(self.state.kfs), len(self.graph.edges), self.state.failures,
                    self.state.counts)

    def keyframe_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Canonical pointmaps in the world, coloured (:func:`.export.keyframe_points`: every ``ply_stride``-th
        pixel with a fused confidence of at least ``ply_min_confidence``)."""
        return keyframe_points(self.state.kfs.values(), self.state.keyframe_T_WC, self.config.ply_stride,
                               self.config.ply_min_confidence)

    def keyframe_depths(self) -> dict[int, tuple[float, np.ndarray, np.ndarray | None]] | None:
        """kf id -> (timestamp, depth (H, W) float32 in the map's scale at the input resolution, confidence
        (H, W) in [0, 1]) (:func:`.export.keyframe_depths`)."""
        st = self.state
        if not st.kfs:
            return None
        return keyframe_depths(st.kfs.values(), st.keyframe_T_WC, st.cam.full)

    def add_loop_counts(self, summary: dict) -> None:
        summary["pointmap_loop_edges"] = self.state.counts["loop_edges"]

    # ------------------------------------------------------------------ the per-frame skeleton's hooks
    _numerical_errors = (OptimizationError, RuntimeError, np.linalg.LinAlgError, DataError)

    @contextlib.contextmanager
    def _measuring(self):
        with torch_threads(self.config.threads), torch.no_grad():
            yield

    def _check_frame(self, frame) -> None:
        st = self.state
        W, H = st.cam.full
        if frame.image.shape[:2] != (H, W):
            raise ConfigError(f"frame {frame.index}: image {frame.image.shape} does not match the calibration {W}x{H}")
        if st.kind == "stereo" and frame.image_right is None:
            raise ConfigError(f"frame {frame.index}: the stereo pointmap source needs a right image")
        if st.kind == "rgbd" and frame.depth is None:
            raise ConfigError(f"frame {frame.index}: the RGB-D pointmap source needs a depth image")

    def _keyframe_T_WC(self, fid: int) -> np.ndarray:
        return self.state.keyframe_T_WC(fid)

    def _recover(self, fid: int, frame, exc: BaseException) -> FrameStatus:
        logger.warning("pointmap frame %d: %s: %s; using the motion model", frame.index, type(exc).__name__, exc)
        return self._fail(fid, frame, f"failed: {exc}")

    def _after_frame(self, fid: int, frame, status: FrameStatus) -> None:
        st = self.state
        tracked = status.pose_source in ("tracked", "relocalized") and st.kf is not None
        st.prev_fid, st.prev_kf = (fid, st.kf.fid) if tracked else (None, None)
        self.source_cache.release(fid)

    # ------------------------------------------------------------------ frames
    def _measure_frame(self, fid: int, frame) -> FrameStatus:
        st = self.state
        st.T_WC_imu = None  # set by the pair tracking (and _fail) for this frame
        grey = st.cam.image(frame.image)
        depth = st.cam.depth(frame.depth) if st.kind == "rgbd" else None
        right = st.cam.image(frame.image_right) if st.kind == "stereo" else None
        colour = st.cam.image(frame.rgb) if frame.rgb is not None else None
        if st.features is None or st.kf is None:  # the features' frames join the source when needed
            self.source_cache.add(fid, grey, depth, right)
        st.frame_surface = None
        if st.depth.enabled:  # made once per frame; a keyframe keeps it
            t0 = time.perf_counter()
            st.frame_surface = st.depth.surface(depth)
            st.times["depth"] += time.perf_counter() - t0
        inputs = (grey, colour, depth, right)
        if st.kf is None:
            return self._start_map(fid, frame, inputs)
        return self._track_frame(fid, frame, inputs)

    def _start_map(self, fid: int, frame, inputs) -> FrameStatus:
        """The map's start (:meth:`.mapping.PointmapKeyframing.initialize`); a monocular start tracks the frame
        against the new keyframe with the starting pair, then (features) starts the keyframe's corners."""
        started = self.keyframing.initialize(fid, frame, inputs)
        if isinstance(started, FrameStatus):
            return started
        status = self._track_frame(fid, frame, inputs, pair=started)
        if self.state.features is not None:  # the corners of the map's keyframe, tracked from here on
            self.feature_tracking.start(fid, inputs[0])
        status.events.append("initialised")
        return status

    def _track_frame(self, fid: int, frame, inputs, pair: PointmapPair | None = None) -> FrameStatus:
        """Frame ``fid`` tracked against the current keyframe: monocular frames by the features (but with
        ``pair``, the map's start), the others by the pair of pointmaps; a lost frame gets :meth:`_fail`'s
        pose."""
        if self.state.features is not None and pair is None:  # monocular: the pose of every frame by the corners
            tracked = self.feature_tracking.track(fid, frame, inputs)
        else:
            tracked = self.pair_tracking.track(fid, frame, inputs, pair)
        if isinstance(tracked, TrackingLost):
            status = self._fail(fid, frame, tracked.reason)
            status.events[:0] = tracked.events
            return status
        return tracked

    def _fail(self, fid: int, frame, reason: str) -> FrameStatus:
        """Tracking lost: the motion prior's pose when it gives one (bridged by the IMU: ``imu``, not a
        failure), else the last tracked relative pose (``motion_model``, counted)."""
        st = self.state
        keyframe = st.kf is not None and st.kf.fid == fid  # failed after it became the keyframe: its pose is the keyframe's
        if not keyframe:
            st.T_WC_imu = st.prior_T_WC(frame.timestamp)
            T_CkCf_imu = None if st.kf is None else st.prior_T_CkCf(st.kf.fid)
            if T_CkCf_imu is not None:
                st.T_CkCf = T_CkCf_imu
                st.records[fid] = RelativePose(st.kf.fid, T_CkCf_imu.copy())
                st.uv_prev = None
                logger.info("pointmap frame %d: %s; pose from the IMU", frame.index, reason)
                return st.status(fid, frame, "imu", events=[reason, "imu bridge"])
        st.failures += 1
        st.counts["failed"] += 1
        logger.info("pointmap frame %d: %s", frame.index, reason)
        if st.kf is None:
            return st.status(fid, frame, "initializing", events=[reason])
        if keyframe:
            st.T_CkCf = np.eye(4)
        else:
            st.records[fid] = RelativePose(st.kf.fid, st.T_CkCf.copy())  # the last tracked relative pose
        st.uv_prev = None
        return st.status(fid, frame, "motion_model", is_keyframe=keyframe, events=[reason])
