"""The patch frontend (DPVO / DPV-SLAM family): patch graph, measurement source, local BA, tracking.

Per frame (after initialisation):

1. predict the pose with the damped constant-velocity model ``T_WCn = T_WCn-1 Exp(damping Log(V))``,
   ``V = T_WCn-2^-1 T_WCn-1`` (DPVO's motion model); motion filter (DROID-SLAM's): the newest
   keyframe's patches are measured in the frame first (these edges are reused in step 3); a median
   flow below ``motion_filter_flow`` means a stationary camera: the frame stays out of the graph, takes
   that keyframe's pose (placed later by its share of the next keyframe's flow), the velocity is reset;
2. add the frame to the patch graph with K new patches (inverse depth: the sensor's for RGB-D,
   else the median of the previous frame's patches, with ``tracking.median_of_measured`` of those
   with a BA-inlier measurement) and connect it (forward, backward, stereo edges);
3. ``ba.rounds`` update rounds: measure edges with the source started from their current
   reprojection (round 1: the new edges; later rounds: new edges that failed or whose residual
   after BA exceeds ``ba.retrack_threshold``; with ``ba.measured_huber`` each fresh measurement
   Huber-weighted by its distance from the reprojection it started from), then
   Levenberg-Marquardt on the optimisation window through the run's backend
   (:meth:`fgslam.backend.Backend.optimize_window`) with one :class:`~.ba.PatchBlock` set as this
   contributor's block (patch depths Schur-eliminated; frames older than the window held fixed by
   the block; each frame's Sim(3) scale held by the backend's gauge); Huber weights and an outlier
   cut are refreshed after each round;
4. too few valid measurements into the frame, or less than ``min_inlier_ratio`` of them BA inliers
   (motion the map's own reprojections contradict): tracking failure - the frame leaves the graph,
   the window's poses and depths are restored, the frame gets the predicted pose
   (``pose_source = "motion_model"``), counted, never raised;
5. the frame ``keyframe_index`` positions before the newest is removed when the mean flow between
   its neighbours is below ``keyframe_threshold`` (its pose kept relative to its older neighbour);
6. edges past the removal window become inactive (bounded store), frames past every active edge's
   reach are finalised, source caches past the patch lifetime are released.

Initialisation: monocular waits until the median rotation-compensated flow of tracked reference
patches exceeds ``init_min_parallax`` and an essential matrix explains the tracks, then builds the
graph from the buffered frames (poses from the essential matrix, interpolated in between) and
optimises with the first keyframe fixed and the distance to the last one as world scale; it never
initialises on a static or purely rotating camera. Stereo and RGB-D initialise on the first frame
with metric depth (stereo: right-image edges through the calibrated ``T_CLCR``; RGB-D: depth prior,
or with ``ba.depth_model: observation`` the sensor depth of every observation as a virtual
right-camera pixel). RGB-D poses are written back rigid (scale exactly 1) after each BA.

Poses are Sim(3) ``T_WC`` with the scale held at its initial value 1, so the output trajectory is
the rigid part ``[R | t]``. Every input frame gets a pose once the map exists (keyframes from the
map, removed frames relative to a neighbour, frames buffered during initialisation interpolated);
frames before a successful initialisation are omitted.

Loop closure, classical and proximity with the global bundle adjustment, is the shared service
:class:`fgslam.services.loops.LoopService` that the system owns and connects as the frontend's loop port
(``self.loops``); the frontend is its contributor
(:mod:`fgslam.services.contributor`: keyframe images and poses, :meth:`PatchFrontend.apply_correction`,
long-range edges, the global BA's snapshot and hand-over). Finalised keyframes (out of the graph)
keep their pose and patches for it (``_final``). Non-keyframes' poses are typed records
(:mod:`.records`).
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import torch

from ...services.contributor import GlobalBAJob, KeyframeImage, PoseCorrection
from ...errors import ConfigError, OptimizationError
from ...factors.depth import depth_priors, inv_depth_sigma
from ...factors.reprojection import ReprojectionConfig, reproject, reproject_edges
from ...factors.robust import kernel_weight
from ...factors.schur import torch_threads
from ...factors.visual_block import BlockConfig
from ...lie import sim3_matrix_components
from ...backend.global_ba import GlobalBAProblem, global_bundle_adjustment
from ...backend.graph import Backend
from ...backend.keys import pose_key
from ..base import BackendFrontend, FrameStatus, SensorMode
from .ba import PatchBlock
from .config import PatchConfig
from .graph import GraphFrame, PatchGraph
from .proximity import Candidate, KeyframeStore, fundamental_inliers, held_frames, pose_filter
from ..records import per_frame_motion
from ..records import AbsolutePose, InterpolatedPose, KeyframePose, PoseRecord, RelativePose, resolve_pose
from ..records import rigid as _rigid
from ..records import sim3_interp as _interp, sim3_power as _sim3_power
from .source import make_source

logger = logging.getLogger(__name__)



# ---------------------------------------------------------------------------------- helpers

def select_patches(image: np.ndarray, count: int, border: int, grid: list[int], method: str,
                   rng: np.random.Generator, block: int = 8, score_width: int = 0) -> np.ndarray:
    """Patch centres (count, 2) float64 in a grey image.

    ``corners``: the strongest local maxima (one per ``block`` x ``block`` pixels) of the min-eigenvalue corner
    response, an equal share per cell of a ``grid[0] x grid[1]`` grid, topped up with the best
    remaining ones; ``random``: uniform (DPVO). Centres keep ``border`` pixels from the edges.
    ``score_width`` > 0: the response is computed on the image resized to at most that width
    (centres are mapped back to full-resolution pixels).
    """
    import cv2

    h, w = image.shape
    if method == "random":
        u = rng.uniform(border, w - 1 - border, count)
        v = rng.uniform(border, h - 1 - border, count)
        return np.stack([np.round(u), np.round(v)], 1)
    if 0 < score_width < w:
        a = score_width / w
        small = cv2.resize(image, (score_width, max(1, round(h * a))), interpolation=cv2.INTER_AREA)
        block_s = max(2, round(block * a))
        border_s = int(np.ceil((border + 0.5) * a))
        uv = select_patches(small, count, border_s, grid, method, rng, block_s)
        uv = np.round((uv + 0.5) / a - 0.5)
        uv[:, 0] = uv[:, 0].clip(border, w - 1 - border)
        uv[:, 1] = uv[:, 1].clip(border, h - 1 - border)
        return uv
    score = cv2.cornerMinEigenVal(image, 3)
    inner = score[border: h - border, border: w - border]
    hb, wb = inner.shape[0] // block, inner.shape[1] // block
    tiles = inner[: hb * block, : wb * block].reshape(hb, block, wb, block).transpose(0, 2, 1, 3).reshape(hb, wb, -1)
    arg = tiles.argmax(-1)
    best = np.take_along_axis(tiles, arg[..., None], -1)[..., 0].reshape(-1)
    by, bx = np.meshgrid(np.arange(hb), np.arange(wb), indexing="ij")
    v = (by * block + arg // block).reshape(-1) + border
    u = (bx * block + arg % block).reshape(-1) + border
    gx, gy = grid
    cell = (u * gx // w).clip(0, gx - 1) + gx * (v * gy // h).clip(0, gy - 1)
    # small random jitter breaks ties between equal scores (flat regions)
    order = np.lexsort((-(best + rng.uniform(0, 1e-9, best.shape)), cell))
    cell_sorted = cell[order]
    first = np.searchsorted(cell_sorted, cell_sorted, side="left")
    rank = np.arange(order.size) - first
    quota = max(1, count // (gx * gy))
    chosen = order[rank < quota]
    chosen = chosen[np.argsort(-best[chosen])][:count]
    if chosen.size < count:
        rest = np.setdiff1d(np.argsort(-best), chosen, assume_unique=False)
        rest = rest[np.argsort(-best[rest])][: count - chosen.size]
        chosen = np.concatenate([chosen, rest])
    uv = np.stack([u[chosen], v[chosen]], 1).astype(np.float64)
    if uv.shape[0] < count:  # tiny image: pad with random centres
        extra = count - uv.shape[0]
        uv = np.concatenate([uv, np.stack([rng.uniform(border, w - 1 - border, extra),
                                            rng.uniform(border, h - 1 - border, extra)], 1).round()])
    return uv


@dataclass
class _InitState:
    """Monocular initialisation: a reference frame and the frames buffered since."""

    ref_fid: int
    ref_frame: object
    ref_features: object
    ref_uv: np.ndarray
    buffer: list = field(default_factory=list)  # (fid, frame, features, tracked uv, valid)


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


class PatchFrontend(BackendFrontend):
    """DPVO / DPV-SLAM-style patch frontend (see module docstring).

    Args:
        config: the ``patch`` section (:class:`PatchConfig`; default values when None).
        calibration: the frames' :class:`fgslam.io.calibration.Calibration` (undistorted pinhole;
            a right camera and ``T_CLCR`` for stereo); None: taken from the first frame.
        sensor_mode: ``mono``, ``stereo`` (needs right images) or ``rgbd`` (needs depth).
        backend: the run's :class:`fgslam.backend.Backend` (the system builds it from ``map``).

    Loop closure reaches it through the loop port the system connects (:meth:`connect`).

    Keyframes: every graph frame is a backend keyframe from when it enters the graph (added with its
    timestamp) until it leaves as redundant or rejected (removed); finalised frames stay. The local
    BA sets this contributor's block (``backend.set_blocks("patch", [block])``), chooses the gauge
    keyframes (``set_gauge``) and runs ``backend.optimize_window(window, ba.iterations)``; the
    solver, gauge sigmas, tolerances and window damping are the backend's (``map``). The backend is
    the only store of keyframe poses: ``GraphFrame.T_WC`` of the frontend's frames
    (:class:`BackendFrame`) reads the backend through a cache keyed by the backend's pose version,
    and assigning it sets the backend's pose.
    """

    name = "patch"

    def __init__(self, config: PatchConfig | None = None, calibration=None, sensor_mode: SensorMode = "mono",
                 backend: Backend | None = None):
        self._attach(config or PatchConfig(), sensor_mode, backend)
        self.proximity_gates = self.config.proximity
        self.source = make_source(self.config)
        self.calibration = None
        if calibration is not None:
            self._set_calibration(calibration)
        self.graph = PatchGraph(self.config.graph, self.config.graph.max_inactive_edges)
        self._rng = np.random.default_rng(self.config.graph.seed)
        self._initialized = False
        self._init: _InitState | None = None
        self._velocity = np.eye(4)
        self._last_fid: int | None = None
        self._lost = 0
        self._failures = 0
        self._times = {"flow": 0.0, "ba": 0.0, "bookkeeping": 0.0}
        self._final: dict[int, GraphFrame] = {}  # finalised keyframes (left the graph; caches released)
        self._map_start_fid: int | None = None  # first keyframe of the current map (since the last initialisation)
        self._reproj = ReprojectionConfig(min_depth=self.config.ba.min_depth)
        self._last_residual = np.zeros(0)
        self._finalised = 0  # keyframes that left the graph (pose final)
        self._keys: dict[int, int] = {}  # fid -> gtsam key cache (bounded to about the graph size)
        self._still: list[tuple[int, int, float]] = []  # stationary frames since the newest keyframe: (fid, keyframe fid, flow px)
        # per-frame motion (Sim(3)) that a frame rejected as implausible motion contradicted, held as the
        # reference of the motion check until a frame is tracked again, though stationary frames after
        # that frame restart the motion model from rest (None: the motion model's velocity is the reference)
        self._motion_reference: np.ndarray | None = None
        # optional pose prediction at a timestamp (4x4 T_WC or None), set by the run's IMU service
        # (fgslam/services/imu.py): the motion prior of tracking, and the pose of a frame whose visual
        # tracking fails (pose_source "imu": bridged, not a failure)
        self.motion_prior = None
        self._loop_images: dict[int, tuple] = {}  # fid -> (image, timestamp, depth) while it may become a loop keyframe
        self._prox_store: KeyframeStore | None = None  # settled keyframes' packed source features (long-range edges)

    # ------------------------------------------------------------------ calibration
    def _set_calibration(self, calibration) -> None:
        self.calibration = calibration
        self.K = torch.as_tensor(np.asarray(calibration.K, dtype=np.float64))
        self.width, self.height = int(calibration.width), int(calibration.height)
        self.K_right = None
        self.T_CRCL = None
        if self.sensor_mode == "stereo":
            if calibration.right is None or calibration.T_CLCR is None:
                raise ConfigError("sensor mode stereo needs a calibration with a right camera and T_CLCR")
            self.K_right = torch.as_tensor(np.asarray(calibration.right.K, dtype=np.float64))
            self.T_CRCL = np.linalg.inv(np.asarray(calibration.T_CLCR, dtype=np.float64))
        self.config.graph.check_image(self.width, self.height)  # before the first frame: the border must leave room
        self._border = self.config.graph.effective_border()

    def _key(self, fid: int) -> int:
        """gtsam key of graph frame ``fid`` (``fgslam.backend.keys.pose_key``), cached."""
        key = self._keys.get(fid)
        if key is None:
            if len(self._keys) > 4 * (len(self.graph) + 1):
                self._keys = {f.fid: self._keys[f.fid] for f in self.graph.frames if f.fid in self._keys}
            key = self._keys[fid] = pose_key(fid)
        return key

    # ------------------------------------------------------------------ Frontend API
    def num_keyframes(self) -> int:
        return len(self.graph) + self._finalised

    @property
    def num_failures(self) -> int:
        """Frames whose pose came from the motion model (tracking failures)."""
        return self._failures

    _numerical_errors = (OptimizationError, RuntimeError, np.linalg.LinAlgError)

    def _measuring(self):
        return torch_threads(self.config.threads)

    def _measure_frame(self, fid: int, frame) -> FrameStatus:
        return self._initialize(fid, frame) if not self._initialized else self._track(fid, frame)

    def _recover(self, fid: int, frame, exc: BaseException) -> FrameStatus:
        logger.warning("frame %d: optimisation failed (%s); using the motion model", frame.index, exc)
        if not self._initialized:
            self._abandon_initialisation()
        elif self.graph.frames and self.graph.frames[-1].fid == fid:
            self._leave(self.graph.remove_frame(fid))
        return self._fail(fid, frame, f"optimisation failed: {exc}")

    def _after_frame(self, fid: int, frame, status: FrameStatus) -> None:
        self._loop_keep_image(fid, frame)
        self._loop_feed_keyframes()
        if self._initialized and status.pose_source == "tracked":
            self._prox_step()

    def keyframe_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        chunks = [self._frame_points(f) for f in list(self._final.values()) + self.graph.frames]
        if not chunks:
            return None
        return np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks])

    def map_export(self):
        """Keyframes (graph and finalised) and one point per patch of positive inverse depth, with
        its track: the source keyframe's patch centre plus every measured left-image edge of the
        patch into another keyframe (active and inactive edges; pixel where the source measured it)."""
        from ...mapdata import MapExport, rigid_poses

        frames = sorted(list(self._final.values()) + self.graph.frames, key=lambda f: f.fid)
        if not frames:
            return None
        fids = np.array([f.fid for f in frames], dtype=np.int64)
        X_W, colour, src_fid, src_patch, src_uv = [], [], [], [], []
        for f in frames:
            X, c = self._frame_points(f)
            ok = np.flatnonzero(f.inv_depth > 0)
            X_W.append(X), colour.append(c), src_fid.append(np.full(len(ok), f.fid)), src_patch.append(ok)
            src_uv.append(f.uv[ok])
        src_fid, src_patch = np.concatenate(src_fid), np.concatenate(src_patch)
        # point index of (source fid, patch): lexicographic search over the sorted (fid, patch) pairs
        order_key = src_fid * (self.config.graph.patches_per_frame + 1) + src_patch
        g, inactive = self.graph, self.graph.inactive.arrays()
        e_src = np.concatenate([g.src, inactive.get("src", np.zeros(0, np.int64))])
        e_patch = np.concatenate([g.patch, inactive.get("patch", np.zeros(0, np.int64))])
        e_tgt = np.concatenate([g.tgt, inactive.get("tgt", np.zeros(0, np.int64))])
        e_uv = np.concatenate([g.uv, inactive.get("uv", np.zeros((0, 2)))]).astype(np.float64)
        e_ok = np.concatenate([~g.right & (g.confidence > 0), ~inactive.get("right", np.zeros(0, bool))])
        e_ok &= np.isin(e_tgt, fids) & (e_tgt != e_src) & np.all(np.isfinite(e_uv), axis=1)
        e_key = e_src * (self.config.graph.patches_per_frame + 1) + e_patch
        pos = np.clip(np.searchsorted(order_key, e_key), 0, max(len(order_key) - 1, 0))
        e_ok &= order_key[pos] == e_key if len(order_key) else np.zeros_like(e_ok)
        n = len(order_key)
        return MapExport(
            fids, [f.timestamp for f in frames], rigid_poses(np.stack([f.T_WC for f in frames])),
            np.concatenate(X_W), np.concatenate(colour),
            track_point=np.concatenate([np.arange(n), pos[e_ok]]),
            track_kf=np.concatenate([src_fid, e_tgt[e_ok]]),
            track_uv=np.concatenate([np.concatenate(src_uv), e_uv[e_ok]]),
        )

    @property
    def map_started(self) -> bool:
        return self._initialized

    def finish(self) -> None:
        self._loop_feed_keyframes(all_frames=True)

    def finish_map(self) -> None:
        logger.info("patch frontend: %d frames, %d keyframes, %d tracking failures",
                    len(self._inputs), self.num_keyframes(), self._failures)

    # ------------------------------------------------------------------ frames and poses
    def _check_frame(self, frame) -> None:
        if frame.image.shape != (self.height, self.width):
            raise ConfigError(f"frame {frame.index}: image {frame.image.shape} does not match the calibration {self.width}x{self.height}")
        if self.sensor_mode == "stereo" and frame.image_right is None:
            raise ConfigError(f"frame {frame.index}: sensor mode stereo but the frame has no right image")
        if self.sensor_mode == "rgbd" and frame.depth is None:
            raise ConfigError(f"frame {frame.index}: sensor mode rgbd but the frame has no depth")

    def _resolve(self, fid: int, cache: dict) -> np.ndarray | None:
        return resolve_pose(fid, self._records, self._keyframe_T_WC, cache)

    def _keyframe_T_WC(self, fid: int) -> np.ndarray:
        f = self._final.get(fid)
        return (f if f is not None else self.graph.frame(fid)).T_WC

    def _pose_of(self, fid: int) -> np.ndarray | None:
        return self._resolve(fid, {})

    def _status(self, fid, frame, source, is_keyframe=False, num_valid=0, events=None) -> FrameStatus:
        T = self._pose_of(fid)
        return FrameStatus(index=int(frame.index), timestamp=float(frame.timestamp),
                           T_WC=None if T is None else _rigid(T), pose_source=source,
                           is_keyframe=is_keyframe, num_valid=int(num_valid), events=list(events or []))

    def _predict(self, timestamp: float | None = None, velocity: np.ndarray | None = None,
                 damping: float | None = None) -> np.ndarray:
        """The motion prior's pose at ``timestamp`` when it gives one, else the damped constant-velocity
        prediction from the last posed frame (per-frame motion ``velocity``, None: the motion model's;
        ``damping``, None: ``tracking.motion_damping``)."""
        if self.motion_prior is not None and timestamp is not None:
            T_prior = self.motion_prior(float(timestamp))
            if T_prior is not None:
                return T_prior
        T_last = self._pose_of(self._last_fid)
        damping = self.config.tracking.motion_damping if damping is None else damping
        return T_last @ _sim3_power(self._velocity if velocity is None else velocity, damping)

    def _update_velocity(self, fid: int) -> None:
        if self._last_fid is not None:
            T_prev, T_new = self._pose_of(self._last_fid), self._pose_of(fid)
            if T_prev is not None and T_new is not None:
                self._velocity = per_frame_motion(T_prev, T_new, fid - self._last_fid)
        self._last_fid = fid

    def _frame_points(self, f: GraphFrame) -> tuple[np.ndarray, np.ndarray]:
        K = self.K.numpy()
        ok = f.inv_depth > 0
        rays = np.stack([(f.uv[:, 0] - K[2]) / K[0], (f.uv[:, 1] - K[3]) / K[1], np.ones(len(f.uv))], 1)
        X_C = rays[ok] / f.inv_depth[ok, None]
        X_W = X_C @ f.T_WC[:3, :3].T + f.T_WC[:3, 3]
        return X_W, f.colour[ok]

    # ------------------------------------------------------------------ graph frames
    def _sensor_inv_depth(self, frame, uv: np.ndarray) -> np.ndarray:
        if self.sensor_mode != "rgbd" or frame.depth is None:
            return np.full(len(uv), np.nan)
        return self._depth_lookup(frame.depth, uv)

    def _depth_lookup(self, depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Inverse sensor depth (n,) at pixels uv (n, 2): median of the valid readings in a window,
        NaN where most are invalid or the window spans a depth discontinuity."""
        out = np.full(len(uv), np.nan)
        h, w = depth.shape
        r = self.config.ba.depth_window
        offs = np.arange(-r, r + 1)
        us = (uv[:, 0:1].round().astype(int) + offs[None, :]).clip(0, w - 1)
        vs = (uv[:, 1:2].round().astype(int) + offs[None, :]).clip(0, h - 1)
        win = depth[vs[:, :, None], us[:, None, :]].reshape(len(uv), -1).astype(np.float64)
        ba = self.config.ba
        valid = (win > ba.depth_min) & (win <= ba.depth_max)
        win = np.where(valid, win, np.nan)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows: no reading there
            med = np.nanmedian(win, axis=1)
            spread = (np.nanmax(win, axis=1) - np.nanmin(win, axis=1)) / med
        good = (valid.sum(1) > valid.shape[1] // 2) & np.isfinite(med) & (spread < ba.depth_max_spread)
        out[good] = 1.0 / med[good]
        return out

    def _new_graph_frame(self, fid: int, frame, T_WC: np.ndarray, features, features_right) -> GraphFrame:
        gcfg = self.config.graph
        uv = select_patches(frame.image, gcfg.patches_per_frame, self._border, gcfg.selection_grid, gcfg.selection, self._rng,
                            gcfg.candidate_block, gcfg.score_width)
        ui, vi = uv[:, 0].astype(int), uv[:, 1].astype(int)
        if frame.rgb is not None:
            colour = frame.rgb[vi, ui].astype(np.uint8)
        else:
            colour = np.repeat(frame.image[vi, ui][:, None], 3, 1).astype(np.uint8)
        sensor = self._sensor_inv_depth(frame, uv)
        if len(self.graph):
            prev = self.graph.frames[-1].inv_depth
            if self.config.tracking.median_of_measured:
                prev = self._measured_inv_depths(self.graph.frames[-1])
            median = float(np.median(prev[prev > 0])) if (prev > 0).any() else 1.0
        else:
            median = float(np.nanmedian(sensor)) if np.isfinite(sensor).any() else 1.0
        inv_depth = np.where(np.isfinite(sensor), sensor, median)
        keep_depth = self.sensor_mode == "rgbd" and self.config.ba.depth_model == "observation"
        return BackendFrame(fid=fid, index=int(frame.index), timestamp=float(frame.timestamp), T_WC=np.array(T_WC, dtype=np.float64),
                          uv=uv, inv_depth=inv_depth, sensor_inv_depth=sensor, colour=colour,
                          features=features, features_right=features_right, depth=frame.depth if keep_depth else None)

    def _measured_inv_depths(self, f: GraphFrame) -> np.ndarray:
        """Inverse depths of graph frame ``f``'s patches that have a BA-inlier measurement (source ``f``);
        all of them when fewer than ``tracking.min_measured_patches`` have one. The others still
        hold the value they were created with, which would otherwise become the median forever."""
        g = self.graph
        seen = np.zeros(len(f.inv_depth), bool)
        seen[g.patch[(g.confidence > 0) & (g.robust > 0) & (g.src == f.fid)]] = True
        measured = f.inv_depth[seen & (f.inv_depth > 0)]
        return measured if len(measured) >= self.config.tracking.min_measured_patches else f.inv_depth

    def _prepare(self, frame, left: bool = True, right: bool = True):
        t0 = time.perf_counter()
        feats = self.source.prepare(frame.image) if left else None
        feats_right = self.source.prepare(frame.image_right) if right and self.sensor_mode == "stereo" else None
        self._times["flow"] += time.perf_counter() - t0
        return feats, feats_right

    def _enter(self, f: GraphFrame) -> None:
        """Frame ``f`` enters the patch graph and becomes a backend keyframe."""
        self.graph.add_frame(f)
        self._ensure_keyframe(f)

    def _ensure_keyframe(self, f: GraphFrame) -> None:
        if not self.backend.has_keyframe(f.fid):
            self.backend.add_keyframe(f.fid, f.T_WC, f.timestamp)
            if isinstance(f, BackendFrame):
                f.attach(self.backend)

    def _leave(self, f: GraphFrame) -> None:
        """Frame ``f`` left the patch graph without being finalised (redundant, rejected): it leaves
        the backend too (its pose stays on the frame)."""
        if isinstance(f, BackendFrame):
            f.detach()
        if self.backend.has_keyframe(f.fid):
            self.backend.remove_keyframe(f.fid)

    # ------------------------------------------------------------------ measurement
    def _predict_edges(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Source pixels (n, 2), current reprojections (n, 2) and validity (n,) of edges ``idx``."""
        g = self.graph
        src, tgt, patch, right = g.src[idx], g.tgt[idx], g.patch[idx], g.right[idx]
        pos_s, pos_t = g.positions(src), g.positions(tgt)
        uv_all = np.stack([f.uv for f in g.frames])
        d_all = np.stack([f.inv_depth for f in g.frames])
        uv_src = uv_all[pos_s, patch]
        d = d_all[pos_s, patch]
        R, t, s = sim3_matrix_components(np.stack([f.T_WC for f in g.frames]))
        ps, pt = torch.as_tensor(pos_s), torch.as_tensor(pos_t)
        uv, valid = reproject_edges(torch.as_tensor(uv_src), torch.as_tensor(d), (R[ps], t[ps], s[ps]),
                                    (R[pt], t[pt], s[pt]), self.K, right=torch.as_tensor(right), K_right=self.K_right,
                                    T_CRCL=self.T_CRCL, config=self._reproj)
        pred = uv.numpy()
        return uv_src, pred, valid.numpy() & self._inside(pred)

    def _measure(self, idx: np.ndarray, huber: bool = False) -> None:
        """Measure edges ``idx`` with the source, started from their current reprojection; ``huber``:
        their robust weights from the distance to it (:meth:`_huber_from`), else 1."""
        if idx.size == 0:
            return
        t0 = time.perf_counter()
        g = self.graph
        uv_src, pred, ok = self._predict_edges(idx)
        g.confidence[idx] = 0.0
        g.robust[idx] = 1.0
        frames = {f.fid: f for f in g.frames}
        key = (g.src[idx] * (g.tgt.max() + 1) + g.tgt[idx]) * 2 + g.right[idx]
        requests, selections = [], []
        for k in np.unique(key[ok]):
            sel = np.nonzero(ok & (key == k))[0]
            e0 = idx[sel[0]]
            fs, ft = frames[int(g.src[e0])], frames[int(g.tgt[e0])]
            tgt_feats = ft.features_right if g.right[e0] else ft.features
            if fs.features is None or tgt_feats is None:
                continue
            requests.append((fs.features, tgt_feats, uv_src[sel], pred[sel]))
            selections.append(idx[sel])
        for edges, m in zip(selections, self.source.measure_batch(requests)):
            g.uv[edges] = m.uv
            g.confidence[edges] = m.confidence
        if huber:
            self._huber_from(idx, pred)
        self._times["flow"] += time.perf_counter() - t0

    def _huber_from(self, idx: np.ndarray, pred: np.ndarray) -> None:
        """``ba.measured_huber``: robust weights of freshly measured edges ``idx`` from their distance to
        the reprojections ``pred`` (n, 2) they were measured from: a track far from where the current
        estimate puts it (a wrong lock, an occlusion edge) enters the next BA with a Huber weight
        instead of full weight, so one LM step cannot follow a few gross outliers."""
        g = self.graph
        r = np.nan_to_num(np.linalg.norm(g.uv[idx] - pred, axis=1), nan=0.0)
        g.robust[idx] = self._huber_weights(g.confidence[idx], r)

    def _huber_weights(self, confidence: np.ndarray, residual_px: np.ndarray) -> np.ndarray:
        """Huber weights (``ba.huber_delta``) of pixel residual norms whitened by ``ba.pixel_sigma``
        and the measurements' confidences."""
        white = np.sqrt(confidence) * residual_px / self.config.ba.pixel_sigma
        return kernel_weight(torch.as_tensor(white), "huber", self.config.ba.huber_delta).numpy()

    # ------------------------------------------------------------------ bundle adjustment
    def _optimize(self, iterations: int, init: bool) -> dict:
        """Local BA over the optimisation window (all graph frames with ``init``); updates poses,
        depths and robust weights. Returns a small report dict."""
        t0 = time.perf_counter()
        g = self.graph
        cfg = self.config
        fids = g.fids
        n = len(fids)
        K = cfg.graph.patches_per_frame
        if init:
            var = fids.copy()
        else:
            keep_fixed = 2 if self.sensor_mode == "mono" else 1
            nvar = max(1, min(cfg.graph.optimization_window, n - keep_fixed))
            var = fids[n - nvar:]
        measured = g.confidence > 0
        touch = measured & (np.isin(g.src, var) | np.isin(g.tgt, var))
        pkey = g.src * K + g.patch
        use = measured & np.isin(pkey, np.unique(pkey[touch]))
        e = np.nonzero(use)[0]
        self._last_residual = np.full(g.num_edges, np.inf)
        if e.size == 0:
            self._times["ba"] += time.perf_counter() - t0
            return {"edges": 0}
        used_frames = np.union1d(np.union1d(g.src[e], g.tgt[e]), var)
        fixed = np.setdiff1d(used_frames, var)
        order = list(var) + list(fixed)
        if init and self.sensor_mode == "mono" and len(var) >= 2:
            # the range gauge acts between the first two keyframes: use the widest baseline
            order = [var[0], var[-1]] + list(var[1:-1])
            var_order = order
        else:
            var_order = list(var)
        local_fids = np.array(var_order + list(fixed), dtype=np.int64)
        sorter = np.argsort(local_fids)
        src_l = sorter[np.searchsorted(local_fids, g.src[e], sorter=sorter)]
        tgt_l = sorter[np.searchsorted(local_fids, g.tgt[e], sorter=sorter)]
        ukeys, struct_idx = np.unique(pkey[e], return_inverse=True)
        pos_src = g.positions(ukeys // K)
        d_all = np.stack([f.inv_depth for f in g.frames])
        uv_all = np.stack([f.uv for f in g.frames])
        depth0 = d_all[pos_src, ukeys % K]
        uv_src = uv_all[g.positions(g.src[e]), g.patch[e]]
        weights = g.confidence[e] * g.robust[e] / cfg.ba.pixel_sigma ** 2
        prior = {}
        right, uv_tgt, K_right, T_CRCL = g.right[e], g.uv[e], self.K_right, self.T_CRCL
        if self.sensor_mode == "rgbd":
            sens = np.stack([f.sensor_inv_depth for f in g.frames])[pos_src, ukeys % K]
            has = np.isfinite(sens) & (sens > 0)
            if cfg.ba.depth_model == "prior":
                prior = depth_priors(sens, cfg.ba.depth_noise_model()).kwargs()
            else:
                src_l, tgt_l, right, uv_src, uv_tgt, weights, struct_idx, K_right, T_CRCL = self._depth_observations(
                    e, src_l, tgt_l, uv_src, struct_idx, weights, sens, has)
        fixed_T = g.poses(fixed) if len(fixed) else np.zeros((0, 4, 4))
        fR, ft, fs = sim3_matrix_components(fixed_T)
        block = PatchBlock(
            [self._key(int(f)) for f in var_order], fR, ft, fs, src_l, tgt_l, right, uv_src, uv_tgt, weights,
            struct_idx, self.K, depth0, K_right=K_right, T_CRCL=T_CRCL,
            config=BlockConfig(threads=cfg.ba.threads), reprojection=self._reproj, **prior,
        )
        mono_init = init and self.sensor_mode == "mono"
        backend = self.backend
        for f in var_order:
            self._ensure_keyframe(g.frame(int(f)))
        # gauge: the oldest window frame anchored when nothing outside the window holds the poses;
        # at monocular initialisation the range between the first and last frame is the world scale
        anchor = int(var_order[0]) if mono_init or len(fixed) == 0 else None
        pair = (int(var_order[0]), int(var_order[1])) if mono_init and len(var_order) >= 2 else None
        backend.set_gauge(anchor=anchor, scale_pair=pair)
        backend.set_blocks(self.name, [block])
        report = backend.optimize_window([int(f) for f in var_order], iterations)
        # robust weights from the final residuals at the optimised poses, before the RGB-D rigid
        # write-back below (the block answers from its memo of the last accepted step)
        r, valid = block.residuals(backend.values_of(block.keys))
        # RGB-D poses are written back rigid (scale exactly 1): its depth priors act on inverse depths
        # in the source camera and observe no Sim(3) scale, and the scale prior only holds each BA
        # near its starting scale, so kept scales drifted from BA to BA (7-Scenes: s fell to 0.87
        # within 200 frames and the trajectory shrank; see README). Stereo observes the scale through
        # the metric baseline (resetting it there moved the EuRoC static clip by 2.6 mm instead of 0.8 mm).
        rigid = self.sensor_mode == "rgbd"
        for f in var_order:
            frame = g.frame(int(f))
            if rigid:
                frame.T_WC = _rigid(frame.T_WC)
            elif not isinstance(frame, BackendFrame):  # a frame built outside the frontend (tests)
                frame.T_WC = backend.pose_matrix(int(f))
        depth = block.structure.numpy()
        for pos in np.unique(pos_src):
            sel = pos_src == pos
            g.frames[pos].inv_depth[ukeys[sel] % K] = depth[sel]
        r, valid = r[: e.size], valid[: e.size]  # the edges' own rows come first in the block
        rn = torch.linalg.vector_norm(r, dim=1).numpy()
        robust = np.where(valid.numpy() & (rn <= cfg.ba.outlier_threshold), self._huber_weights(g.confidence[e], rn), 0.0)
        g.robust[e] = robust
        self._last_residual[e] = np.where(valid.numpy(), rn, np.inf)
        self._times["ba"] += time.perf_counter() - t0
        return {"edges": int(e.size), "initial_cost": report.initial_cost, "final_cost": report.final_cost,
                "iterations": report.iterations}

    def _inv_depth_sigma(self, inv_depth: np.ndarray) -> np.ndarray:
        """Standard deviation of sensor inverse depths (1/m) under ``ba.depth_noise``."""
        return inv_depth_sigma(inv_depth, self.config.ba.depth_noise_model())

    def _depth_observations(self, e, src_l, tgt_l, uv_src, struct_idx, weights, sens, has):
        """RGB-D observation model (ORB-SLAM3's RGB-D mode): every observation with a sensor depth
        also observes a virtual right camera ``depth_virtual_baseline`` to the right, at
        ``u_R = u - f b / z`` (the u row only; v would repeat the left image's). Sources observe
        themselves there (a pose-free inverse-depth term), targets at the measured pixel with the
        target frame's own depth reading. Returns the block's edge arrays (edges ``e`` first, in
        their order) extended with these rows, which go through the calibrated stereo residual:
        ``(src, tgt, right, uv_src, uv_tgt, weights (n, 2), struct_idx, K_right, T_CRCL)``."""
        g = self.graph
        ba = self.config.ba
        fx = float(self.K[0])
        b = ba.depth_virtual_baseline
        T_CRCL = np.eye(4)
        T_CRCL[0, 3] = -b
        pos_t = g.positions(g.tgt[e])
        d_tgt = np.full(e.size, np.nan)
        left = ~g.right[e]
        for pos in np.unique(pos_t[left]):
            depth = g.frames[pos].depth
            if depth is None:
                continue
            sel = np.nonzero(left & (pos_t == pos))[0]
            d_tgt[sel] = self._depth_lookup(depth, g.uv[e][sel])
        ok_t = np.isfinite(d_tgt) & (d_tgt > 0)
        # source self-observations: one per patch with a reading
        ps = np.nonzero(has)[0]
        first = np.zeros(len(sens), np.int64)
        first[struct_idx[::-1]] = np.arange(e.size)[::-1]  # an edge of each patch (its source frame)
        src_self = src_l[first[ps]]
        uv_self = uv_src[first[ps]]
        uv_self_R = uv_self - np.stack([fx * b * sens[ps], np.zeros(ps.size)], 1)
        uv_t = g.uv[e][ok_t]
        uv_t_R = uv_t - np.stack([fx * b * d_tgt[ok_t], np.zeros(int(ok_t.sum()))], 1)
        sigma_px2 = ba.pixel_sigma ** 2
        # u_R rows: the left observation's pixel variance (sigma^2 / confidence, times its robust
        # weight) plus the depth noise in pixels; sources: a full-confidence pixel plus depth noise
        w_t, conf = weights[ok_t], g.confidence[e][ok_t]
        m = (w_t > 0) & (conf > 0)
        px_var = sigma_px2 / conf[m]
        w_R_t = np.zeros(w_t.size)
        w_R_t[m] = w_t[m] * px_var / (px_var + (fx * b * self._inv_depth_sigma(d_tgt[ok_t][m])) ** 2)
        var_s = sigma_px2 + (fx * b * self._inv_depth_sigma(sens[ps])) ** 2
        w_all = np.concatenate([np.stack([weights, weights], 1), np.stack([1.0 / var_s, np.zeros(ps.size)], 1),
                                np.stack([w_R_t, np.zeros(w_R_t.size)], 1)])
        n_new = ps.size + int(ok_t.sum())
        return (np.concatenate([src_l, src_self, src_l[ok_t]]), np.concatenate([tgt_l, src_self, tgt_l[ok_t]]),
                np.concatenate([g.right[e], np.ones(n_new, bool)]),
                np.concatenate([uv_src, uv_self, uv_src[ok_t]]), np.concatenate([g.uv[e], uv_self_R, uv_t_R]),
                w_all, np.concatenate([struct_idx, ps, struct_idx[ok_t]]), self.K, T_CRCL)

    def _rounds(self, new_edges: np.ndarray, rounds: int, iterations: int, init: bool, new_fid: int | None,
                premeasured: np.ndarray | None = None) -> int:
        """Measure / optimise rounds; returns the number of valid new measurements of ``new_fid``.
        ``premeasured``: new edges already measured (skipped in the first round)."""
        g = self.graph
        to_measure = new_edges if premeasured is None else np.setdiff1d(new_edges, premeasured)
        valid_new = 0
        for r in range(rounds):
            self._measure(to_measure, huber=not init and self.config.ba.measured_huber)
            if new_fid is not None:
                valid_new = self._valid_into(new_fid)
                if valid_new < self.config.tracking.min_valid_edges:
                    return valid_new
            self._optimize(iterations, init)
            if r + 1 < rounds:
                created = np.arange(g.num_edges) if init else np.nonzero(g.created == new_fid)[0]
                res = self._last_residual[created]
                redo = (g.confidence[created] <= 0) | (res > self.config.ba.retrack_threshold)
                to_measure = created[redo]
        # drop edges that never got a valid measurement
        t0 = time.perf_counter()
        g._select(g.confidence > 0)
        self._times["bookkeeping"] += time.perf_counter() - t0
        if new_fid is not None:
            valid_new = self._valid_into(new_fid)
        return valid_new

    def _valid_into(self, fid: int) -> int:
        g = self.graph
        ok = (g.confidence > 0) & (g.robust > 0) & ~g.right
        return int((ok & ((g.tgt == fid) | (g.src == fid))).sum())

    # ------------------------------------------------------------------ initialisation
    def _initialize(self, fid: int, frame) -> FrameStatus:
        if self.sensor_mode in ("stereo", "rgbd"):
            return self._initialize_metric(fid, frame, np.eye(4) if self._last_fid is None else self._predict())
        return self._initialize_mono(fid, frame)

    def _initialize_metric(self, fid: int, frame, T_WC: np.ndarray) -> FrameStatus:
        feats, feats_right = self._prepare(frame)
        t0 = time.perf_counter()
        gf = self._new_graph_frame(fid, frame, T_WC, feats, feats_right)
        self._enter(gf)
        self._records[fid] = KeyframePose()
        self._times["bookkeeping"] += time.perf_counter() - t0
        if self.sensor_mode == "stereo":
            idx = self.graph.connect_all(stereo=True)
            self._measure(idx)
            ok = self.graph.confidence[idx] > 0
            self._refine_depths_fixed(idx[ok], self.config.ba.stereo_init_steps)
            valid = int(ok.sum())
            self.graph._select(self.graph.confidence > 0)
        else:
            valid = int(np.isfinite(gf.sensor_inv_depth).sum())
        if valid < self.config.tracking.min_valid_edges:
            for f in self.graph.clear():
                self._leave(f)
            self._records[fid] = None
            return self._status(fid, frame, "initializing", events=[f"waiting for depth ({valid} valid patches)"])
        self._initialized = True
        self._map_start_fid = fid
        self._lost = 0
        self._update_velocity(fid)
        return self._status(fid, frame, "tracked", is_keyframe=True, num_valid=valid, events=["initialised"])

    def _abandon_initialisation(self) -> None:
        """After a failed initialisation: the frames it put in the graph (or buffered) get no pose and
        leave; the next frame starts a new initialisation (keyframes of an earlier map stay final)."""
        for f in self.graph.clear():
            self._leave(f)
            self._records[f.fid] = None
        if self._init is not None:
            for b in [(self._init.ref_fid,)] + self._init.buffer:
                self._records[b[0]] = None
        self._init = None
        self._still = []

    def _refine_depths_fixed(self, idx: np.ndarray, steps: int) -> None:
        """Per-patch Gauss-Newton on inverse depth with every pose fixed (stereo initial depths)."""
        if idx.size == 0:
            return
        g = self.graph
        K = self.config.graph.patches_per_frame
        pkey = g.src[idx] * K + g.patch[idx]
        ukeys, struct_idx = np.unique(pkey, return_inverse=True)
        frames_used = np.union1d(g.src[idx], g.tgt[idx])
        R, t, s = sim3_matrix_components(g.poses(frames_used))
        pos_src = g.positions(ukeys // K)
        d0 = np.stack([f.inv_depth for f in g.frames])[pos_src, ukeys % K]
        uv_src = np.stack([f.uv for f in g.frames])[g.positions(g.src[idx]), g.patch[idx]]
        block = PatchBlock([], R, t, s, np.searchsorted(frames_used, g.src[idx]), np.searchsorted(frames_used, g.tgt[idx]),
                           g.right[idx], uv_src, g.uv[idx], g.confidence[idx], struct_idx, self.K, d0,
                           K_right=self.K_right, T_CRCL=self.T_CRCL, reprojection=self._reproj)
        block.refine_structure(None, steps)
        depth = block.structure.numpy()
        for pos in np.unique(pos_src):
            sel = pos_src == pos
            g.frames[pos].inv_depth[ukeys[sel] % K] = depth[sel]

    def _initialize_mono(self, fid: int, frame) -> FrameStatus:
        tcfg = self.config.tracking
        feats, _ = self._prepare(frame)
        st = self._init
        if st is None:
            uv = select_patches(frame.image, self.config.graph.patches_per_frame, self._border,
                                self.config.graph.selection_grid, self.config.graph.selection, self._rng,
                                self.config.graph.candidate_block, self.config.graph.score_width)
            self._init = _InitState(fid, frame, feats, uv)
            return self._status(fid, frame, "initializing", events=["initialisation reference"])
        last_uv = st.buffer[-1][3] if st.buffer else st.ref_uv
        last_valid = st.buffer[-1][4] if st.buffer else np.ones(len(st.ref_uv), bool)
        t0 = time.perf_counter()
        m = self.source.measure(st.ref_features, feats, st.ref_uv, last_uv)
        self._times["flow"] += time.perf_counter() - t0
        valid = last_valid & (m.confidence > 0)
        st.buffer.append((fid, frame, feats, m.uv, valid))
        if int(valid.sum()) < tcfg.init_min_tracks:
            # lost the reference: the buffered frames never get a pose; restart from this frame
            for b in st.buffer[:-1]:
                self._records[b[0]] = None
            uv = select_patches(frame.image, self.config.graph.patches_per_frame, self._border,
                                self.config.graph.selection_grid, self.config.graph.selection, self._rng,
                                self.config.graph.candidate_block, self.config.graph.score_width)
            self._init = _InitState(fid, frame, feats, uv)
            return self._status(fid, frame, "initializing", events=["initialisation reference reset (tracks lost)"])
        if len(st.buffer) >= tcfg.init_max_frames:
            # subsample: drop the second-newest frame every other time, interpolated later
            drop = len(st.buffer) - 2 if len(st.buffer) % 2 else 0
            dropped = st.buffer.pop(drop)
            prev = st.ref_fid if drop == 0 else st.buffer[drop - 1][0]
            nxt = st.buffer[drop][0]
            alpha = (dropped[1].timestamp - self._stamp(prev)) / max(self._stamp(nxt) - self._stamp(prev), 1e-9)
            self._records[dropped[0]] = InterpolatedPose(prev, nxt, float(alpha))
        if len(st.buffer) + 1 < tcfg.init_min_frames:
            return self._status(fid, frame, "initializing", events=["collecting initialisation frames"])
        ok, T_C0Cn, depths, parallax = self._two_view(st.ref_uv[valid], m.uv[valid])
        if not ok:
            return self._status(fid, frame, "initializing", events=[f"waiting for parallax ({parallax:.1f} px)"])
        return self._build_initial_map(fid, frame, valid, T_C0Cn, depths)

    def _stamp(self, fid: int) -> float:
        for f, stamp, _ in reversed(self._inputs):
            if f == fid:
                return stamp
        raise KeyError(fid)

    def _two_view(self, uv0: np.ndarray, uv1: np.ndarray):
        """Essential-matrix test: (ok, T_C0C1 (4, 4) with |t| = 1, inverse depths of uv0 (NaN: none), parallax px)."""
        import cv2

        tcfg = self.config.tracking
        flow = np.linalg.norm(uv1 - uv0, axis=1)
        if np.median(flow) < tcfg.init_min_parallax:
            return False, None, None, float(np.median(flow))
        Kmat = np.array([[self.K[0], 0, self.K[2]], [0, self.K[1], self.K[3]], [0, 0, 1]], dtype=np.float64)
        E, mask = cv2.findEssentialMat(uv0, uv1, Kmat, cv2.RANSAC, 0.999, tcfg.init_ransac_threshold)
        if E is None or E.shape != (3, 3):
            return False, None, None, 0.0
        _, R, t, mask = cv2.recoverPose(E, uv0, uv1, Kmat, mask=mask)
        inl = mask.reshape(-1) > 0
        if inl.mean() < tcfg.init_min_inlier_ratio:
            return False, None, None, 0.0
        K = self.K.numpy()
        rays0 = np.stack([(uv0[:, 0] - K[2]) / K[0], (uv0[:, 1] - K[3]) / K[1], np.ones(len(uv0))], 1)
        rot = rays0 @ R.T
        uv_rot = np.stack([K[0] * rot[:, 0] / rot[:, 2] + K[2], K[1] * rot[:, 1] / rot[:, 2] + K[3]], 1)
        parallax = float(np.median(np.linalg.norm(uv1[inl] - uv_rot[inl], axis=1)))
        if parallax < tcfg.init_min_parallax:
            return False, None, None, parallax
        P0 = Kmat @ np.hstack([np.eye(3), np.zeros((3, 1))])
        P1 = Kmat @ np.hstack([R, t.reshape(3, 1)])
        Xh = cv2.triangulatePoints(P0, P1, uv0.T.astype(np.float64), uv1.T.astype(np.float64))
        z0 = Xh[2] / Xh[3]
        z1 = (R @ (Xh[:3] / Xh[3]) + t.reshape(3, 1))[2]
        good = inl & (z0 > 0) & (z1 > 0) & np.isfinite(z0)
        inv_depth = np.where(good, 1.0 / np.where(good, z0, 1.0), np.nan)
        T_C1C0 = np.eye(4)
        T_C1C0[:3, :3] = R
        T_C1C0[:3, 3] = t.reshape(3) / np.linalg.norm(t)
        inv_depth = inv_depth * np.linalg.norm(t)
        return True, np.linalg.inv(T_C1C0), inv_depth, parallax

    def _build_initial_map(self, fid: int, frame, valid: np.ndarray, T_C0Cn: np.ndarray, depths: np.ndarray) -> FrameStatus:
        st = self._init
        T_W0 = np.eye(4) if self._last_fid is None else self._predict_reference()
        t_ref, t_last = self._stamp(st.ref_fid), self._stamp(fid)
        members = [(st.ref_fid, st.ref_frame, st.ref_features)] + [(b[0], b[1], b[2]) for b in st.buffer]
        T_Wn = T_W0 @ T_C0Cn
        for mfid, mframe, mfeats in members:
            alpha = (float(mframe.timestamp) - t_ref) / max(t_last - t_ref, 1e-9)
            T = _interp(T_W0, T_Wn, alpha) if mfid != st.ref_fid else T_W0
            gf = self._new_graph_frame(mfid, mframe, T, mfeats, None)
            if mfid == st.ref_fid:
                gf.uv = st.ref_uv.copy()
                d = np.full(len(gf.uv), np.nan)
                d[np.nonzero(valid)[0]] = depths
                med = float(np.nanmedian(d)) if np.isfinite(d).any() else 1.0
                gf.inv_depth = np.where(np.isfinite(d), d, med)
            else:
                ref_d = self.graph.frames[0].inv_depth
                gf.inv_depth[:] = float(np.median(ref_d))
            self._enter(gf)
            self._records[mfid] = KeyframePose()
        idx = self.graph.connect_all(stereo=False)
        ba = self.config.ba
        self._rounds(idx, ba.init_rounds, ba.init_iterations, init=True, new_fid=None)
        n_valid = int(((self.graph.confidence > 0) & (self.graph.robust > 0)).sum())
        if n_valid < self.config.tracking.min_valid_edges * len(members):
            logger.info("initialisation at frame %d rejected (%d valid edges); waiting", frame.index, n_valid)
            for f in self.graph.clear():
                self._leave(f)
                self._records[f.fid] = None
            self._init = None
            return self._status(fid, frame, "initializing", events=["initialisation rejected"])
        self._initialized = True
        self._map_start_fid = self.graph.frames[0].fid
        self._init = None
        self._lost = 0
        self._last_fid = None
        for mfid, _, _ in members:
            self._update_velocity(mfid)
        logger.info("initialised at frame %d with %d frames, %d edges", frame.index, len(members), self.graph.num_edges)
        return self._status(fid, frame, "tracked", is_keyframe=True, num_valid=n_valid, events=["initialised"])

    def _predict_reference(self) -> np.ndarray:
        return self._pose_of(self._last_fid)

    # ------------------------------------------------------------------ tracking
    def _track(self, fid: int, frame) -> FrameStatus:
        cfg = self.config
        T_pred = self._predict(frame.timestamp)
        feats, _ = self._prepare(frame, right=False)
        last = self.graph.frames[-1]
        flow, kf_uv, kf_conf, kf_pred = self._keyframe_flow(last, feats, T_pred)
        if flow < cfg.tracking.motion_filter_flow:
            return self._stationary(fid, frame, last.fid, flow, int((kf_conf > 0).sum()))
        _, feats_right = self._prepare(frame, left=False)  # stereo: the right image only for a moving frame
        t0 = time.perf_counter()
        gf = self._new_graph_frame(fid, frame, T_pred, feats, feats_right)
        self._enter(gf)
        self._records[fid] = KeyframePose()
        idx = self.graph.connect_new_frame(self.sensor_mode == "stereo", cfg.ba.stereo_cross_edges)
        g = self.graph
        done = idx[(g.src[idx] == last.fid) & (g.tgt[idx] == fid) & ~g.right[idx]]  # measured by the motion filter
        g.uv[done] = kf_uv[g.patch[done]]
        g.confidence[done] = kf_conf[g.patch[done]]
        if cfg.ba.measured_huber:
            self._huber_from(done, kf_pred[g.patch[done]])
        saved = [(f.T_WC.copy(), f.inv_depth.copy()) for f in g.frames[:-1]], g.robust[: g.num_edges - len(idx)].copy()
        # the motion the implausible-motion check expects (undamped: the camera's last motion, or the one a
        # rejected frame contradicted), relative to the newest keyframe before the BA moves it
        T_ref = self._predict(frame.timestamp, self._motion_reference, damping=1.0)
        T_CkCref = np.linalg.inv(last.T_WC) @ T_ref
        self._times["bookkeeping"] += time.perf_counter() - t0
        valid = self._rounds(idx, cfg.ba.rounds, cfg.ba.iterations, init=False, new_fid=fid, premeasured=done)
        implausible = None if valid < cfg.tracking.min_valid_edges else self._implausible(fid, last, T_CkCref)
        if valid < cfg.tracking.min_valid_edges or implausible is not None:
            self._drop_new_frame(fid, saved)
            if implausible is not None and self._motion_reference is None:
                self._motion_reference = self._velocity.copy()
            reason = f"tracking lost: {valid} valid measurements" if implausible is None else implausible
            return self._fail(fid, frame, reason, T_pred)
        self._lost = 0
        self._motion_reference = None
        t0 = time.perf_counter()
        events = []
        self._place_still(fid, flow)
        removed = self._remove_redundant()
        if removed is not None:
            events.append(f"keyframe {removed} removed")
        self._retire()
        self._update_velocity(fid)
        self._times["bookkeeping"] += time.perf_counter() - t0
        return self._status(fid, frame, "tracked", is_keyframe=True, num_valid=valid, events=events)

    def _implausible(self, fid: int, kf: GraphFrame, T_CkCref: np.ndarray) -> str | None:
        """Why the motion of the BA'd new frame ``fid`` is implausible, or None: too few of its
        measurements are BA inliers, or its tracked motion contradicts the expected motion
        ``T_CkCref`` (relative to the newest keyframe ``kf`` as it was before the BA; the motion
        model's prediction, or with the motion reference held after a rejected frame, the prediction
        with that motion; :meth:`_motion_contradiction`). The caller drops such a frame: it never
        becomes a keyframe, moves the window or sets the velocity, and takes the motion model's pose."""
        tcfg = self.config.tracking
        ratio = self._inlier_ratio(fid)
        if ratio < tcfg.min_inlier_ratio:
            return f"implausible motion: {ratio:.0%} of the measurements are inliers after BA"
        T_CkCnew = np.linalg.inv(kf.T_WC) @ self.graph.frame(fid).T_WC
        contradiction, deviation_px = self._motion_contradiction(kf, T_CkCref, T_CkCnew)
        if contradiction > tcfg.max_motion_contradiction and deviation_px > tcfg.min_contradiction_px:
            return (f"implausible motion: tracked motion contradicts the motion model "
                    f"({contradiction:.2f} times the motion, {deviation_px:.0f} px)")
        return None

    def _motion_contradiction(self, kf: GraphFrame, T_CkCpred: np.ndarray, T_CkCnew: np.ndarray) -> tuple[float, float]:
        """How far the tracked motion ``T_CkCnew`` departs from the predicted ``T_CkCpred`` (both
        relative to keyframe ``kf``), measured on ``kf``'s patches reprojected through both (in
        pixels: rotation and translation alike, scale-free): (median |tracked flow - predicted flow|
        over the larger of the median tracked and predicted flows, that median distance in px).
        The ratio is 0 when the prediction held, about 1 for a start from rest, a stop or a turn at a
        right angle, about 2 when the motion reversed (a stream jumping back and forth); (0, 0) when
        neither motion moves the patches or none reprojects through both."""
        uv_pred, ok_pred = self._reproject_to(kf, kf.T_WC @ T_CkCpred)
        uv_new, ok_new = self._reproject_to(kf, kf.T_WC @ T_CkCnew)
        ok = ok_pred & ok_new
        if not ok.any():
            return 0.0, 0.0
        flow_pred, flow_new = uv_pred[ok] - kf.uv[ok], uv_new[ok] - kf.uv[ok]
        motion = max(float(np.median(np.linalg.norm(flow_pred, axis=1))), float(np.median(np.linalg.norm(flow_new, axis=1))))
        deviation = float(np.median(np.linalg.norm(uv_new[ok] - uv_pred[ok], axis=1)))
        return (deviation / motion if motion > 0 else 0.0), deviation

    def _inlier_ratio(self, fid: int) -> float:
        """Share of the measured left-image edges into and from frame ``fid`` that the last BA kept
        as inliers (non-zero robust weight); 1 when there are none."""
        g = self.graph
        new = ((g.tgt == fid) | (g.src == fid)) & ~g.right & (g.confidence > 0)
        n = int(new.sum())
        return float((g.robust[new] > 0).sum()) / n if n else 1.0

    def _drop_new_frame(self, fid: int, saved) -> None:
        """A rejected new frame leaves the graph, and the window gets back the poses, depths and
        robust weights it had before that frame's BA."""
        g = self.graph
        self._leave(g.remove_frame(fid))
        frames, robust = saved
        if len(frames) == len(g.frames) and robust.shape == g.robust.shape:
            for f, (T_WC, inv_depth) in zip(g.frames, frames):
                f.T_WC, f.inv_depth = T_WC, inv_depth
            g.robust = robust

    def _keyframe_flow(self, last: GraphFrame, feats, T_WC: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Motion filter measurement: the newest keyframe's patches measured in the new frame (features
        ``feats``, predicted pose ``T_WC``) from their reprojection, as the first BA round would (these
        edges are not measured again). Returns (median flow px of the valid tracks, or inf with fewer
        than ``min_valid_edges`` of them; target pixels (K, 2); confidences (K,); the reprojections
        they were measured from (K, 2))."""
        t0 = time.perf_counter()
        K = len(last.uv)
        uv = np.full((K, 2), np.nan)
        conf = np.zeros(K)
        pred, ok = self._reproject_to(last, T_WC)
        ok &= self._inside(pred)
        if ok.any() and last.features is not None:
            m = self.source.measure(last.features, feats, last.uv[ok], pred[ok])
            uv[ok] = m.uv
            conf[ok] = m.confidence
        self._times["flow"] += time.perf_counter() - t0
        good = conf > 0
        if good.sum() < self.config.tracking.min_valid_edges:
            return float("inf"), uv, conf, pred
        return float(np.median(np.linalg.norm(uv[good] - last.uv[good], axis=1))), uv, conf, pred

    def _stationary(self, fid: int, frame, kf_fid: int, flow: float, n_valid: int) -> FrameStatus:
        """A frame whose image barely moved from the newest keyframe's: it does not enter the graph
        (no keyframe, no BA; depths and scale stay untouched) and takes the keyframe's pose until the
        next keyframe places it by its flow (:meth:`_place_still`); the motion model restarts from rest."""
        self._records[fid] = RelativePose(kf_fid, np.eye(4))
        self._still.append((fid, kf_fid, flow))
        self._velocity = np.eye(4)
        self._last_fid = fid
        self._lost = 0
        return self._status(fid, frame, "tracked", num_valid=n_valid, events=["stationary"])

    def _place_still(self, fid: int, flow: float) -> None:
        """Stationary frames since the previous keyframe get a pose between it and the new keyframe
        ``fid``, interpolated by their flow relative to the new keyframe's (``flow`` px)."""
        for still_fid, kf_fid, still_flow in self._still:
            alpha = min(still_flow / flow, 1.0) if np.isfinite(flow) and flow > 0 else 0.0
            self._records[still_fid] = InterpolatedPose(kf_fid, fid, float(alpha))
        self._still = []

    def _fail(self, fid: int, frame, reason: str, T_pred: np.ndarray | None = None) -> FrameStatus:
        self._still = []  # stationary frames keep their keyframe's pose
        T_prior = self.motion_prior(float(frame.timestamp)) if self.motion_prior is not None and self._initialized else None
        if T_prior is not None and self._last_fid is not None:  # bridged by the IMU: no failure, no reset
            self._records[fid] = RelativePose(self._last_fid, np.linalg.inv(self._pose_of(self._last_fid)) @ T_prior)
            self._last_fid = fid
            logger.info("frame %d: %s; pose from the IMU", frame.index, reason)
            return self._status(fid, frame, "imu", events=[reason, "imu bridge"])
        self._failures += 1
        self._lost += 1
        events = [reason]
        if self._last_fid is None or not self._initialized:
            self._records[fid] = None
            return self._status(fid, frame, "initializing", events=events)
        if T_pred is None:
            T_pred = self._predict()
        ref = self._last_fid
        self._records[fid] = RelativePose(ref, np.linalg.inv(self._pose_of(ref)) @ T_pred)
        # keep the velocity; the next prediction continues from this frame
        self._last_fid = fid
        source = "motion_model"
        if self._lost > self.config.tracking.max_motion_model_frames:
            if self._loop_relocalize(fid, frame) is not None:  # anchor of the re-initialisation
                events.append("relocalised")
                source = "relocalized"
            events.append("re-initialising")
            self._reset()
        logger.info("frame %d: %s", frame.index, reason)
        return self._status(fid, frame, source, events=events)

    def _reset(self) -> None:
        """Finalise the graph and start a new initialisation anchored at the last predicted pose."""
        self._loop_feed_keyframes(all_frames=True)
        for f in self.graph.clear():
            self._finalise(f)
        self.loops.map_reset()
        self._initialized = False
        self._init = None
        self._lost = 0
        self._still = []
        self._motion_reference = None

    def _remove_redundant(self) -> int | None:
        """DPVO keyframe removal: drop the frame ``keyframe_index`` positions before the newest when
        the mean flow between its two neighbours is below ``keyframe_threshold``."""
        g = self.graph
        n = len(g) - 1
        k = n - self.config.tracking.keyframe_index
        if k < 1 or self.sensor_mode == "mono" and len(g) <= 3:
            return None
        a, b = g.frames[k - 1], g.frames[k + 1]
        flow = 0.5 * (self._mean_flow(a, b) + self._mean_flow(b, a))
        if flow >= self.config.tracking.keyframe_threshold:
            return None
        victim = g.frames[k]
        self._records[victim.fid] = RelativePose(a.fid, np.linalg.inv(a.T_WC) @ victim.T_WC)
        self._leave(g.remove_frame(victim.fid))
        return int(victim.index)

    def _mean_flow(self, a: GraphFrame, b: GraphFrame) -> float:
        uv, ok = self._reproject_frame(a, b)
        if not ok.any():
            return float("inf")
        return float(np.linalg.norm(uv[ok] - a.uv[ok], axis=1).mean())

    def _reproject_frame(self, a: GraphFrame, b: GraphFrame) -> tuple[np.ndarray, np.ndarray]:
        """Frame a's patch centres reprojected into frame b's left image at the current poses and
        depths: (K, 2) pixels and validity (in front of b)."""
        return self._reproject_to(a, b.T_WC)

    def _reproject_to(self, a: GraphFrame, T_WCb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frame a's patch centres reprojected into a left image at pose ``T_WCb`` (see :meth:`_reproject_frame`)."""
        Ra, ta, sa = sim3_matrix_components(a.T_WC[None])
        Rb, tb, sb = sim3_matrix_components(T_WCb[None])
        uv, ok = reproject(torch.as_tensor(a.uv), torch.as_tensor(a.inv_depth), (Ra[0], ta[0], sa[0]),
                           (Rb[0], tb[0], sb[0]), self.K, config=self._reproj)
        return uv.numpy(), ok.numpy()

    def _inside(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) whose patch footprint (half ``patch_size * patch_stride``) lies in the image."""
        margin = 0.5 * self.config.graph.patch_size * self.config.graph.patch_stride
        return (uv[:, 0] >= margin) & (uv[:, 0] <= self.width - 1 - margin) & (uv[:, 1] >= margin) & (
            uv[:, 1] <= self.height - 1 - margin)

    def _retire(self) -> None:
        """Deactivate old edges, finalise frames no active edge reaches, release old caches."""
        g = self.graph
        gcfg = self.config.graph
        g.deactivate_old_edges()
        n = len(g) - 1
        for f in g.frames[: max(0, n - gcfg.patch_lifetime)]:
            f.features = None
            f.features_right = None
        for f in g.pop_frames_before(n - gcfg.removal_window - gcfg.patch_lifetime):
            self._finalise(f)

    def _finalise(self, f: GraphFrame) -> None:
        """A keyframe leaves the graph: its pose and patches are kept (global BA, point export)."""
        f.features = None
        f.features_right = None
        f.depth = None
        self._final[f.fid] = f
        self._records[f.fid] = KeyframePose()
        self._finalised += 1

    # ------------------------------------------------------------------ loop closure: the service's hooks
    def connect(self, loops=None, motion_prior=None) -> None:
        """Take the loop port (and motion prior); with proximity loops on, keep settled keyframes'
        packed source features for long-range edges."""
        super().connect(loops, motion_prior)
        self._prox_store = None
        if self.loops.proximity is not None:
            self._prox_store = KeyframeStore(self.config.proximity.max_stored_keyframes)
            self._times.setdefault("proximity", 0.0)

    def inactive_edges(self) -> dict:
        """The bounded store of inactive edges (see :class:`~.graph.InactiveEdges`)."""
        return self.graph.inactive.arrays()

    def _loop_keep_image(self, fid: int, frame) -> None:
        """Keep the image of frame ``fid`` while it is in the graph (or buffered for initialisation)."""
        if not self.loops.classical:
            return
        self._loop_images[fid] = (frame.image, float(frame.timestamp), frame.depth)
        if self._init is not None:
            keep = {self._init.ref_fid} | {b[0] for b in self._init.buffer}
        else:
            keep = {f.fid for f in self.graph.frames}
        for old in [k for k in self._loop_images if k not in keep]:
            del self._loop_images[old]

    def _loop_feed_keyframes(self, all_frames: bool = False) -> None:
        """Hand keyframes that can no longer be removed (graph positions below
        ``len - 1 - keyframe_index``; every graph frame with ``all_frames``) to the closer, then the
        latest graph poses."""
        if not self.loops.classical:
            return
        g = self.graph
        final = len(g) if all_frames else len(g) - 1 - self.config.tracking.keyframe_index
        for p in range(max(final, 0)):
            fid = g.frames[p].fid
            if fid in self._loop_images:
                self.loops.add_keyframe(fid, [g.frames[q].fid for q in (p - 1, p + 1) if 0 <= q < len(g)])
                del self._loop_images[fid]
        self.loops.update_poses({f.fid: f.T_WC for f in g.frames})

    def _loop_relocalize(self, fid: int, frame) -> np.ndarray | None:
        """Pose of a lost frame from the closer's keyframe database (``T_WC`` 4x4 in the map's units) or
        None; on success it becomes frame ``fid``'s pose, the anchor of the re-initialisation."""
        found = self.loops.relocalize(frame.image, self.K.numpy())
        if found is None:
            return None
        kf_id, T_WC = found
        self._records[fid] = AbsolutePose(np.asarray(T_WC, dtype=np.float64))
        if self.sensor_mode == "mono":
            logger.info("frame %d relocalised on keyframe %d; monocular: the re-initialised map starts at this "
                        "pose but gets a scale of its own (not tied to the old map's)", frame.index, kf_id)
        else:
            logger.info("frame %d relocalised on keyframe %d", frame.index, kf_id)
        return T_WC

    def add_loop_counts(self, summary: dict) -> None:
        if self._prox_store is not None and "proximity" in summary:
            summary["proximity"]["stored_keyframes"] = len(self._prox_store.order) - self._prox_store.dropped

    def _prox_step(self) -> None:
        """Store newly settled keyframes (their packed source features, for long-range edges) and search
        a proximity loop for the newest one."""
        if self._prox_store is None:
            return
        t0 = time.perf_counter()
        g = self.graph
        settled = len(g) - 1 - self.config.tracking.keyframe_index
        query = None
        for p in range(max(settled, 0)):
            f = g.frames[p]
            last = self._prox_store.last
            if (last is not None and f.fid <= last) or f.features is None:
                continue
            self._prox_store.add(f.fid, self.source.pack(f.features))
            self.loops.keyframe_settled(f.fid)
            query = f
        self._times["proximity"] += time.perf_counter() - t0
        if query is not None:
            self.loops.search(query.fid)

    # ------------------------------------------------------------------ contributor contract (fgslam.services.contributor)
    def _keyframe(self, fid: int) -> GraphFrame | None:
        """The keyframe ``fid`` (in the graph or finalised), or None."""
        f = self._final.get(fid)
        if f is not None:
            return f
        try:
            return self.graph.frame(fid)
        except KeyError:
            return None

    def keyframe_image(self, kf_id: int) -> KeyframeImage | None:
        kept = self._loop_images.get(kf_id)
        if kept is None:
            return None
        image, timestamp, depth = kept
        return KeyframeImage(image, self.K.numpy(), timestamp, depth)

    def keyframe_pose(self, kf_id: int) -> np.ndarray | None:
        f = self._keyframe(kf_id)
        return None if f is None else f.T_WC

    def apply_correction(self, correction: PoseCorrection) -> None:
        """Graph and finalised keyframes ``T_WC <- U_k T_WC`` with the folded scale in their patch
        inverse depths (sensor depths stay as measured); non-keyframe records re-expressed
        (:meth:`.records.PoseRecord.corrected`) and the motion model's velocity (and the motion
        check's held reference) in its reference's folded units."""
        for f in list(self.graph.frames) + list(self._final.values()):
            f.T_WC, s = correction.apply_pose(f.fid, f.T_WC)
            if s != 1.0:
                f.inv_depth = f.inv_depth / s
        for fid, rec in list(self._records.items()):
            if rec is not None:
                self._records[fid] = rec.corrected(fid, correction)
        if self._last_fid is not None and correction.fold_scale:
            update = correction.update_for(self._last_fid)[1]
            self._velocity = PoseCorrection.fold_relative(self._velocity, update)
            if self._motion_reference is not None:
                self._motion_reference = PoseCorrection.fold_relative(self._motion_reference, update)

    def proximity_candidate(self, query_kf_id: int, candidate_kf_ids: list[int]) -> Candidate | None:
        """The best proximity candidate of settled keyframe ``query_kf_id`` among ``candidate_kf_ids``
        (stored, of the current map): pose, angle and flow tests (:mod:`.proximity`), least flow wins."""
        pc = self.config.proximity
        q = self._keyframe(query_kf_id)
        fids = [fid for fid in candidate_kf_ids if fid in self._prox_store and fid >= (self._map_start_fid or 0)]
        frames = [f for f in (self._keyframe(fid) for fid in fids) if f is not None]
        if q is None or not frames:
            return None
        good = q.inv_depth > 0
        if not good.any():
            return None
        depth = float(np.median(1.0 / q.inv_depth[good]))
        T_c = np.stack([f.T_WC for f in frames])
        ok, dist, angle = pose_filter(q.T_WC, T_c, pc.radius * depth, pc.max_angle_deg)
        best = None
        for i in np.nonzero(ok)[0]:
            f = frames[i]
            uv, valid = self._reproject_patches(f, q)
            if valid.mean() < pc.min_overlap:
                continue
            flow = float(np.linalg.norm(uv[valid] - f.uv[valid], axis=1).mean())
            if flow <= pc.max_flow_px and (best is None or flow < best.flow):
                best = Candidate(f.fid, float(dist[i]), float(angle[i]), flow, float(valid.mean()))
        return best

    def _reproject_patches(self, a: GraphFrame, b: GraphFrame) -> tuple[np.ndarray, np.ndarray]:
        """Frame a's patch centres reprojected into frame b's left image at the current poses and
        depths: (K, 2) pixels and validity (in front, inside the image with the patch margin)."""
        uv, ok = self._reproject_frame(a, b)
        return uv, ok & self._inside(uv)

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> dict | None:
        """Loop edges between the candidate's neighbourhood (stored keyframes) and the query's (graph
        frames with features), measured from two starts (current reprojection and zero motion; the
        more confident wins) and verified per frame pair by a fundamental-matrix RANSAC. Returns
        the verified edges as an inactive-edge chunk, or None."""
        pc = self.config.proximity
        store = self._prox_store
        q = self._keyframe(query_kf_id)
        old = [candidate_kf_id] + store.neighbours(candidate_kf_id, pc.old_neighbours)
        old = [f for f in (self._keyframe(fid) for fid in old) if f is not None]
        if q is None or not old:
            return None
        pq = self.graph.position(q.fid)
        new = [f for f in self.graph.frames[max(0, pq - pc.new_neighbours): pq + pc.new_neighbours + 1]
               if f.features is not None]
        feats_old = {f.fid: self.source.unpack(store.get(f.fid)) for f in old}
        groups = []  # (src frame, tgt frame, src feats, tgt feats, pair id)
        for pair, (o, n) in enumerate((o, n) for o in old for n in new):
            groups.append((o, n, feats_old[o.fid], n.features, pair))
            groups.append((n, o, n.features, feats_old[o.fid], pair))
        requests, starts = [], []
        for a, b, fa, fb, _ in groups:
            pred, _ = self._reproject_patches(a, b)
            requests.append((fa, fb, a.uv, pred))
            starts.append((fa, fb, a.uv, a.uv.copy()))
        t0 = time.perf_counter()
        from_pred = self.source.measure_batch(requests)
        from_zero = self.source.measure_batch(starts)
        self._times["flow"] += time.perf_counter() - t0
        chunks, valid_total, inlier_total = [], 0, 0
        by_pair: dict[int, list] = {}
        for (a, b, _, _, pair), m1, m0 in zip(groups, from_pred, from_zero):
            use0 = m0.confidence > m1.confidence
            uv = np.where(use0[:, None], m0.uv, m1.uv)
            conf = np.where(use0, m0.confidence, m1.confidence)
            by_pair.setdefault(pair, []).append((a, b, uv, conf))
        for pair, parts in by_pair.items():
            # one fundamental matrix per frame pair: both directions as (old pixel, new pixel)
            pts_o, pts_n, owners = [], [], []
            for k, (a, b, uv, conf) in enumerate(parts):
                ok = conf > 0
                if k == 0:
                    pts_o.append(a.uv[ok]); pts_n.append(uv[ok])
                else:
                    pts_o.append(uv[ok]); pts_n.append(a.uv[ok])
                owners.append(np.nonzero(ok)[0])
            counts = [len(o) for o in owners]
            valid_total += sum(counts)
            inl = fundamental_inliers(np.concatenate(pts_o), np.concatenate(pts_n), pc.ransac_threshold_px)
            inlier_total += int(inl.sum())
            offset = 0
            for (a, b, uv, conf), idx, cnt in zip(parts, owners, counts):
                keep = idx[inl[offset: offset + cnt]]
                offset += cnt
                if keep.size:
                    chunks.append({"src": np.full(keep.size, a.fid, np.int64), "patch": keep.astype(np.int64),
                                   "tgt": np.full(keep.size, b.fid, np.int64), "right": np.zeros(keep.size, bool),
                                   "uv_src": a.uv[keep].astype(np.float32), "uv": uv[keep].astype(np.float32),
                                   "confidence": conf[keep].astype(np.float32),
                                   "inv_depth": a.inv_depth[keep].astype(np.float32)})
        ratio = inlier_total / max(valid_total, 1)
        if inlier_total < pc.min_loop_edges or ratio < pc.min_inlier_ratio:
            logger.info("proximity loop %d -> %d rejected: %d verified of %d measured loop edges",
                        q.index, self._keyframe(candidate_kf_id).index, inlier_total, valid_total)
            return None
        return {key: np.concatenate([c[key] for c in chunks]) for key in chunks[0]}

    def global_ba_job(self, loop_edges: dict | None = None) -> GlobalBAJob | None:
        """Snapshot for a global BA over the current map's keyframes with every active, inactive and
        (given) loop edge (held: keyframes known only through loop edges, and the gauge: the oldest
        one, monocular two); solved by :func:`.global_ba.global_bundle_adjustment`."""
        pc = self.config.proximity
        g = self.graph
        start = self._map_start_fid or 0
        frames = sorted([f for f in self._final.values() if f.fid >= start] + list(g.frames), key=lambda f: f.fid)
        if not frames:
            return None
        fids = np.array([f.fid for f in frames], np.int64)
        parts = []
        inactive = g.inactive.arrays()
        if inactive:
            parts.append({k: inactive[k] for k in ("src", "patch", "tgt", "right", "uv", "confidence")})
        active = g.confidence > 0
        parts.append({"src": g.src[active], "patch": g.patch[active], "tgt": g.tgt[active], "right": g.right[active],
                      "uv": g.uv[active], "confidence": g.confidence[active]})
        n_loop = 0
        if loop_edges is not None:
            parts.append({k: loop_edges[k] for k in ("src", "patch", "tgt", "right", "uv", "confidence")})
            n_loop = len(loop_edges["src"])
        e = {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in parts[0]}
        is_loop = np.zeros(len(e["src"]), bool)
        if n_loop:
            is_loop[-n_loop:] = True
        known = np.isin(e["src"], fids) & np.isin(e["tgt"], fids) & (e["confidence"] > 0)
        e = {k: v[known] for k, v in e.items()}
        is_loop = is_loop[known]
        src_i, tgt_i = np.searchsorted(fids, e["src"]), np.searchsorted(fids, e["tgt"])
        Kp = self.config.graph.patches_per_frame
        ukeys, struct_idx = np.unique(src_i * Kp + e["patch"], return_inverse=True)
        owner, patch = ukeys // Kp, ukeys % Kp
        uv_all = np.stack([f.uv for f in frames])
        d_all = np.stack([f.inv_depth for f in frames])
        prior = {}
        if self.sensor_mode == "rgbd":
            sens = np.stack([f.sensor_inv_depth for f in frames])[owner, patch]
            prior = depth_priors(sens, self.config.ba.depth_noise_model()).kwargs()
        fixed = held_frames(len(frames), src_i, tgt_i, is_loop, 2 if self.sensor_mode == "mono" else 1)
        T_WC = np.stack([f.T_WC for f in frames])
        problem = GlobalBAProblem(
            T_WC=T_WC.copy(), fixed=fixed, src=src_i, tgt=tgt_i, right=e["right"].astype(bool),
            uv_src=uv_all[src_i, e["patch"]], uv=e["uv"].astype(np.float64),
            weight=e["confidence"].astype(np.float64) / self.config.ba.pixel_sigma ** 2, struct_idx=struct_idx,
            inv_depth=d_all[owner, patch], K=self.K.numpy().copy(),
            K_right=None if self.K_right is None else self.K_right.numpy().copy(), T_CRCL=self.T_CRCL, **prior)
        return GlobalBAJob(solve=partial(global_bundle_adjustment, problem, pc.ba, self._reproj), kf_ids=fids,
                           T_WC=T_WC, is_loop=is_loop, loop_edges=loop_edges, in_process=True,
                           context={"owner": owner, "patch": patch, "inv_depth": d_all, "known": known, "n_loop": n_loop})

    def apply_global_ba(self, job: GlobalBAJob, result, keep_loop: np.ndarray) -> None:
        """Hand-over of an accepted global BA (before its pose correction): the optimised patch depths
        of the keyframes whose pose and depths did not change since the snapshot (the others keep
        theirs: their pose gets the correction, and their depths are the newer local BA's); the loop
        edges that kept a weight join the inactive store."""
        ctx = job.context
        owner, patch = ctx["owner"], ctx["patch"]
        for pos in np.unique(owner):
            f = self._keyframe(int(job.kf_ids[pos]))
            if f is None or not (np.array_equal(f.T_WC, job.T_WC[pos]) and np.array_equal(f.inv_depth, ctx["inv_depth"][pos])):
                continue
            sel = owner == pos
            f.inv_depth = f.inv_depth.copy()
            f.inv_depth[patch[sel]] = result.inv_depth[sel]
        n_loop = ctx["n_loop"]
        if n_loop:
            keep = np.zeros(n_loop, bool)
            keep[ctx["known"][-n_loop:]] = keep_loop
            if keep.any():
                self.graph.inactive.add({k: v[keep] for k, v in job.loop_edges.items()})
