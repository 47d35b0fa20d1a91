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

The frontend owns the state and the per-frame steps; the work is in collaborators: steps 1-3 and the PnP
fallback in :mod:`.tracker` (the source's frames in :mod:`.cache`), step 4, 5 and the map start in
:mod:`.mapping`, step 6 and the loop edges in :mod:`.edges`, step 7 in :mod:`.relocalization`, the
contributor contract in :mod:`.contributor`, the outputs in :mod:`.export`, the working resolution in
:mod:`.camera`.
"""

from __future__ import annotations

import contextlib
import logging
import time

import numpy as np
import torch

from ...backend.graph import Backend
from ...errors import ConfigError, DataError, OptimizationError
from ...factors.schur import torch_threads
from ..base import BackendFrontend, FrameStatus, SensorMode
from ..depth_tracking import DepthTracking
from ..records import RelativePose, resolve_pose, rigid
from .config import PointmapConfig
from .keyframes import PointmapKeyframe, query_grid
from .source import make_pointmap_source
from .cache import SourceCache
from .camera import WorkingCamera
from .contributor import PointmapLoopContributor
from .edges import PointmapGraph
from .export import keyframe_depths, keyframe_points
from .features import FeatureTracks
from .mapping import PointmapKeyframing
from .relocalization import relocalize
from .tracker import PointmapTracker, matrix_of

logger = logging.getLogger(__name__)

__all__ = ["PointmapFrontend", "WorkingCamera"]


class PointmapFrontend(BackendFrontend):
    """MASt3R-SLAM-style pointmap frontend (module docstring); a contributor of the run's backend.

    Args:
        config: the ``pointmap`` section (defaults when None).
        calibration: the frames' calibration (None: from the first frame).
        sensor_mode: ``mono``, ``stereo`` or ``rgbd`` (``source.kind: auto`` follows it).
        backend: the run's backend (as for every family; loop closure reaches it through the loop
            port the system connects).

    The frontend owns the state (keyframes ``_kfs``, the current keyframe ``_kf`` and the last tracked
    ``T_CkCf``, pose records, counts, stage times) and runs the per-frame steps; its collaborators read
    and write that state through it: ``source_cache`` (:class:`.cache.SourceCache`), ``tracker``
    (:class:`.tracker.PointmapTracker`, relocalisation :func:`.relocalization.relocalize`), ``keyframing``
    (:class:`.mapping.PointmapKeyframing`), ``graph`` (:class:`.edges.PointmapGraph`) and
    ``loop_contributor`` (:class:`.contributor.PointmapLoopContributor`).
    """

    name = "pointmap"

    def __init__(self, config: PointmapConfig | None = None, calibration=None, sensor_mode: SensorMode = "mono",
                 backend: Backend | None = None):
        self._attach(config or PointmapConfig(), sensor_mode, backend)
        self.kind = self.config.source_kind(sensor_mode)
        if self.kind == "rgbd" and sensor_mode != "rgbd":
            raise ConfigError(f"pointmap.source.kind=rgbd needs sensor: rgbd (the run's sensor is {sensor_mode})")
        if self.kind == "stereo" and sensor_mode != "stereo":
            raise ConfigError(f"pointmap.source.kind=stereo needs sensor: stereo (the run's sensor is {sensor_mode})")
        scale = self.config.tracking.scale
        self.fixed_scale = (self.kind in ("rgbd", "stereo")) if scale == "auto" else scale == "fixed"
        self.metric_scale = self.fixed_scale  # loop corrections are SE(3) on a fixed-scale map
        if not self.fixed_scale and self.backend.config.gauge.hold_scale:
            # the pointmaps' scale is real (docs/design.md section 4): no per-keyframe log-scale priors
            logger.info("pointmap frontend: Sim(3) keyframes, map.gauge.hold_scale switched off")
            self.backend.config.gauge.hold_scale = False
        self.source = None
        self.features: FeatureTracks | None = None  # monocular: the per-frame pose by corners (issue 28)
        self.cam: WorkingCamera | None = None
        self._kfs: dict[int, PointmapKeyframe] = {}  # every keyframe, insertion order
        self._kf: PointmapKeyframe | None = None  # the current keyframe
        self._T_CkCf = np.eye(4)  # last tracked frame relative to the current keyframe
        self._motion_prior = None  # the IMU service's prediction (connect)
        self._T_WC_imu: np.ndarray | None = None  # the current frame's pose from the motion prior (None: none)
        self._uv_prev: torch.Tensor | None = None  # previous frame's matches into the current keyframe
        self._since_kf = 0
        self._init_fid: int | None = None
        self._prev_fid: int | None = None  # the previous frame when it was tracked (its pose is _T_CkCf)
        self._prev_kf: int | None = None  # ... and its keyframe
        self._last_good = None  # (fid, frame, inputs, result, T_CkCf) of the last frame tracked against the keyframe
        self._failures = 0
        self._times = {"source": 0.0, "matching": 0.0, "tracking": 0.0, "optimization": 0.0, "bookkeeping": 0.0}
        self._counts = {"keyframes": 0, "loop_edges": 0, "relocalized": 0, "pnp_tracked": 0, "failed": 0}
        if self.kind == "mono" and self.config.features.mode == "features":
            self._counts["feature_tracked"] = 0  # frames posed by the corners alone (not keyframes)
        self.depth = DepthTracking(self.config.depth_align, self.backend, active=self.kind == "rgbd")
        self._frame_surface = None  # the current frame's depth surface (RGB-D depth alignment)
        if self.depth.enabled:
            self._times["depth"] = 0.0  # surfaces and depth-only tracking of frames
            self._counts["depth_tracked"] = 0  # frames tracked by depth alone
        self.source_cache = SourceCache(self)
        self.tracker = PointmapTracker(self)
        self.keyframing = PointmapKeyframing(self)
        self.graph = PointmapGraph(self)
        self._contributor = PointmapLoopContributor(self)
        if calibration is not None:
            self._set_calibration(calibration)

    # ------------------------------------------------------------------ setup
    def _set_calibration(self, calibration) -> None:
        self.calibration = calibration
        self.cam = WorkingCamera(calibration, self.config.image_width, self.sensor_mode)
        src_cfg = self.config.source
        if src_cfg.kind == "auto":
            from dataclasses import replace

            src_cfg = replace(src_cfg, kind=self.kind)
        self.source = make_pointmap_source(src_cfg, self.cam.K, baseline=self.cam.baseline)
        self.query = query_grid(self.cam.H, self.cam.W, self.config.query_stride)
        self.K_t = torch.as_tensor(self.cam.K)
        self.depth.set_intrinsics(self.cam.K)
        if self.kind == "mono" and self.config.features.mode == "features":
            self.features = FeatureTracks(self.config.features, self.cam.K)

    # ------------------------------------------------------------------ Frontend API
    def num_keyframes(self) -> int:
        return len(self._kfs)

    @property
    def num_failures(self) -> int:
        return self._failures

    _numerical_errors = (OptimizationError, RuntimeError, np.linalg.LinAlgError, DataError)

    def _has_calibration(self) -> bool:
        return self.cam is not None

    @contextlib.contextmanager
    def _measuring(self):
        with torch_threads(self.config.threads), torch.no_grad():
            yield

    def _recover(self, fid: int, frame, exc: BaseException) -> FrameStatus:
        logger.warning("pointmap frame %d: %s: %s; using the motion model", frame.index, type(exc).__name__, exc)
        return self._fail(fid, frame, f"failed: {exc}")

    def _after_frame(self, fid: int, frame, status: FrameStatus) -> None:
        tracked = status.pose_source in ("tracked", "relocalized") and self._kf is not None
        self._prev_fid, self._prev_kf = (fid, self._kf.fid) if tracked else (None, None)
        self.source_cache.release()

    @property
    def map_started(self) -> bool:
        return self._kf is not None

    def corrections_applied(self) -> None:
        self.graph.loop_edges()

    def finish_map(self) -> None:
        self.graph.loop_edges()
        self.graph.final_optimize()
        logger.info("pointmap frontend: %d frames, %d keyframes, %d edges, %d tracking failures, %s",
                    len(self._inputs), len(self._kfs), len(self.graph.edges), self._failures, self._counts)

    def keyframe_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Canonical pointmaps in the world, coloured (:func:`.export.keyframe_points`: every ``ply_stride``-th
        pixel with a fused confidence of at least ``ply_min_confidence``)."""
        return keyframe_points(self._kfs.values(), self._keyframe_T_WC, self.config.ply_stride,
                               self.config.ply_min_confidence)

    def keyframe_depths(self) -> dict[int, tuple[float, np.ndarray, np.ndarray | None]] | None:
        """kf id -> (timestamp, depth (H, W) float32 in the map's scale at the input resolution, confidence
        (H, W) in [0, 1]) (:func:`.export.keyframe_depths`)."""
        if not self._kfs:
            return None
        return keyframe_depths(self._kfs.values(), self._keyframe_T_WC, self.cam.full)

    def add_loop_counts(self, summary: dict) -> None:
        summary["pointmap_loop_edges"] = self._counts["loop_edges"]

    @staticmethod
    def backend_key(fid: int) -> int:
        from ...backend.keys import pose_key

        return pose_key(fid)

    # ------------------------------------------------------------------ frames
    def _check_frame(self, frame) -> None:
        W, H = self.cam.full
        if frame.image.shape[:2] != (H, W):
            raise ConfigError(f"frame {frame.index}: image {frame.image.shape} does not match the calibration {W}x{H}")
        if self.kind == "stereo" and frame.image_right is None:
            raise ConfigError(f"frame {frame.index}: the stereo pointmap source needs a right image")
        if self.kind == "rgbd" and frame.depth is None:
            raise ConfigError(f"frame {frame.index}: the RGB-D pointmap source needs a depth image")

    def _keyframe_T_WC(self, fid: int) -> np.ndarray:
        return self.backend.pose_matrix(fid)

    def _pose_of(self, fid: int) -> np.ndarray | None:
        return resolve_pose(fid, self._records, self._keyframe_T_WC, {})

    def _status(self, fid, frame, source, is_keyframe=False, num_valid=0, events=None) -> FrameStatus:
        T = self._pose_of(fid)
        return FrameStatus(int(frame.index), float(frame.timestamp), None if T is None else rigid(T), source,
                           is_keyframe, int(num_valid), list(events or []))

    def _measure_frame(self, fid: int, frame) -> FrameStatus:
        self._T_WC_imu = None  # set by _track_frame (and _fail) for this frame
        grey = self.cam.image(frame.image)
        depth = self.cam.depth(frame.depth) if self.kind == "rgbd" else None
        right = self.cam.image(frame.image_right) if self.kind == "stereo" else None
        colour = self.cam.image(frame.rgb) if frame.rgb is not None else None
        if self.features is None or self._kf is None:  # the features' frames join the source when needed
            self.source_cache.add(fid, grey, depth, right)
        self._frame_surface = None
        if self.depth.enabled:  # made once per frame; a keyframe keeps it
            t0 = time.perf_counter()
            self._frame_surface = self.depth.surface(depth)
            self._times["depth"] += time.perf_counter() - t0
        inputs = (grey, colour, depth, right)
        if self._kf is None:
            return self.keyframing.initialize(fid, frame, inputs)
        return self._track_frame(fid, frame, inputs)

    def connect(self, loops=None, motion_prior=None) -> None:
        """Take the loop port and the motion prior (the IMU service's ``predict``): the prediction of a
        metric frame the image cannot measure, and the pose of a frame tracking loses (``imu``)."""
        super().connect(loops)
        self._motion_prior = motion_prior

    def _prior_T_WC(self, timestamp: float) -> np.ndarray | None:
        """The motion prior's ``T_WC`` of the frame at ``timestamp`` once the map has a keyframe, or None."""
        if self._motion_prior is None or self._kf is None:
            return None
        return self._motion_prior(float(timestamp))

    def prior_T_CkCf(self, kf_fid: int) -> np.ndarray | None:
        """The current frame's motion-prior pose relative to keyframe ``kf_fid`` (rigid on a metric map), or None."""
        if self._T_WC_imu is None:
            return None
        T_CkCf = np.linalg.inv(self._keyframe_T_WC(kf_fid)) @ self._T_WC_imu
        return rigid(T_CkCf) if self.metric_scale else T_CkCf

    # ------------------------------------------------------------------ tracking
    def _track_frame(self, fid: int, frame, inputs, pair=None) -> FrameStatus:
        if self.features is not None and pair is None:  # monocular: the pose of every frame by the corners
            return self.tracker.track_features(fid, frame, inputs)
        kf = self._kf
        self._T_WC_imu = self._prior_T_WC(frame.timestamp)
        surface = self._frame_surface
        res = self.tracker.track_against(kf, fid, self._T_CkCf, self._uv_prev, pair, surface)
        events = []
        if res is not None and res.get("held") is not None:  # no confident flow, the depth holds it
            return self._track_by_depth(kf, fid, frame, inputs, res, res["held"], events, "no confident flow")
        min_fraction = self.config.tracking.min_valid_fraction
        if not self.tracker.ok(res, min_fraction) and self.keyframing.promote_last():
            events.append(f"keyframe {self._kf.fid} (look-back)")  # the last good frame became the keyframe
            kf = self._kf
            res = self.tracker.track_against(kf, fid, self._T_CkCf, None, surface=surface)
        if not self.tracker.ok(res, min_fraction) and self.kind == "mono":
            status = self.tracker.track_pnp(fid, frame)  # no (usable) two-view pointmap: pose by PnP
            status.events[:0] = events
            return status
        if not self.tracker.ok(res, min_fraction) and self.depth.enabled:
            held = self.tracker.by_depth(kf, res, surface)
            if held is not None:  # the matches lost it, the depth holds it
                return self._track_by_depth(kf, fid, frame, inputs, res, held, events, f"{res['n_valid']} valid matches")
        if not self.tracker.ok(res, min_fraction):
            found = relocalize(self, fid, frame)
            if found is None:
                why = "no pair" if res is None else (f"{res['n_valid']} valid matches ({100 * res['fraction']:.0f} %), "
                                                     f"{res['inliers']} inliers")
                return self._fail(fid, frame, f"tracking lost: {why}")
            kf, res = found
            self._kf, self._uv_prev, self._since_kf = kf, None, 0
            source = "relocalized"
        else:
            source = "tracked"
            self._uv_prev = res["matches"].uv_lm
        T_CkCf = res["T"]
        self._T_CkCf = matrix_of(T_CkCf)
        self.keyframing.fuse(kf, T_CkCf, res)
        self._since_kf += 1
        new_kf = res["fraction"] < self.config.keyframe.new_fraction or (
            self.config.keyframe.max_gap > 0 and self._since_kf >= self.config.keyframe.max_gap)
        self._last_good = None
        if new_kf:
            self.keyframing.make_keyframe(kf, fid, frame, inputs, res)
            events.append(f"keyframe {fid}")
        else:
            self._records[fid] = RelativePose(kf.fid, self._T_CkCf.copy())
            if source == "tracked":  # a keyframe candidate when the next frame no longer tracks against kf
                self._last_good = (fid, frame, inputs, res, self._T_CkCf.copy())
        return self._status(fid, frame, source, new_kf, res["inliers"], events)

    def _track_by_depth(self, kf, fid: int, frame, inputs, res, held, events, why: str) -> FrameStatus:
        """Frame ``fid`` tracked against ``kf`` by depth alone (``held``: its ``T_CkCf`` and the share of its
        depth points paired): nothing fused; a new keyframe (joined to ``kf`` by its depth block) when that
        share falls below ``keyframe.new_fraction`` (or after ``keyframe.max_gap`` frames)."""
        T_CkCf, share = held
        self._T_CkCf = T_CkCf
        self._uv_prev = None
        self._last_good = None
        self._since_kf += 1
        self._counts["depth_tracked"] += 1
        events.append(f"tracked by depth ({why}, {100 * share:.0f} % of the depth paired)")
        new_kf = share < self.config.keyframe.new_fraction or (
            self.config.keyframe.max_gap > 0 and self._since_kf >= self.config.keyframe.max_gap)
        if new_kf:
            res = {**res, "inlier": None}
            self.keyframing.make_keyframe(kf, fid, frame, inputs, res)
            events.append(f"keyframe {fid}")
        else:
            self._records[fid] = RelativePose(kf.fid, self._T_CkCf.copy())
        return self._status(fid, frame, "tracked", new_kf, 0, events)

    def _fail(self, fid: int, frame, reason: str) -> FrameStatus:
        """Tracking lost: the motion prior's pose when it gives one (bridged by the IMU: ``imu``, not a
        failure), else the last tracked relative pose (``motion_model``, counted)."""
        self._T_WC_imu = self._prior_T_WC(frame.timestamp)
        T_CkCf_imu = None if self._kf is None else self.prior_T_CkCf(self._kf.fid)
        if T_CkCf_imu is not None:
            self._T_CkCf = T_CkCf_imu
            self._records[fid] = RelativePose(self._kf.fid, T_CkCf_imu.copy())
            self._uv_prev = None
            logger.info("pointmap frame %d: %s; pose from the IMU", frame.index, reason)
            return self._status(fid, frame, "imu", events=[reason, "imu bridge"])
        self._failures += 1
        self._counts["failed"] += 1
        logger.info("pointmap frame %d: %s", frame.index, reason)
        if self._kf is None:
            return self._status(fid, frame, "initializing", events=[reason])
        self._records[fid] = RelativePose(self._kf.fid, self._T_CkCf.copy())  # the last tracked relative pose
        self._uv_prev = None
        return self._status(fid, frame, "motion_model", events=[reason])
