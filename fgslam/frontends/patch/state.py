"""The state the patch frontend's collaborators share (:class:`PatchState`): the patch graph, the
measurement source, the calibrated cameras, the pose records, the finalised keyframes and the
tracking counters; plus :class:`BackendFrame`, a graph frame whose pose lives in the backend.

The collaborators (:mod:`.patches`, :mod:`.window`, :mod:`.keyframes`, :mod:`.motion`,
:mod:`.initialisation`, :mod:`.tracking`, :mod:`.contributor`) each take this one object and the
collaborators they call; none holds the frontend."""

from __future__ import annotations

import numpy as np
import torch

from ...backend.graph import Backend
from ...core.errors import ConfigError
from ...factors.reprojection import ReprojectionConfig, reproject
from ...core.lie import sim3_matrix_components
from ..base import FrameStatus
from ..depth_tracking import DepthTracking
from ..records import resolve_pose
from ..records import rigid as _rigid
from .config import PatchConfig
from .graph import GraphFrame, PatchGraph
from .source import make_source

#: keyframes held fixed at the old end of a monocular window or global BA (pose and Sim(3) scale gauge)
MONO_GAUGE_FRAMES = 2


class BackendFrame(GraphFrame):
    """A graph frame whose pose lives in the backend once :meth:`attach` ties it to a keyframe.

    ``T_WC`` reads the backend's pose through a cache refreshed when the backend's pose version of
    the keyframe changes (an optimisation, a ``set_pose``); assigning ``T_WC`` sets the backend's pose.
    Never change the returned array in place (that would bypass the backend): assign a new one.
    Detached (before it enters the backend, after it leaves) the frame keeps its last pose itself.
    """

    _backend: Backend | None = None
    _version: int = -1

    @property
    def T_WC(self) -> np.ndarray:
        backend = self._backend
        if backend is not None:
            version = backend.pose_version(self.fid)
            if version != self._version:
                self._T_WC = backend.pose_matrix(self.fid)
                self._version = version
        return self._T_WC

    @T_WC.setter
    def T_WC(self, T_WC: np.ndarray) -> None:
        T_WC = np.array(T_WC, dtype=np.float64)
        backend = self._backend
        if backend is not None:
            backend.set_pose(self.fid, T_WC)
            self._version = backend.pose_version(self.fid)
        self._T_WC = T_WC

    def attach(self, backend: Backend) -> None:
        self._backend = backend
        self._version = backend.pose_version(self.fid)

    def detach(self) -> None:
        _ = self.T_WC  # keep the backend's last pose
        self._backend = None


class PatchState:
    """What the patch frontend's collaborators share (module docstring).

    Args:
        config: the ``patch`` section.
        sensor_mode: ``mono``, ``stereo`` or ``rgbd``.
        backend: the run's backend (the only store of keyframe poses).
        records: fid -> pose record of every input frame (the frontend's ``_records``, shared).
        inputs: (fid, timestamp, index) per input frame (the frontend's ``_inputs``, shared).

    The cameras (``K``, ``K_right``, ``T_CRCL``, ``width``, ``height``, ``border``) are set by
    :meth:`set_calibration`.
    """

    def __init__(self, config: PatchConfig, sensor_mode: str, backend: Backend, records: dict, inputs: list):
        self.config = config
        self.sensor_mode = sensor_mode
        self.backend = backend
        self.records = records
        self.inputs = inputs
        self.source = make_source(config)
        self.graph = PatchGraph(config.graph, config.graph.max_inactive_edges)
        self.rng = np.random.default_rng(config.graph.seed)
        self.reproj = ReprojectionConfig(min_depth=config.ba.min_depth)
        self.times = {"flow": 0.0, "ba": 0.0, "bookkeeping": 0.0}
        self.final: dict[int, GraphFrame] = {}  # finalised keyframes (left the graph; caches released)
        self.finalised = 0  # keyframes that left the graph (pose final)
        self.initialized = False
        self.map_start_fid: int | None = None  # first keyframe of the current map (since the last initialisation)
        self.lost = 0  # consecutive frames without visual tracking
        self.failures = 0  # frames whose pose came from the motion model
        self.depth = DepthTracking(config.depth_align, backend, active=sensor_mode == "rgbd")
        if self.depth.enabled:
            self.times["depth"] = 0.0  # surfaces and depth-only alignment of new frames
        self.K: torch.Tensor | None = None
        self.K_right: torch.Tensor | None = None
        self.T_CRCL: np.ndarray | None = None
        self.width = self.height = self.border = 0

    # ------------------------------------------------------------------ cameras
    def set_calibration(self, calibration) -> None:
        """The left camera (and for stereo the right one and ``T_CRCL``) from ``calibration``."""
        self.K = torch.as_tensor(np.asarray(calibration.K, dtype=np.float64))
        self.depth.set_intrinsics(calibration.K)
        self.width, self.height = int(calibration.width), int(calibration.height)
        self.K_right = None
        self.T_CRCL = None
        if self.sensor_mode == "stereo":
            if calibration.right is None or calibration.T_CLCR is None:
                raise ConfigError("sensor mode stereo needs a calibration with a right camera and T_CLCR")
            self.K_right = torch.as_tensor(np.asarray(calibration.right.K, dtype=np.float64))
            self.T_CRCL = np.linalg.inv(np.asarray(calibration.T_CLCR, dtype=np.float64))
        self.config.graph.check_image(self.width, self.height)  # before the first frame: the border must leave room
        self.border = self.config.graph.effective_border()

    def inside(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) whose patch footprint (half ``patch_size * patch_stride``) lies in the image."""
        margin = 0.5 * self.config.graph.patch_size * self.config.graph.patch_stride
        return (uv[:, 0] >= margin) & (uv[:, 0] <= self.width - 1 - margin) & (uv[:, 1] >= margin) & (
            uv[:, 1] <= self.height - 1 - margin)

    def reproject_to(self, a: GraphFrame, T_WCb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frame a's patch centres reprojected into a left image at pose ``T_WCb`` at the current
        depths: (K, 2) pixels and validity (in front of that camera). A stack of poses (B, 4, 4) gives
        (B, K, 2) and (B, K) in one call."""
        return self._reproject(a, torch.as_tensor(a.inv_depth), T_WCb)

    def reproject_rotation(self, a: GraphFrame, T_WCb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frame a's patch centres reprojected into a left image at pose ``T_WCb`` at infinite depth
        (the rotation alone): (K, 2) pixels and validity."""
        return self._reproject(a, torch.zeros(len(a.uv), dtype=torch.as_tensor(a.inv_depth).dtype), T_WCb)

    def _reproject(self, a: GraphFrame, inv_depth: torch.Tensor, T_WCb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Ra, ta, sa = sim3_matrix_components(a.T_WC[None])
        stacked = T_WCb.ndim == 3
        Rb, tb, sb = sim3_matrix_components(T_WCb if stacked else T_WCb[None])
        target = (Rb[:, None], tb[:, None], sb[:, None]) if stacked else (Rb[0], tb[0], sb[0])
        uv, ok = reproject(torch.as_tensor(a.uv), inv_depth, (Ra[0], ta[0], sa[0]), target, self.K, config=self.reproj)
        return uv.numpy(), ok.numpy()

    def reproject_patches(self, a: GraphFrame, b: GraphFrame) -> tuple[np.ndarray, np.ndarray]:
        """Frame a's patch centres reprojected into frame b's left image at the current poses and
        depths: (K, 2) pixels and validity (in front, inside the image with the patch margin)."""
        uv, ok = self.reproject_to(a, b.T_WC)
        return uv, ok & self.inside(uv)

    # ------------------------------------------------------------------ keyframes and poses
    def keyframe(self, fid: int) -> GraphFrame | None:
        """The keyframe ``fid`` (in the graph or finalised), or None."""
        f = self.final.get(fid)
        if f is not None:
            return f
        try:
            return self.graph.frame(fid)
        except KeyError:
            return None

    def keyframe_T_WC(self, fid: int) -> np.ndarray:
        """``T_WC`` of keyframe ``fid`` (finalised or in the graph; KeyError otherwise)."""
        f = self.final.get(fid)
        return (f if f is not None else self.graph.frame(fid)).T_WC

    @property
    def gauge_frames(self) -> int:
        """Oldest keyframes that hold a window's or a global BA's gauge: monocular two (pose and
        scale), else one."""
        return MONO_GAUGE_FRAMES if self.sensor_mode == "mono" else 1

    def pose_of(self, fid: int) -> np.ndarray | None:
        """The current ``T_WC`` of input frame ``fid`` from its record, or None."""
        return resolve_pose(fid, self.records, self.keyframe_T_WC, {})

    def stamp(self, fid: int) -> float:
        """Timestamp of input frame ``fid``."""
        for f, stamp, _ in reversed(self.inputs):
            if f == fid:
                return stamp
        raise KeyError(fid)

    def status(self, fid, frame, source, is_keyframe=False, num_valid=0, events=None, new_map=False) -> FrameStatus:
        """The :class:`FrameStatus` of frame ``fid`` with its current pose (rigid)."""
        T_WC = self.pose_of(fid)
        return FrameStatus(index=int(frame.index), timestamp=float(frame.timestamp),
                           T_WC=None if T_WC is None else _rigid(T_WC), pose_source=source,
                           is_keyframe=is_keyframe, num_valid=int(num_valid), events=list(events or []), new_map=bool(new_map))
