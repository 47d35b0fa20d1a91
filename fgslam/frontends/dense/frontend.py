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
5. keyframes beyond ``graph.active_keyframes`` leave the active graph (to the loop closer); every
   ``global_ba.every`` keyframes and at the end a **global optimisation** rebuilds the edges from the
   N x N flow-distance matrix (:func:`.graph.select_global_edges`) and optimises every keyframe of
   the map through the backend (``optimize_window`` over them: older maps stay as they are).

Initialisation: monocular collects ``graph.init_keyframes`` keyframes (tracked against a constant
depth map), connects them and optimises them all (first keyframe anchored, the distance between
the first and last the world scale); stereo and RGB-D start with metric depth at the first frame.
"""

from __future__ import annotations

import logging
import time
from typing import Optional

import cv2
import numpy as np
import torch

from ...services.contributor import KeyframeImage, PoseCorrection
from ...backend.graph import Backend
from ...backend.keys import pose_key
from ...errors import ConfigError, DataError, OptimizationError
from ...factors.dense import DenseBlock, DenseBlockConfig, DenseEdge, DenseKeyframe, DenseSourceBlock, DenseStereo
from ...factors.reprojection import ReprojectionConfig
from ...factors.schur import POSE_DIM, torch_threads
from ...factors.visual_block import BlockConfig
from ...lie import gtsam_matrix, gtsam_sim3, sim3_matrix_parts
from ..base import BackendFrontend, FrameStatus, SensorMode
from ..records import per_frame_motion
from ..records import AbsolutePose, KeyframePose, PoseRecord, RelativePose, resolve_pose, rigid, sim3_power
from .config import DenseConfig
from .graph import DenseKeyframeState, EdgeMeasurement, FrameGraph, select_global_edges
from ..flow import grid_intrinsics
from .source import make_dense_source

logger = logging.getLogger(__name__)

#: information added to every inverse depth in the motion-only optimisation (holds the keyframe's map)
_HOLD_DEPTH = 1e12
#: information on the frame's log-scale in the motion-only optimisation (unobservable there)
_HOLD_SCALE = 1e8
_HOLD_SCALE_ONLY = np.array([0.0] * (POSE_DIM - 1) + [_HOLD_SCALE])


def _pool(a: np.ndarray, s: int) -> np.ndarray:
    """Block means of an (H, W[, C]) array over s x s blocks."""
    H, W = a.shape[:2]
    return a.reshape(H // s, s, W // s, s, *a.shape[2:]).mean(axis=(1, 3))


class DenseFrontend(BackendFrontend):
    """DROID-SLAM-style dense frontend (module docstring); builder of the ``dense`` family.

    Args as :class:`fgslam.frontends.patch.PatchFrontend`: ``config`` the ``dense`` section,
    ``calibration`` (None: the first frame's), ``sensor_mode`` mono | stereo | rgbd, ``backend`` (the
    run's backend; every keyframe pose lives there). Loop closure reaches it through the loop port the
    system connects (the frontend is the loop service's contributor).
    """

    name = "dense"
    _skip_nonfinite_poses = True  # a diverged motion-only solve leaves no pose (not a non-finite one)

    def __init__(self, config: DenseConfig | None = None, calibration=None, sensor_mode: SensorMode = "mono",
                 backend: Backend | None = None):
        self._attach(config or DenseConfig(), sensor_mode, backend)
        self.source = make_dense_source(self.config.source)
        self.stride = int(self.config.source.stride)
        self._reproj = ReprojectionConfig(min_depth=self.config.ba.min_depth)
        self.calibration = None
        self.graph: FrameGraph | None = None
        if calibration is not None:
            self._set_calibration(calibration)
        self._final: dict[int, DenseKeyframeState] = {}  # keyframes of earlier maps (after a restart)
        self._initialized = False
        self._last_fid: int | None = None
        self._velocity = np.eye(4)
        self._lost = 0
        self._failures = 0
        self._counts = {"keyframes_added": 0, "keyframes_removed": 0, "tracking_failures": 0, "map_restarts": 0,
                        "global_runs": 0, "low_confidence_frames": 0, "low_texture_frames": 0}
        self._new_since_global = 0
        self._times = {"flow": 0.0, "tracking": 0.0, "ba": 0.0, "global": 0.0, "bookkeeping": 0.0}
        self._pending_origin: np.ndarray | None = None  # pose of the next map's first keyframe after a restart
        self._init_frames: dict[int, tuple[int, np.ndarray]] = {}  # monocular, before initialisation: fid -> (keyframe, image)

    # ------------------------------------------------------------------ calibration
    def _set_calibration(self, calibration) -> None:
        self.calibration = calibration
        self.K = np.asarray(calibration.K, dtype=np.float64)
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
        self.graph = FrameGraph(self.K_grid, (self.height // s, self.width // s), s, self._reproj, self._kf_pose)

    def _cropped(self, image: np.ndarray | None) -> np.ndarray | None:
        """The part of an image (or depth map) the grid covers."""
        if image is None:
            return None
        H, W = self.crop
        return image if image.shape[:2] == (H, W) else np.ascontiguousarray(image[:H, :W])

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
            self._global()
        self._feed_loops(all_keyframes=True)

    def finish_map(self) -> None:
        logger.info("dense frontend: %d frames, %d keyframes, %d tracking failures, counts %s",
                    len(self._inputs), self.num_keyframes(), self._failures, self._counts)

    def keyframe_depths(self) -> dict[int, tuple[float, np.ndarray, np.ndarray | None]] | None:
        """Keyframe id -> (timestamp, depth (H, W) float32 in map units, confidence (H, W) in [0, 1]):
        the grid inverse depths upsampled (bilinear) to the image and inverted; pixels whose
        confidence is below ``point_confidence`` are 0 (no depth)."""
        kfs = self._all_keyframes()
        if not kfs:
            return None
        out = {}
        for kf in kfs:
            T = self._keyframe_T_WC(kf.fid)
            s = float(sim3_matrix_parts(T)[2])
            H, W = self.crop
            inv = np.zeros((self.height, self.width), np.float32)
            conf = np.zeros((self.height, self.width), np.float32)
            inv[:H, :W] = cv2.resize(kf.inv_depth.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
            conf[:H, :W] = cv2.resize(kf.confidence.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
            depth = np.where((inv > 0) & (conf >= self.config.point_confidence), s / np.maximum(inv, 1e-12), 0.0)
            out[kf.fid] = (kf.timestamp, depth.astype(np.float32), np.clip(conf, 0.0, 1.0))
        return out

    def keyframe_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Confidence-filtered grid points of every keyframe in the world frame, with their colours."""
        chunks_X, chunks_c = [], []
        fx, fy, cx, cy = self.K_grid if self.graph is not None else (1, 1, 0, 0)
        for kf in self._all_keyframes():
            ok = (kf.confidence >= self.config.point_confidence) & (kf.inv_depth > 0)
            if not ok.any():
                continue
            y, x = np.nonzero(ok)
            z = 1.0 / kf.inv_depth[y, x]
            X_C = np.stack([(x - cx) / fx * z, (y - cy) / fy * z, z], -1)
            T = self._keyframe_T_WC(kf.fid)
            chunks_X.append(X_C @ T[:3, :3].T + T[:3, 3])
            chunks_c.append(kf.colour[y, x])
        if not chunks_X:
            return None
        return np.concatenate(chunks_X), np.concatenate(chunks_c).astype(np.uint8)

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

    def _kf_pose(self, fid: int) -> np.ndarray:
        return self.backend.pose_matrix(fid)

    def _keyframe_T_WC(self, fid: int) -> np.ndarray:
        return self.backend.pose_matrix(fid)

    def _pose_of(self, fid: int) -> np.ndarray | None:
        return resolve_pose(fid, self._records, self._keyframe_T_WC, {})

    def _status(self, fid, frame, source, is_keyframe=False, num_valid=0, events=None) -> FrameStatus:
        T = self._pose_of(fid) if self._initialized else None
        return FrameStatus(index=int(frame.index), timestamp=float(frame.timestamp),
                           T_WC=None if T is None else rigid(T), pose_source=source, is_keyframe=is_keyframe,
                           num_valid=int(num_valid), events=list(events or []))

    def _predict(self) -> np.ndarray:
        T_last = self._pose_of(self._last_fid) if self._last_fid is not None else None
        if T_last is None:
            return np.eye(4) if self._pending_origin is None else self._pending_origin
        return T_last @ sim3_power(self._velocity, self.config.tracking.motion_damping)

    def _update_velocity(self, fid: int) -> None:
        if self._last_fid is not None:
            T_prev, T_new = self._pose_of(self._last_fid), self._pose_of(fid)
            if T_prev is not None and T_new is not None:
                self._velocity = per_frame_motion(T_prev, T_new, fid - self._last_fid)
        self._last_fid = fid

    # ------------------------------------------------------------------ per frame
    def _measure_frame(self, fid: int, frame) -> FrameStatus:
        g = self.graph
        if not g.keyframes:  # the first keyframe of a map
            T0 = self._pending_origin if self._pending_origin is not None else np.eye(4)
            self._pending_origin = None
            self._new_keyframe(fid, frame, T0)
            self._velocity = np.eye(4)
            self._last_fid = fid
            if self.sensor_mode != "mono":
                self._initialized = True
                return self._status(fid, frame, "tracked", is_keyframe=True, events=["initialised"])
            return self._status(fid, frame, "initializing", is_keyframe=True)
        t0 = time.perf_counter()
        kf_fid = g.active[-1]
        T_pred = self._predict()
        textured = self._textured_share(frame.image)
        if textured < self.config.tracking.min_textured:
            self._counts["low_texture_frames"] += 1
            return self._fail(fid, frame, f"tracking lost: no texture ({100 * textured:.1f} % of the grid textured)", T_pred)
        flow0 = self._times["flow"]
        self.source.add_frame(fid, self._cropped(frame.image))
        T_WC, flow, n_conf, ok = self._track(kf_fid, fid, T_pred)
        self._times["tracking"] += time.perf_counter() - t0 - (self._times["flow"] - flow0)
        n_pix = g.shape[0] * g.shape[1]
        if not ok or n_conf < self.config.tracking.min_confident * n_pix:
            self.source.remove_frame(fid)
            self._counts["low_confidence_frames"] += 1
            return self._fail(fid, frame, f"tracking lost: {n_conf} of {n_pix} grid pixels confident", T_pred)
        self._lost = 0
        if flow <= self.config.graph.motion_filter_flow:
            self.source.remove_frame(fid)
            self._records[fid] = RelativePose(kf_fid, np.linalg.inv(self._keyframe_T_WC(kf_fid)) @ T_WC)
            if not self._initialized:  # tracked against a provisional depth map: re-tracked after the initialisation
                self._init_frames[fid] = (kf_fid, self._cropped(frame.image))
            self._update_velocity(fid)
            source = "tracked" if self._initialized else "initializing"
            return self._status(fid, frame, source, num_valid=n_conf)
        events = []
        self._new_keyframe(fid, frame, T_WC, source_added=True)
        if not self._initialized:
            if len(g.keyframes) >= self.config.graph.init_keyframes:
                self._initialize()
                events.append("initialised")
            self._update_velocity(fid)
            return self._status(fid, frame, "tracked" if self._initialized else "initializing", True, n_conf, events)
        self._local_ba(fid)
        removed = self._remove_redundant()
        if removed is not None:
            events.append(f"keyframe removed: {removed}")
        self._retire()
        self._update_velocity(fid)
        self._new_since_global += 1
        every = self.config.global_ba.every
        if every and self._new_since_global >= every:
            self._global()
        return self._status(fid, frame, "tracked", fid in g.keyframes, n_conf, events)

    def _textured_share(self, image: np.ndarray) -> float:
        """Share of grid blocks of the frame whose RMS image gradient exceeds ``tracking.texture_gradient``."""
        img = self._cropped(image).astype(np.float32)
        gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
        gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)
        energy = _pool(gx * gx + gy * gy, self.stride)
        return float((energy > self.config.tracking.texture_gradient ** 2).mean())

    def _fail(self, fid: int, frame, reason: str, T_pred: np.ndarray | None = None) -> FrameStatus:
        """Tracking failure: predicted pose relative to the newest keyframe, counted; a map restart
        after ``tracking.max_lost`` in a row."""
        self._failures += 1
        self._counts["tracking_failures"] += 1
        self._lost += 1
        events = [reason]
        g = self.graph
        if g is not None and g.active and self._last_fid is not None:
            if T_pred is None:
                T_pred = self._predict()
            ref = g.active[-1]
            self._records[fid] = RelativePose(ref, np.linalg.inv(self._keyframe_T_WC(ref)) @ T_pred)
            self._last_fid = fid
        logger.info("frame %d: %s", frame.index, reason)
        if self._lost >= self.config.tracking.max_lost and g is not None and g.keyframes:
            events.append(self._restart(fid, frame))
        return self._status(fid, frame, "motion_model", events=events)

    def _restart(self, fid: int, frame) -> str:
        """Start a new map: the current one is finalised (kept for outputs), the next keyframe starts at
        the relocalised pose when the loop service finds one, else at the last prediction."""
        self._counts["map_restarts"] += 1
        self._feed_loops(all_keyframes=True)
        T = self._pose_of(fid)
        found = self.loops.relocalize(frame.image, self.K)
        if found is not None:
            T = np.asarray(found[1], dtype=np.float64)
            self._records[fid] = AbsolutePose(T)
        g = self.graph
        for kf in g.keyframes.values():
            kf.image = None
            self._final[kf.fid] = kf
            self.source.remove_frame(kf.fid)
        self.backend.set_blocks(self.name, [])
        self._set_calibration(self.calibration)  # an empty graph
        self.loops.map_reset()
        self._initialized = False
        self._lost = 0
        self._pending_origin = T if T is not None else np.eye(4)
        self._last_fid = None
        self._velocity = np.eye(4)
        return "map restarted" + (" (relocalised)" if found is not None else "")

    # ------------------------------------------------------------------ tracking
    def _track(self, kf_fid: int, fid: int, T_pred: np.ndarray) -> tuple[np.ndarray, float, int, bool]:
        """Motion-only pose of frame ``fid`` against keyframe ``kf_fid``: (T_WC, mean measured flow in
        image px over confident pixels, confident grid pixels, success)."""
        import gtsam

        cfg = self.config.tracking
        g = self.graph
        kf = g.keyframes[kf_fid]
        T_kf = self._keyframe_T_WC(kf_fid)
        # the frame starts at the keyframe's scale (its scale is unobservable here)
        R, t, _ = sim3_matrix_parts(T_pred, project=True)
        s_kf = float(sim3_matrix_parts(T_kf)[2])
        T = np.eye(4)
        T[:3, :3] = s_kf * R
        T[:3, 3] = t
        key_kf, key_f = pose_key(kf_fid), pose_key(fid)
        flow, n_conf, rev = np.inf, 0, None
        for _ in range(cfg.rounds):
            t0 = time.perf_counter()
            induced = self._induced_to(kf, T_kf, T)
            (rev,) = self.source.revise([(kf_fid, fid)], induced[None])
            self._times["flow"] += time.perf_counter() - t0
            weight = rev.weight * self._huber(rev.target - induced)
            conf = rev.weight.mean(-1) > cfg.confident_weight
            n_conf = int(conf.sum())
            if n_conf == 0:
                return T, np.inf, 0, False
            block = DenseSourceBlock(
                DenseKeyframe(key_kf, kf.inv_depth, damping=np.full(g.shape, _HOLD_DEPTH)),
                [DenseEdge(key_kf, key_f, rev.target, weight * self._information())], self.K_grid,
                self._block_config())
            values = gtsam.Values()
            values.insert(key_kf, gtsam_sim3(T_kf))
            values.insert(key_f, gtsam_sim3(T))
            result = self.backend.optimize_pose([block], values, key_f, cfg.iterations, hold=_HOLD_SCALE_ONLY)
            T = gtsam_matrix(result.values.atSimilarity3(key_f))
        flow = float(np.linalg.norm(rev.target - g.grid, axis=-1)[conf].mean() * self.stride)
        return T, flow, n_conf, bool(np.isfinite(T).all())

    def _induced_to(self, kf: DenseKeyframeState, T_kf: np.ndarray, T: np.ndarray) -> np.ndarray:
        """Field (h, w, 2) keyframe ``kf``'s grid induces in a camera at ``T`` (NaN: invalid)."""
        from ...factors.reprojection import reproject
        from ...lie import sim3_matrix_components

        Ra, ta, sa = sim3_matrix_components(T_kf[None])
        Rb, tb, sb = sim3_matrix_components(T[None])
        g = self.graph
        uv, ok = reproject(torch.as_tensor(g.grid.reshape(-1, 2)), torch.as_tensor(kf.inv_depth.reshape(-1)),
                           (Ra[0], ta[0], sa[0]), (Rb[0], tb[0], sb[0]), g.K, config=self._reproj)
        out = uv.numpy().reshape(*g.shape, 2).copy()
        out[~ok.numpy().reshape(g.shape)] = np.nan
        return out

    def _huber(self, revision: np.ndarray) -> np.ndarray:
        """Huber weight (h, w, 1) of a revision (grid px) measured in image px (1 below the threshold)."""
        k = self.config.ba.huber
        if k <= 0:
            return np.ones(revision.shape[:-1] + (1,))
        r = np.linalg.norm(np.nan_to_num(revision, nan=0.0), axis=-1, keepdims=True) * self.stride
        return np.where(r <= k, 1.0, k / np.maximum(r, 1e-12))

    def _information(self) -> float:
        """Weight of a fully confident flow row: 1 / sigma^2 with sigma in grid px."""
        return (self.stride / self.config.ba.pixel_sigma) ** 2

    def _block_config(self) -> DenseBlockConfig:
        return DenseBlockConfig(block=BlockConfig(structure_damping=self.config.ba.damping, threads=self.config.threads,
                                                  per_edge_min_rows=self.config.ba.per_edge_min_rows),
                                reprojection=self._reproj, depth_prior=self.config.ba.depth_prior)

    # ------------------------------------------------------------------ keyframes
    def _new_keyframe(self, fid: int, frame, T_WC: np.ndarray, source_added: bool = False) -> None:
        g = self.graph
        s = self.stride
        image = self._cropped(frame.image)
        if not source_added:
            self.source.add_frame(fid, image)
        rgb = self._cropped(frame.rgb) if frame.rgb is not None else np.repeat(image[..., None], 3, axis=-1)
        colour = np.clip(_pool(rgb.astype(np.float32), s), 0, 255).astype(np.uint8)
        sensor = None
        inv = None
        if self.sensor_mode == "rgbd":
            sensor = self._grid_depth(self._cropped(frame.depth))
            inv = 1.0 / sensor
        prev = g.keyframes[g.active[-1]] if g.active else None
        if inv is None or not np.isfinite(inv).any():
            inv = self._splat_depth(prev, T_WC) if prev is not None else np.full(g.shape, 1.0)
        else:
            fill = np.nanmedian(inv)
            inv = np.where(np.isfinite(inv), inv, fill)
        kf = DenseKeyframeState(fid=fid, index=int(frame.index), timestamp=float(frame.timestamp), image=frame.image,
                                inv_depth=inv.astype(np.float64), colour=colour, sensor_depth=sensor,
                                depth_image=frame.depth if self.sensor_mode == "rgbd" else None,
                                confidence=np.zeros(g.shape))
        self.backend.add_keyframe(fid, T_WC, float(frame.timestamp))
        self._records[fid] = KeyframePose()
        g.add(kf)
        self._counts["keyframes_added"] += 1
        if self.sensor_mode == "stereo":
            self._measure_stereo(kf, self._cropped(frame.image_right), init_depth=True)
        self._connect(fid)

    def _grid_depth(self, depth: np.ndarray) -> np.ndarray:
        """Sensor depth per grid block (metres; NaN where the block has too few readings, or spans a depth
        edge / misregistered boundary: relative spread of its inverse depths above ``ba.depth_edge``)."""
        s = self.stride
        z = np.asarray(depth, dtype=np.float64)
        ok = np.isfinite(z) & (z > 0)
        inv = np.where(ok, 1.0 / np.where(ok, z, 1.0), 0.0)
        n = _pool(ok.astype(np.float64), s)
        mean = _pool(inv, s) / np.maximum(n, 1e-12)
        sq = _pool(inv * inv, s) / np.maximum(n, 1e-12)
        spread = np.sqrt(np.maximum(sq - mean * mean, 0.0)) / np.maximum(mean, 1e-12)
        good = (n >= 0.5) & (mean > 0)
        if self.config.ba.depth_edge > 0:
            good &= spread <= self.config.ba.depth_edge
        bad = int((~good).sum())
        if bad == good.size:
            logger.info("RGB-D keyframe: no valid sensor depth (holes / NaN); depth from the flow only")
        return np.where(good, 1.0 / np.maximum(mean, 1e-12), np.nan)

    def _splat_depth(self, prev: DenseKeyframeState, T_WC: np.ndarray) -> np.ndarray:
        """Inverse-depth map of a new keyframe at ``T_WC``: the previous keyframe's map transferred into it
        (z-buffered, nearest grid pixel), holes filled with the median."""
        g = self.graph
        h, w = g.shape
        fx, fy, cx, cy = self.K_grid
        T_prev = self._keyframe_T_WC(prev.fid)
        P = np.linalg.inv(T_WC) @ T_prev  # prev camera -> new camera (Sim(3) matrices: metric per camera)
        z = 1.0 / np.maximum(prev.inv_depth, 1e-9)
        X = np.stack([(g.grid[..., 0] - cx) / fx * z, (g.grid[..., 1] - cy) / fy * z, z], -1).reshape(-1, 3)
        Xn = X @ P[:3, :3].T + P[:3, 3]
        zn = Xn[:, 2]
        ok = zn > self.config.ba.min_depth
        u = np.rint(fx * Xn[:, 0] / np.where(ok, zn, 1.0) + cx).astype(np.int64)
        v = np.rint(fy * Xn[:, 1] / np.where(ok, zn, 1.0) + cy).astype(np.int64)
        ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
        out = np.zeros(h * w)
        np.maximum.at(out, v[ok] * w + u[ok], 1.0 / zn[ok])
        fill = np.median(out[out > 0]) if (out > 0).any() else float(np.median(prev.inv_depth))
        return np.where(out > 0, out, fill).reshape(h, w)

    def _measure_stereo(self, kf: DenseKeyframeState, right: np.ndarray, init_depth: bool) -> None:
        """Left-right flow of a stereo keyframe (its rows fix the metric depth through ``T_CRCL``);
        ``init_depth``: the keyframe's inverse depths from the measured disparity first."""
        from ...factors.reprojection import reproject

        g = self.graph
        rid = -(kf.fid + 1)
        t0 = time.perf_counter()
        self.source.add_frame(rid, right)
        try:
            if init_depth:
                (rev,) = self.source.revise([(kf.fid, rid)], g.grid[None])
                baseline = float(np.linalg.norm(self.T_CRCL[:3, 3]))
                disparity = g.grid[..., 0] - rev.target[..., 0]
                good = (rev.weight.mean(-1) > self.config.tracking.confident_weight) & (disparity > 1e-3)
                if good.sum() >= 0.05 * good.size:
                    inv = disparity / (self.K_grid[0] * baseline)
                    kf.inv_depth = np.where(good, inv, np.median(inv[good]))
            I = (torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), torch.ones((), dtype=torch.float64))
            uv, ok = reproject(torch.as_tensor(g.grid.reshape(-1, 2)), torch.as_tensor(kf.inv_depth.reshape(-1)), I, I,
                               g.K, torch.as_tensor(self.K_right_grid), T_CtCj=torch.as_tensor(self.T_CRCL),
                               config=self._reproj)
            induced = uv.numpy().reshape(*g.shape, 2).copy()
            induced[~ok.numpy().reshape(g.shape)] = np.nan
            (rev,) = self.source.revise([(kf.fid, rid)], induced[None])
        finally:
            self.source.remove_frame(rid)
        self._times["flow"] += time.perf_counter() - t0
        weight = rev.weight * self._huber(rev.target - induced) * self.config.ba.stereo_weight
        kf.stereo = DenseStereo(rev.target, weight * self._information(), self.K_right_grid, self.T_CRCL)

    def _connect(self, fid: int) -> None:
        """Edges (both ways) from the new keyframe to the previous ``temporal_radius`` active keyframes
        and to the ``neighbours`` nearest others by flow distance (below ``max_edge_distance``)."""
        g = self.graph
        cfg = self.config.graph
        others = [f for f in g.active if f != fid]
        if not others:
            return
        temporal = others[-cfg.temporal_radius:]
        rest = [f for f in others if f not in temporal]
        near: list[int] = []
        if rest:
            d = g.flow_distance([(fid, f) for f in rest] + [(f, fid) for f in rest], cfg.distance_stride)
            d = 0.5 * (d[:len(rest)] + d[len(rest):])
            order = np.argsort(d, kind="stable")
            near = [rest[k] for k in order[:cfg.neighbours] if d[k] < cfg.max_edge_distance]
        for f in temporal + near:
            for e in ((fid, f), (f, fid)):
                g.edges.setdefault(e, EdgeMeasurement(np.full(g.shape + (2,), np.nan), np.zeros(g.shape + (2,))))

    # ------------------------------------------------------------------ measurement and BA
    def _measure(self, edges: list[tuple[int, int]]) -> None:
        """Measure ``edges`` from the fields the current estimate induces; stores their revisions
        (confidence times the Huber weight of the revision) and the sources' confidence maps."""
        if not edges:
            return
        t0 = time.perf_counter()
        g = self.graph
        induced, _ = g.induced(edges)
        revs = self.source.revise(edges, induced)
        for (i, j), rev, ind in zip(edges, revs, induced):
            w = rev.weight * self._huber(rev.target - ind)
            g.edges[(i, j)] = EdgeMeasurement(rev.target, w)
        for i in {e[0] for e in edges}:
            kf = g.keyframes[i]
            kf.confidence = np.max([g.edges[e].weight.mean(-1) for e in g.edges if e[0] == i], axis=0)
        self._times["flow"] += time.perf_counter() - t0

    def _block(self, edges: list[tuple[int, int]]) -> DenseBlock:
        g = self.graph
        info = self._information()
        sources = sorted({i for i, _ in edges}, key=list(g.keyframes).index)
        kfs = [DenseKeyframe(pose_key(i), g.keyframes[i].inv_depth, sensor_depth=g.keyframes[i].sensor_depth,
                             stereo=g.keyframes[i].stereo) for i in sources]
        dedges = [DenseEdge(pose_key(i), pose_key(j), g.edges[(i, j)].target, g.edges[(i, j)].weight * info)
                  for i, j in edges]
        return DenseBlock(kfs, dedges, self.K_grid, self._block_config())

    def _optimize(self, free: list[int], edges: list[tuple[int, int]], iterations: int, init: bool,
                  global_: bool = False) -> None:
        """One optimisation of the free keyframes with the dense block of ``edges`` through the backend."""
        g = self.graph
        block = self._block(edges)
        fixed = [k for k in block.keys if k not in {pose_key(f) for f in free}]
        anchor = free[0] if (init or global_ or not fixed) else None
        pair = (free[0], free[-1]) if init and self.sensor_mode == "mono" and len(free) >= 2 else None
        if global_ and self.sensor_mode == "mono" and len(free) >= 2:
            pair = (free[0], free[1])
        self.backend.set_gauge(anchor=anchor, scale_pair=pair)
        self.backend.set_blocks(self.name, [block])
        self.backend.optimize_window(free, iterations)
        fid_of = {pose_key(f): f for f in g.keyframes}
        for src in block.sources:
            g.keyframes[fid_of[src.keys[0]]].inv_depth = src.inverse_depth.numpy().copy()
        if self.sensor_mode == "rgbd":  # sensor depths observe no Sim(3) scale: written back rigid (as patch)
            for f in free:
                self.backend.set_pose(f, rigid(self.backend.pose_matrix(f)))

    def _local_ba(self, new_fid: int) -> None:
        t0 = time.perf_counter()
        g = self.graph
        cfg = self.config.ba
        free = g.active[-cfg.window:]
        free_set = set(free)
        edges = [e for e in g.active_edges() if e[0] in free_set or e[1] in free_set]
        newest = set(g.active[-cfg.remeasure:]) | {new_fid}
        fresh = [e for e in edges if e[0] in newest or e[1] in newest]
        flow0 = self._times["flow"]
        for _ in range(cfg.rounds):
            self._measure(fresh)
            self._optimize(free, edges, cfg.iterations, init=False)
        self._times["ba"] += time.perf_counter() - t0 - (self._times["flow"] - flow0)

    def _initialize(self) -> None:
        """Monocular initialisation: every collected keyframe connected to its neighbours and optimised."""
        t0 = time.perf_counter()
        g = self.graph
        cfg = self.config.ba
        free = list(g.active)
        for fid in free:  # connect each to every other within reach (few keyframes)
            for f in free:
                if f != fid and g.distance(fid, f, self.config.graph.distance_stride) < self.config.graph.max_edge_distance:
                    g.edges.setdefault((fid, f), EdgeMeasurement(np.full(g.shape + (2,), np.nan), np.zeros(g.shape + (2,))))
        edges = g.active_edges()
        flow0 = self._times["flow"]
        for _ in range(cfg.init_rounds):
            self._measure(edges)
            self._optimize(free, edges, cfg.init_iterations, init=True)
        self._initialized = True
        self._times["ba"] += time.perf_counter() - t0 - (self._times["flow"] - flow0)
        logger.info("dense frontend: initialised on %d keyframes, %d edges", len(free), len(edges))
        self._retrack(self._init_frames)
        self._init_frames = {}

    def _retrack(self, frames: dict[int, tuple[int, np.ndarray]]) -> None:
        """Motion-only poses of non-keyframes ``fid -> (keyframe, image)`` against their keyframe's
        current map, from their current pose (their records become relative to that keyframe)."""
        t0 = time.perf_counter()
        flow0 = self._times["flow"]
        for fid, (kf_fid, image) in frames.items():
            T0 = self._pose_of(fid)
            if T0 is None or kf_fid not in self.graph.keyframes:
                continue
            self.source.add_frame(fid, image)
            try:
                T, _, n_conf, ok = self._track(kf_fid, fid, T0)
            finally:
                self.source.remove_frame(fid)
            if ok and n_conf > 0:
                self._records[fid] = RelativePose(kf_fid, np.linalg.inv(self._keyframe_T_WC(kf_fid)) @ T)
        self._times["tracking"] += time.perf_counter() - t0 - (self._times["flow"] - flow0)

    def _remove_redundant(self) -> int | None:
        g = self.graph
        thr = self.config.graph.remove_threshold
        if thr <= 0 or len(g.active) < 4:
            return None
        a, b = g.active[-3], g.active[-2]
        if g.distance(a, b, self.config.graph.distance_stride) >= thr:
            return None
        kf = g.keyframes[b]
        self._records[b] = RelativePose(a, np.linalg.inv(self._keyframe_T_WC(a)) @ self._keyframe_T_WC(b))
        g.remove(b)
        self.backend.remove_keyframe(b)
        self.source.remove_frame(b)
        self._counts["keyframes_removed"] += 1
        # keep the newest keyframe connected to the older one
        new = g.active[-1]
        for e in ((new, a), (a, new)):
            g.edges.setdefault(e, EdgeMeasurement(np.full(g.shape + (2,), np.nan), np.zeros(g.shape + (2,))))
        return kf.index

    def _retire(self) -> None:
        """Keyframes beyond ``active_keyframes`` leave the active graph (handed to the loop closer);
        images beyond ``global_ba.max_keyframes`` are dropped (their last edges kept)."""
        g = self.graph
        while len(g.active) > self.config.graph.active_keyframes:
            g.active.pop(0)
        self._feed_loops()
        order = g.order()
        for fid in order[: max(0, len(order) - self.config.global_ba.max_keyframes)]:
            kf = g.keyframes[fid]
            if kf.image is not None and fid not in g.active:
                kf.image = None
                self.source.remove_frame(fid)

    # ------------------------------------------------------------------ global optimisation
    def _global(self) -> None:
        """Edges rebuilt from the N x N flow-distance matrix of the map's keyframes (those whose images
        are kept), measured, and every keyframe of the map optimised through the backend."""
        t0 = time.perf_counter()
        flow0 = self._times["flow"]
        g = self.graph
        cfg = self.config.global_ba
        self._new_since_global = 0
        fids = [f for f in g.order() if g.keyframes[f].image is not None]
        n = len(fids)
        if n < 3:
            return
        pairs = [(a, b) for a in fids for b in fids if a != b]
        dist = np.full((n, n), np.inf)
        d = g.flow_distance(pairs, self.config.graph.distance_stride)
        index = {f: k for k, f in enumerate(fids)}
        for (a, b), v in zip(pairs, d):
            dist[index[a], index[b]] = v
        edges = select_global_edges(fids, dist, cfg.temporal_radius, cfg.nms_radius, cfg.max_distance, cfg.max_edges)
        imaged = set(fids)
        kept = [e for e in g.edges if not (e[0] in imaged and e[1] in imaged)]  # edges of dropped images: as stored
        for e in edges:
            g.edges.setdefault(e, EdgeMeasurement(np.full(g.shape + (2,), np.nan), np.zeros(g.shape + (2,))))
        free = g.order()
        for _ in range(cfg.rounds):
            self._measure(edges)
            self._optimize(free, edges + kept, cfg.iterations, init=False, global_=True)
        # the active graph's own edges stay; others built for this run are dropped again (memory)
        active = set(g.active)
        for e in [e for e in g.edges if e not in kept and not (e[0] in active and e[1] in active) and e not in edges]:
            del g.edges[e]
        self._counts["global_runs"] += 1
        self._times["global"] += time.perf_counter() - t0 - (self._times["flow"] - flow0)
        logger.info("dense global optimisation: %d keyframes, %d edges, %.2f s", len(free), len(edges),
                    time.perf_counter() - t0)

    # ------------------------------------------------------------------ loop closure (contributor contract)
    def _feed_loops(self, all_keyframes: bool = False) -> None:
        if not self.loops.classical or self.graph is None:
            return
        g = self.graph
        active = set(g.active)
        order = g.order()
        for p, fid in enumerate(order):
            if all_keyframes or fid not in active:
                self.loops.add_keyframe(fid, [order[q] for q in (p - 1, p + 1) if 0 <= q < len(order)])
        self.loops.update_poses({f: self._keyframe_T_WC(f) for f in order})

    def keyframe_image(self, kf_id: int) -> Optional[KeyframeImage]:
        kf = self.graph.keyframes.get(kf_id) if self.graph is not None else None
        if kf is None or kf.image is None:
            return None
        return KeyframeImage(kf.image, self.K.copy(), kf.timestamp, kf.depth_image)

    def keyframe_pose(self, kf_id: int) -> Optional[np.ndarray]:
        return self.backend.pose_matrix(kf_id) if self.backend.has_keyframe(kf_id) else None

    def apply_correction(self, correction: PoseCorrection) -> None:
        """Keyframe poses ``T_WC <- U_k T_WC`` (the folded scale into their inverse depths), pose records
        re-expressed, the motion model's velocity kept in its reference's units."""
        for kf in self._all_keyframes():
            if not self.backend.has_keyframe(kf.fid):
                continue
            T, s = correction.apply_pose(kf.fid, self.backend.pose_matrix(kf.fid))
            self.backend.set_pose(kf.fid, T)
            if s != 1.0:
                kf.inv_depth = kf.inv_depth / s
        for fid, rec in list(self._records.items()):
            if rec is not None:
                self._records[fid] = rec.corrected(fid, correction)

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> Optional[dict]:
        return None  # classical loops only (no proximity edges of this family yet)
