"""The state the pointmap frontend's collaborators share (:class:`PointmapState`): the set-up (source
kind, scale model, working camera, measurement source, query grid, depth alignment), the keyframes and
the current one, the motion state of the last tracked frame, the pose records, counts and stage times;
plus the small helpers they all need (keyframe poses, a frame's pose and status, the motion prior's
prediction).

The frontend (:mod:`.frontend`) owns it; its collaborators (:mod:`.cache`, :mod:`.tracker`,
:mod:`.relocalization`, :mod:`.edges`, :mod:`.mapping`, :mod:`.pair_tracking`, :mod:`.feature_tracking`,
:mod:`.contributor`) each take this one object and the collaborators they call; none holds the
frontend."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import torch

from ...backend.graph import Backend
from ...core.errors import ConfigError
from ..base import NO_LOOPS, FrameStatus, LoopPort, MotionPrior
from ..depth_tracking import DepthTracking
from ..records import resolve_pose, rigid
from .camera import WorkingCamera
from .config import PointmapConfig
from .features import FeatureTracks
from .keyframes import PointmapKeyframe, query_grid
from .source import PointmapSource, make_pointmap_source

logger = logging.getLogger(__name__)


class PointmapState:
    """What the pointmap frontend's collaborators share (module docstring).

    Args:
        config: the ``pointmap`` section.
        sensor_mode: ``mono``, ``stereo`` or ``rgbd`` (``source.kind: auto`` follows it).
        backend: the run's backend (the only store of keyframe poses).
        records: fid -> pose record of every input frame (the frontend's ``_records``, shared).
        inputs: (fid, timestamp, index) per input frame (the frontend's ``_inputs``, shared).
        sources: fid -> pose source reported (the frontend's ``_sources``, shared).

    ``kind`` is the source kind and ``fixed_scale`` the scale model (SE(3) tracking on a metric map,
    else Sim(3)); the working camera ``cam``, the measurement ``source``, the query grid ``query``,
    ``K_t`` and, for monocular frames posed by the features, ``features`` are set by
    :meth:`set_calibration`. The loop port ``loops`` and the motion prior ``motion_prior`` are the
    ones the frontend was connected to.

    Keyframes: ``kfs`` (every keyframe by fid, insertion order) and the current one ``kf``. Motion
    state: ``T_CkCf`` (the last tracked frame relative to ``kf``), ``uv_prev`` (its matches into ``kf``:
    the next matching's warm start), ``since_kf`` (frames tracked since ``kf``), ``prev_fid`` /
    ``prev_kf`` (the previous frame when it was tracked, and its keyframe), ``last_good`` (``(fid,
    frame, inputs, result, T_CkCf)`` of the last frame tracked against ``kf``: the look-back keyframe),
    ``T_WC_imu`` (the current frame's pose from the motion prior) and ``frame_surface`` (its depth
    surface, RGB-D depth alignment). Monocular start: ``init_fid`` / ``init_frame`` (the first frame of
    the pair waited for).
    """

    def __init__(self, config: PointmapConfig, sensor_mode: str, backend: Backend, records: dict, inputs: list,
                 sources: dict):
        self.config = config
        self.sensor_mode = sensor_mode
        self.backend = backend
        self.records = records
        self.inputs = inputs
        self.sources = sources
        self.kind = config.source_kind(sensor_mode)
        if self.kind == "rgbd" and sensor_mode != "rgbd":
            raise ConfigError(f"pointmap.source.kind=rgbd needs sensor: rgbd (the run's sensor is {sensor_mode})")
        if self.kind == "stereo" and sensor_mode != "stereo":
            raise ConfigError(f"pointmap.source.kind=stereo needs sensor: stereo (the run's sensor is {sensor_mode})")
        scale = config.tracking.scale
        self.fixed_scale = (self.kind in ("rgbd", "stereo")) if scale == "auto" else scale == "fixed"
        if not self.fixed_scale and backend.config.gauge.hold_scale:
            # the pointmaps' scale is real (docs/architecture.md section 4): no per-keyframe log-scale priors
            logger.info("pointmap frontend: Sim(3) keyframes, map.gauge.hold_scale switched off")
            backend.config.gauge.hold_scale = False
        self.loops: LoopPort = NO_LOOPS
        self.motion_prior: MotionPrior | None = None  # the IMU service's prediction (the frontend's connect)
        self.source: PointmapSource | None = None
        self.features: FeatureTracks | None = None  # monocular: the per-frame pose by corners (issue 28)
        self.cam: WorkingCamera | None = None
        self.query: torch.Tensor | None = None
        self.K_t: torch.Tensor | None = None
        self.kfs: dict[int, PointmapKeyframe] = {}  # every keyframe, insertion order
        self.kf: PointmapKeyframe | None = None  # the current keyframe
        self.T_CkCf = np.eye(4)  # last tracked frame relative to the current keyframe
        self.T_WC_imu: np.ndarray | None = None  # the current frame's pose from the motion prior (None: none)
        self.uv_prev: torch.Tensor | None = None  # previous frame's matches into the current keyframe
        self.since_kf = 0
        self.init_fid: int | None = None
        self.init_frame: tuple | None = None  # (frame, inputs) of init_fid
        self.prev_fid: int | None = None  # the previous frame when it was tracked (its pose is T_CkCf)
        self.prev_kf: int | None = None  # ... and its keyframe
        self.last_good: tuple | None = None  # (fid, frame, inputs, result, T_CkCf) of the last frame tracked against the keyframe
        self.failures = 0
        self.times = {"source": 0.0, "matching": 0.0, "tracking": 0.0, "optimization": 0.0, "bookkeeping": 0.0}
        self.counts = {"keyframes": 0, "loop_edges": 0, "relocalized": 0, "pnp_tracked": 0, "failed": 0}
        if self.uses_features:
            self.counts["feature_tracked"] = 0  # frames posed by the corners alone (not keyframes)
        self.depth = DepthTracking(config.depth_align, backend, active=self.kind == "rgbd")
        self.frame_surface = None  # the current frame's depth surface (RGB-D depth alignment)
        if self.depth.enabled:
            self.times["depth"] = 0.0  # surfaces and depth-only tracking of frames
            self.counts["depth_tracked"] = 0  # frames tracked by depth alone

    @property
    def uses_features(self) -> bool:
        """Monocular frames are posed by the features (``features.mode: features``, :mod:`.features`)."""
        return self.kind == "mono" and self.config.features.mode == "features"

    def set_calibration(self, calibration) -> None:
        """The working camera, the measurement source, the query grid and (monocular features) the
        feature tracks from ``calibration``."""
        self.cam = WorkingCamera(calibration, self.config.image_width, self.sensor_mode)
        src_cfg = self.config.source
        if src_cfg.kind == "auto":
            src_cfg = replace(src_cfg, kind=self.kind)
        self.source = make_pointmap_source(src_cfg, self.cam.K, baseline=self.cam.baseline)
        self.query = query_grid(self.cam.H, self.cam.W, self.config.query_stride)
        self.K_t = torch.as_tensor(self.cam.K)
        self.depth.set_intrinsics(self.cam.K)
        if self.uses_features:
            self.features = FeatureTracks(self.config.features, self.cam.K)

    # ------------------------------------------------------------------ poses
    def keyframe_T_WC(self, fid: int) -> np.ndarray:
        """``T_WC`` of keyframe ``fid`` (the backend's)."""
        return self.backend.pose_matrix(fid)

    def pose_of(self, fid: int) -> np.ndarray | None:
        """The current ``T_WC`` of input frame ``fid`` from its record, or None."""
        return resolve_pose(fid, self.records, self.keyframe_T_WC, {})

    def status(self, fid, frame, source, is_keyframe=False, num_valid=0, events=None) -> FrameStatus:
        """The :class:`FrameStatus` of frame ``fid`` with its current pose (rigid)."""
        T = self.pose_of(fid)
        return FrameStatus(int(frame.index), float(frame.timestamp), None if T is None else rigid(T), source,
                           is_keyframe, int(num_valid), list(events or []))

    def prior_T_WC(self, timestamp: float) -> np.ndarray | None:
        """The motion prior's ``T_WC`` of the frame at ``timestamp`` once the map has a keyframe, or None."""
        if self.motion_prior is None or self.kf is None:
            return None
        return self.motion_prior(float(timestamp))

    def prior_T_CkCf(self, kf_fid: int) -> np.ndarray | None:
        """The current frame's motion-prior pose (``T_WC_imu``) relative to keyframe ``kf_fid`` (rigid on a
        metric map), or None."""
        if self.T_WC_imu is None:
            return None
        T_CkCf = np.linalg.inv(self.keyframe_T_WC(kf_fid)) @ self.T_WC_imu
        return rigid(T_CkCf) if self.fixed_scale else T_CkCf
