"""The state the dense frontend's collaborators share (:class:`DenseState`): the frame graph, the
measurement source, the calibrated grid cameras, the pose records, the finalised keyframes of earlier
maps, the motion model (velocity, last posed frame, motion prior), the counts and stage times, and the
small helpers they all need (keyframe poses, frame statuses, cropping, prediction).

The frontend (:class:`~.frontend.DenseFrontend`) owns it and runs the per-frame steps; the
collaborators (:mod:`.tracking`, :mod:`.keyframes`, :mod:`.ba`, :mod:`.lifecycle`, :mod:`.contributor`)
each take this one object and the collaborators they call; none holds the frontend."""

from __future__ import annotations

import logging

import numpy as np

from ...backend.graph import Backend
from ...core.errors import ConfigError
from ...factors.reprojection import ReprojectionConfig
from ..base import NO_LOOPS, FrameStatus, LoopPort, MotionPrior
from ..depth_tracking import DepthTracking
from ..flow import grid_intrinsics
from ..records import per_frame_motion, resolve_pose, rigid, sim3_power
from .config import DenseConfig
from .graph import DenseKeyframeState, FrameGraph
from .source import make_dense_source

logger = logging.getLogger(__name__)


class DenseState:
    """What the dense frontend's collaborators share (module docstring).

    Args:
        config: the ``dense`` section.
        sensor_mode: ``mono``, ``stereo`` or ``rgbd``.
        backend: the run's backend (the only store of keyframe poses).
        records: fid -> pose record of every input frame (the frontend's ``_records``, shared).
        inputs: (fid, timestamp, index) per input frame (the frontend's ``_inputs``, shared).

    The cameras (``calibration``, ``K``, ``width``, ``height``, the grid's ``crop`` and ``K_grid``,
    stereo ``T_CRCL`` and ``K_right_grid``) and a new empty ``graph`` are set by :meth:`set_calibration`
    (again at a map restart); ``loops`` and ``motion_prior`` by the frontend's ``connect``.
    """

    def __init__(self, config: DenseConfig, sensor_mode: str, backend: Backend, records: dict, inputs: list):
        self.config = config
        self.sensor_mode = sensor_mode
        self.metric_scale = sensor_mode != "mono"  # stereo / RGB-D: keyframes at scale 1
        self.backend = backend
        self.records = records
        self.inputs = inputs
        self.source = make_dense_source(config.source)
        self.stride = int(config.source.stride)
        self.reproj = ReprojectionConfig(min_depth=config.ba.min_depth)
        self.depth = DepthTracking(config.depth_align, backend, active=sensor_mode == "rgbd")
        self.loops: LoopPort = NO_LOOPS  # the loop port (the frontend's connect)
        self.motion_prior: MotionPrior | None = None  # the IMU service's prediction (connect): tracking prior and bridge
        self.background_global_ba = config.global_ba.background and config.global_ba.every > 0
        # cameras and the current map's graph (set_calibration)
        self.calibration = None
        self.K: np.ndarray | None = None
        self.width = self.height = 0
        self.crop: tuple[int, int] = (0, 0)  # (H, W) the grid covers
        self.K_grid: np.ndarray | None = None
        self.T_CRCL: np.ndarray | None = None
        self.K_right_grid: np.ndarray | None = None
        self.graph: FrameGraph | None = None
        # maps and motion
        self.final: dict[int, DenseKeyframeState] = {}  # keyframes of earlier maps (after a restart)
        self.initialized = False
        self.last_fid: int | None = None
        self.velocity = np.eye(4)
        self.lost = 0  # consecutive failed frames
        self.failures = 0  # frames whose pose came from the motion model
        self.counts = {"keyframes_added": 0, "keyframes_removed": 0, "tracking_failures": 0, "map_restarts": 0,
                       "global_runs": 0, "low_confidence_frames": 0, "low_texture_frames": 0,
                       "edges_kept": 0, "fading_keyframes": 0}
        self.new_since_global = 0  # keyframes since the last global optimisation
        self.loop_edges: set[tuple[int, int]] = set()  # proximity loop edges kept by a global optimisation (re-measured in every later one)
        self.times = {"flow": 0.0, "tracking": 0.0, "ba": 0.0, "global": 0.0, "bookkeeping": 0.0}
        if self.depth.enabled:
            self.times["depth"] = 0.0  # surfaces and depth-only tracking of frames
            self.counts["depth_tracked"] = 0
        self.pending_origin: np.ndarray | None = None  # pose of the next map's first keyframe after a restart
        self.init_frames: dict[int, tuple[int, np.ndarray]] = {}  # monocular, before initialisation: fid -> (keyframe, image)

    # ------------------------------------------------------------------ cameras
    def set_calibration(self, calibration) -> None:
        """The cameras from ``calibration`` and a new empty graph (the first frame's, a map restart's)."""
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
        self.graph = FrameGraph(self.K_grid, (self.height // s, self.width // s), s, self.reproj, self.keyframe_T_WC)

    def cropped(self, image: np.ndarray | None) -> np.ndarray | None:
        """The part of an image (or depth map) the grid covers."""
        if image is None:
            return None
        H, W = self.crop
        return image if image.shape[:2] == (H, W) else np.ascontiguousarray(image[:H, :W])

    def source_image(self, frame, right: bool = False) -> np.ndarray:
        """The cropped image the source is fed: colour (RGB) for a source that takes it, else grey."""
        if self.source.colour:
            return self.cropped(frame.colour_or_grey(right))
        return self.cropped(frame.image_right if right else frame.image)

    # ------------------------------------------------------------------ keyframes and poses
    def all_keyframes(self) -> list[DenseKeyframeState]:
        """The keyframes of earlier maps, then those of the current one."""
        return list(self.final.values()) + ([] if self.graph is None else list(self.graph.keyframes.values()))

    def keyframe_T_WC(self, fid: int) -> np.ndarray:
        """``T_WC`` of keyframe ``fid`` (the backend's)."""
        return self.backend.pose_matrix(fid)

    def pose_of(self, fid: int) -> np.ndarray | None:
        """The current ``T_WC`` of input frame ``fid`` from its record, or None."""
        return resolve_pose(fid, self.records, self.keyframe_T_WC, {})

    def status(self, fid, frame, source, is_keyframe=False, num_valid=0, events=None, new_map=False) -> FrameStatus:
        """The :class:`FrameStatus` of frame ``fid`` with its current pose (rigid; None before the map
        is initialised)."""
        T = self.pose_of(fid) if self.initialized else None
        return FrameStatus(index=int(frame.index), timestamp=float(frame.timestamp),
                           T_WC=None if T is None else rigid(T), pose_source=source, is_keyframe=is_keyframe,
                           num_valid=int(num_valid), events=list(events or []), new_map=bool(new_map))

    # ------------------------------------------------------------------ motion
    def prior_pose(self, timestamp: float | None) -> np.ndarray | None:
        """The motion prior's ``T_WC`` at ``timestamp`` once the map is initialised (rigid for a metric
        map, whose keyframes are at scale 1 as the constant-velocity prediction's), else None."""
        if self.motion_prior is None or timestamp is None or not self.initialized:
            return None
        T_WC = self.motion_prior(float(timestamp))
        if T_WC is None:
            return None
        return rigid(T_WC) if self.metric_scale else T_WC

    def predict(self, timestamp: float | None = None) -> np.ndarray:
        """The motion prior's pose at ``timestamp`` when it gives one, else the damped constant velocity."""
        T_WC_prior = self.prior_pose(timestamp)
        if T_WC_prior is not None:
            return T_WC_prior
        T_WC_last = self.pose_of(self.last_fid) if self.last_fid is not None else None
        if T_WC_last is None:
            return np.eye(4) if self.pending_origin is None else self.pending_origin
        return T_WC_last @ sim3_power(self.velocity, self.config.tracking.motion_damping)

    def update_velocity(self, fid: int) -> None:
        """The per-frame motion from the last posed frame to ``fid``, which becomes the last one."""
        if self.last_fid is not None:
            T_WC_prev, T_WC_new = self.pose_of(self.last_fid), self.pose_of(fid)
            if T_WC_prev is not None and T_WC_new is not None:
                self.velocity = per_frame_motion(T_WC_prev, T_WC_new, fid - self.last_fid)
        self.last_fid = fid
