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

Monocular frames without enough parallax for a two-view pointmap (the source logs it) are tracked by PnP
on the source's dense flow against k's canonical pointmap (pose only, no fusion, never a keyframe). The
monocular map starts when a pair (first frame, later frame) has ``tracking.init_min_confident`` of its
pixels confident; frames before it get no pose.

Loop closure is the shared :class:`~fgslam.services.loops.LoopService` (classical: BoW retrieval,
verification, Sim(3) pose graph, corrections through :meth:`apply_correction`); each loop it accepts is
measured as a pointmap edge (:func:`.keyframes.measure_edge`, accepted with ``graph.min_edge_matches``)
and joins the global optimisation. Non-keyframe poses are :mod:`fgslam.frontends.records` relative to
their keyframe.
"""

from __future__ import annotations

import contextlib
import logging
import time

import cv2
import numpy as np
import torch

from ...services.contributor import KeyframeImage, PoseCorrection
from ...backend.graph import Backend
from ...errors import ConfigError, DataError, OptimizationError
from ...factors.pointmap_block import PointmapBlock, PointmapEdge
from ...factors.schur import torch_threads
from ...lie import Sim3
from ..base import BackendFrontend, FrameStatus, SensorMode
from ..records import AbsolutePose, InterpolatedPose, KeyframePose, PoseRecord, RelativePose, resolve_pose, rigid
from .config import PointmapConfig
from .keyframes import PointmapKeyframe, even_subset, match_frame, measure_edge, query_grid
from .source import make_pointmap_source
from .tracking import fuse_pointmap, track_pose

logger = logging.getLogger(__name__)

__all__ = ["PointmapFrontend", "WorkingCamera"]


class WorkingCamera:
    """The frames at the working resolution: ``scale`` so that the width is at most ``image_width``
    (never enlarged), ``K`` ``(4,)`` scaled with the pixel-centre convention, stereo ``baseline``."""

    def __init__(self, calibration, image_width: int, sensor_mode: str):
        W, H = int(calibration.width), int(calibration.height)
        scale = 1.0 if image_width <= 0 or W <= image_width else image_width / W
        self.W, self.H = int(round(W * scale)), int(round(H * scale))
        self.full = (W, H)
        sx, sy = self.W / W, self.H / H
        fx, fy, cx, cy = (float(k) for k in calibration.K)
        self.K = np.array([fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5])
        self.baseline = None
        if sensor_mode == "stereo":
            if calibration.right is None or calibration.T_CLCR is None:
                raise ConfigError("sensor mode stereo needs a calibration with a right camera and T_CLCR")
            self.baseline = float(np.linalg.norm(np.asarray(calibration.T_CLCR)[:3, 3]))

    def image(self, img: np.ndarray | None) -> np.ndarray | None:
        if img is None or (img.shape[1], img.shape[0]) == (self.W, self.H):
            return img
        return cv2.resize(img, (self.W, self.H), interpolation=cv2.INTER_AREA)

    def depth(self, depth: np.ndarray | None) -> np.ndarray | None:
        if depth is None or (depth.shape[1], depth.shape[0]) == (self.W, self.H):
            return depth
        return cv2.resize(np.asarray(depth, np.float32), (self.W, self.H), interpolation=cv2.INTER_NEAREST)


def _sim3(M: np.ndarray) -> Sim3:
    return Sim3.from_matrix(torch.as_tensor(np.asarray(M, np.float64)))


def _matrix(T: Sim3) -> np.ndarray:
    return T.matrix().numpy().astype(np.float64)


class PointmapFrontend(BackendFrontend):
    """MASt3R-SLAM-style pointmap frontend (module docstring); a contributor of the run's backend.

    Args:
        config: the ``pointmap`` section (defaults when None).
        calibration: the frames' calibration (None: from the first frame).
        sensor_mode: ``mono``, ``stereo`` or ``rgbd`` (``source.kind: auto`` follows it).
        backend: the run's backend (as for every family; loop closure reaches it through the loop
            port the system connects).
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
        self.cam: WorkingCamera | None = None
        self._kfs: dict[int, PointmapKeyframe] = {}  # every keyframe, insertion order
        self._kf: PointmapKeyframe | None = None  # the current keyframe
        self._edges: list[PointmapEdge] = []
        self._edge_pairs: set[tuple[int, int]] = set()
        self._T_kf = np.eye(4)  # last tracked frame relative to the current keyframe (T_CkCf)
        self._uv_prev: torch.Tensor | None = None  # previous frame's matches into the current keyframe
        self._since_kf = 0
        self._init_fid: int | None = None
        self._in_source: list[int] = []  # frames whose source cache is loaded (oldest first)
        self._prev_fid: int | None = None  # the previous frame when it was tracked (its pose is T_kf)
        self._prev_kf: int | None = None  # ... and its keyframe
        self._last_good = None  # (fid, frame, inputs, result, T_CkCf) of the last frame tracked against the keyframe
        self._failures = 0
        self._loops_seen = 0
        self._times = {"source": 0.0, "matching": 0.0, "tracking": 0.0, "optimization": 0.0, "bookkeeping": 0.0}
        self._counts = {"keyframes": 0, "loop_edges": 0, "relocalized": 0, "pnp_tracked": 0, "failed": 0}
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
        self._release_source()

    @property
    def map_started(self) -> bool:
        return self._kf is not None

    def corrections_applied(self) -> None:
        self._loop_edges()

    def finish_map(self) -> None:
        self._loop_edges()
        if self.config.graph.final_iterations > 0 and len(self._kfs) > 1:
            t0 = time.perf_counter()
            try:
                self._set_block()
                self.backend.optimize_window(list(self._kfs), self.config.graph.final_iterations)
            except (OptimizationError, RuntimeError, np.linalg.LinAlgError) as exc:
                logger.warning("pointmap final optimisation failed (%s); poses kept", exc)
            self._times["optimization"] += time.perf_counter() - t0
        logger.info("pointmap frontend: %d frames, %d keyframes, %d edges, %d tracking failures, %s",
                    len(self._inputs), len(self._kfs), len(self._edges), self._failures, self._counts)

    def keyframe_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Canonical pointmaps in the world (every ``ply_stride``-th pixel with a fused confidence of at
        least ``ply_min_confidence``), coloured by the keyframe image."""
        pts, cols = [], []
        for kf in self._kfs.values():
            grid = query_grid(kf.H, kf.W, self.config.ply_stride)
            ok = grid[(kf.C[grid] >= self.config.ply_min_confidence) & torch.isfinite(kf.X[grid]).all(-1)]
            if ok.numel() == 0:
                continue
            T = self._keyframe_T_WC(kf.fid)
            X = kf.X[ok].numpy().astype(np.float64)
            pts.append(X @ T[:3, :3].T + T[:3, 3])
            if kf.colour is not None:
                cols.append(kf.colour.reshape(-1, 3)[ok.numpy()])
            else:
                cols.append(np.repeat(kf.grey.reshape(-1, 1)[ok.numpy()], 3, axis=1))
        if not pts:
            return None
        return np.concatenate(pts), np.concatenate(cols).astype(np.uint8)

    def keyframe_depths(self) -> dict[int, tuple[float, np.ndarray, np.ndarray | None]] | None:
        """kf id -> (timestamp, depth (H, W) float32 metres in the map's scale at the input resolution,
        confidence (H, W) in [0, 1]): the canonical pointmaps' z times the keyframe's scale (0: no point)."""
        if not self._kfs:
            return None
        W, H = self.cam.full
        out = {}
        for kf in self._kfs.values():
            s = float(np.cbrt(abs(np.linalg.det(self._keyframe_T_WC(kf.fid)[:3, :3]))))
            z = (kf.X[:, 2] * s).view(kf.H, kf.W).numpy().astype(np.float32)
            c = kf.C.view(kf.H, kf.W).numpy().astype(np.float32)
            valid = np.isfinite(z) & (z > 0) & (c > 0)
            z = np.where(valid, z, 0.0).astype(np.float32)
            conf = np.where(valid, np.minimum(c, 1.0), 0.0).astype(np.float32)
            if (kf.W, kf.H) != (W, H):
                z = cv2.resize(z, (W, H), interpolation=cv2.INTER_NEAREST)
                conf = cv2.resize(conf, (W, H), interpolation=cv2.INTER_NEAREST)
            out[kf.fid] = (kf.timestamp, z, conf)
        return out

    def add_loop_counts(self, summary: dict) -> None:
        summary["pointmap_loop_edges"] = self._counts["loop_edges"]

    # ------------------------------------------------------------------ contributor contract
    def keyframe_image(self, kf_id: int) -> KeyframeImage | None:
        kf = self._kfs.get(int(kf_id))
        if kf is None:
            return None
        return KeyframeImage(kf.grey, self.cam.K.copy(), kf.timestamp, kf.depth)

    def keyframe_pose(self, kf_id: int) -> np.ndarray | None:
        return self._keyframe_T_WC(int(kf_id)) if int(kf_id) in self._kfs else None

    def apply_correction(self, correction: PoseCorrection) -> None:
        """Every keyframe moved by its update (a folded scale multiplies its canonical pointmap);
        non-keyframe records re-expressed."""
        for fid, kf in self._kfs.items():
            T_new, s = correction.apply_pose(fid, self._keyframe_T_WC(fid))
            self.backend.set_pose(fid, T_new)
            if s != 1.0:
                kf.X *= s
                kf.changed()
                for e in self._edges:  # the edges' snapshot points of this keyframe follow
                    if e.key_i == self.backend_key(fid):
                        e.X_i_in_i = e.X_i_in_i * s
                    if e.key_j == self.backend_key(fid):
                        e.X_j_in_j = e.X_j_in_j * s
        for fid, rec in list(self._records.items()):
            if rec is not None:
                self._records[fid] = rec.corrected(fid, correction)
        if correction.fold_scale and self._kf is not None:
            self._T_kf = PoseCorrection.fold_relative(self._T_kf, correction.update_for(self._kf.fid)[1])

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> dict | None:
        return None  # no proximity loops in this family (loop edges come from the classical service)

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

    def _add_to_source(self, fid: int, grey, depth, right) -> None:
        t0 = time.perf_counter()
        if fid not in self._in_source:
            self.source.add_frame(fid, grey, depth=depth, right=right)
            self._in_source.append(fid)
        self._times["source"] += time.perf_counter() - t0

    def _release_source(self) -> None:
        """Keep the source caches of the current frame and the newest keyframes only."""
        keep = set(list(self._kfs)[-self.config.keyframe.keep_source_frames:])
        if self._kf is not None:
            keep.add(self._kf.fid)
        if self._init_fid is not None:
            keep.add(self._init_fid)
        newest = self._fid - 1
        for fid in list(self._in_source):
            if fid not in keep and fid != newest and fid != self._prev_fid:
                self.source.remove_frame(fid)
                self._in_source.remove(fid)
        for fid, kf in self._kfs.items():
            if fid not in keep and kf.D is not None:
                kf.release()

    def _ensure_in_source(self, kf: PointmapKeyframe) -> None:
        self._add_to_source(kf.fid, kf.grey, kf.depth, kf.right)

    def _measure_frame(self, fid: int, frame) -> FrameStatus:
        grey = self.cam.image(frame.image)
        depth = self.cam.depth(frame.depth) if self.kind == "rgbd" else None
        right = self.cam.image(frame.image_right) if self.kind == "stereo" else None
        colour = self.cam.image(frame.rgb) if frame.rgb is not None else None
        self._add_to_source(fid, grey, depth, right)
        inputs = (grey, colour, depth, right)
        if self._kf is None:
            return self._initialize(fid, frame, inputs)
        return self._track_frame(fid, frame, inputs)

    # ------------------------------------------------------------------ initialisation
    def _new_keyframe(self, fid: int, frame, inputs, X: np.ndarray | torch.Tensor, C, T_WC: np.ndarray,
                      D: np.ndarray | None = None) -> PointmapKeyframe:
        grey, colour, depth, right = inputs
        H, W = self.cam.H, self.cam.W
        X = torch.as_tensor(np.asarray(X, np.float32) if not isinstance(X, torch.Tensor) else X).reshape(-1, 3)
        C = torch.as_tensor(np.asarray(C, np.float32) if not isinstance(C, torch.Tensor) else C).reshape(-1)
        ok = torch.isfinite(X).all(-1) & torch.isfinite(C) & (C > 0)
        X = torch.where(ok[:, None], X, torch.zeros((), dtype=torch.float32)).to(torch.float32).clone()
        C = torch.where(ok, C, torch.zeros((), dtype=torch.float32)).to(torch.float32).clone()
        kf = PointmapKeyframe(fid, float(frame.timestamp), int(frame.index), H, W, X, C, grey, colour, depth, right)
        if D is not None:
            kf.D = torch.as_tensor(np.asarray(D, np.float32) if not isinstance(D, torch.Tensor) else D).reshape(H * W, -1)
        self._kfs[fid] = kf
        self.backend.add_keyframe(fid, T_WC, float(frame.timestamp))
        if len(self._kfs) == 1:
            self.backend.set_gauge(anchor=fid, scale_pair=None)  # first pose fixed (7 dof); the scale is real
        self._records[fid] = KeyframePose()
        self._counts["keyframes"] += 1
        return kf

    def _initialize(self, fid: int, frame, inputs) -> FrameStatus:
        if self.kind in ("rgbd", "stereo"):
            pair = self.source.predict(fid, fid, np.eye(4))
            frac = float((pair.C_i > 0).mean())
            if frac < self.config.tracking.init_min_confident:
                logger.warning("pointmap frame %d: %.0f %% of the pixels have a point (< %.0f %%); not initialised",
                               frame.index, 100 * frac, 100 * self.config.tracking.init_min_confident)
                return self._status(fid, frame, "initializing", events=["init: too few points"])
            self._kf = self._new_keyframe(fid, frame, inputs, pair.X_i_in_i, pair.C_i, np.eye(4), pair.D_i)
            self._T_kf, self._uv_prev, self._since_kf = np.eye(4), None, 0
            self._after_keyframe(self._kf, None)
            return self._status(fid, frame, "tracked", True, int((pair.C_i > 0).sum()), ["initialised"])
        if self._init_fid is None:
            self._init_fid = fid
            self._init_frame = (frame, inputs)
            return self._status(fid, frame, "initializing")
        pair = self.source.predict(self._init_fid, fid)
        frac = float((pair.C_i >= self.config.tracking.min_confidence).mean())
        if pair.T_CiCj is None or frac < self.config.tracking.init_min_confident:
            if fid - self._init_fid >= self.config.tracking.init_max_frames:  # the first frame is stale: start over
                logger.info("pointmap: no two-view start from frame %d in %d frames; starting from frame %d",
                            self._init_frame[0].index, fid - self._init_fid, frame.index)
                self._init_fid, self._init_frame = fid, (frame, inputs)
            return self._status(fid, frame, "initializing", events=[f"init: {100 * frac:.0f} % confident"])
        f0, inputs0 = self._init_frame
        i0 = self._init_fid
        kf = self._new_keyframe(i0, f0, inputs0, pair.X_i_in_i, pair.C_i, np.eye(4), pair.D_i)
        self._kf = kf
        self._init_fid = None
        self._after_keyframe(kf, None)
        for other, _, _ in self._inputs:  # frames between the two: interpolated
            if i0 < other < fid:
                self._records[other] = InterpolatedPose(i0, fid, (other - i0) / (fid - i0))
                self._sources[other] = "tracked"
        self._T_kf, self._uv_prev, self._since_kf = pair.T_CiCj, None, 0
        status = self._track_frame(fid, frame, inputs, pair=pair)
        status.events.append("initialised")
        return status

    # ------------------------------------------------------------------ tracking
    def _pair_in(self, kf: PointmapKeyframe, fid: int, T_pred: np.ndarray, pair=None):
        """``(X_f^f (HW, 3), X_f^k (HW, 3), C_f (HW,), D_f, T0 (4x4))`` of frame ``fid`` against keyframe
        ``kf`` (module docstring, step 1); None when the two-view source found no pose."""
        t0 = time.perf_counter()
        self._ensure_in_source(kf)
        if self.kind in ("rgbd", "stereo"):
            if pair is None:
                T_pred = self._measured_prediction(kf, fid, T_pred)
                pair = self.source.predict(kf.fid, fid, rigid(T_pred))
            T0 = pair.T_CiCj
            a = 1.0
        else:
            pair = self.source.predict(kf.fid, fid) if pair is None else pair
            if pair.T_CiCj is None:
                self._times["source"] += time.perf_counter() - t0
                return None
            a = self._pair_scale(kf, pair)
            if a is None:
                self._times["source"] += time.perf_counter() - t0
                return None
            T0 = np.array(pair.T_CiCj, dtype=np.float64)
            T0[:3, :] *= a
        self._times["source"] += time.perf_counter() - t0
        n = self.cam.H * self.cam.W
        X_ff = torch.from_numpy(np.ascontiguousarray(pair.X_j_in_j, np.float32)).reshape(n, 3)
        X_fk = torch.from_numpy(np.ascontiguousarray(pair.X_j_in_i, np.float32)).reshape(n, 3) * a
        C_f = torch.from_numpy(np.ascontiguousarray(pair.C_j, np.float32)).reshape(n)
        D_f = torch.from_numpy(np.ascontiguousarray(pair.D_j, np.float32)).reshape(n, -1)
        return X_ff, X_fk, C_f, D_f, T0

    def _measured_prediction(self, kf: PointmapKeyframe, fid: int, T_pred: np.ndarray) -> np.ndarray:
        """Metric sources: ``T_CkCf`` with the last step measured by PnP on the dense flow from the previous
        frame (``T_CkCp T_CpCf``; from the keyframe itself right after a keyframe change), which stays
        reliable at video rate where the flow to an older keyframe fails; ``T_pred`` when that fails."""
        if not self.config.tracking.measure_pose:
            return T_pred
        prev = self._prev_fid
        if prev is None or prev not in self._in_source or prev == kf.fid or self._prev_kf != kf.fid:
            T = self.source.predict(kf.fid, fid, None).T_CiCj
            return T_pred if T is None else np.asarray(T, np.float64)
        T_step = self.source.predict(prev, fid, None).T_CiCj
        return T_pred if T_step is None else T_pred @ np.asarray(T_step, np.float64)

    def _pair_scale(self, kf: PointmapKeyframe, pair) -> float | None:
        """Scale taking the pair's pointmap of k to k's canonical one: median ratio of the norms over the
        pixels confident in both."""
        X_pair = torch.from_numpy(np.ascontiguousarray(pair.X_i_in_i, np.float32)).reshape(-1, 3)
        C_pair = torch.from_numpy(np.ascontiguousarray(pair.C_i, np.float32)).reshape(-1)
        ok = (C_pair >= self.config.tracking.min_confidence) & (kf.C > 0)
        if int(ok.sum()) < self.config.tracking.min_matches:
            logger.info("pointmap: pair (%d, %d) shares %d confident pixels with the canonical pointmap; no scale",
                        kf.fid, pair.j, int(ok.sum()))
            return None
        ratio = torch.linalg.vector_norm(kf.X[ok], dim=-1) / torch.linalg.vector_norm(X_pair[ok], dim=-1).clamp_min(1e-9)
        return float(ratio.median())

    def _track_against(self, kf: PointmapKeyframe, fid: int, T_pred: np.ndarray, warm: torch.Tensor | None,
                       pair=None):
        """Match and track frame ``fid`` against ``kf``; returns a dict with the result, or None (no pair)."""
        got = self._pair_in(kf, fid, T_pred, pair)
        if got is None:
            return None
        X_ff, X_fk, C_f, D_f, T0 = got
        q = self.query
        qvalid = (C_f[q] >= self.config.tracking.min_confidence) & torch.isfinite(X_fk[q]).all(-1)
        t0 = time.perf_counter()
        if self.config.tracking.warm_start == "projection":
            warm = None  # match_frame starts from the projection of the query points
        m = match_frame(kf, X_fk[q], qvalid, D_f[q], warm, self.cam.K, self.config.matching, self.config.source.descriptor)
        t1 = time.perf_counter()
        self._times["matching"] += t1 - t0
        n_points = max(int(qvalid.sum()), 1)
        n_valid = int(m.valid.sum())
        out = {"matches": m, "n_valid": n_valid, "fraction": n_valid / n_points, "X_ff": X_ff, "C_f": C_f,
               "D_f": D_f, "T": None, "inliers": 0}
        if n_valid < self.config.tracking.min_matches:
            return out
        sel = even_subset(m.valid.nonzero().squeeze(1), self.config.tracking.max_query_points)
        qi, p = q[sel], m.index[sel]
        X_f = X_ff[qi].to(torch.float64)
        X_k = kf.X[p].to(torch.float64)
        w = torch.sqrt(C_f[qi].clamp(max=1.0) * kf.C[p].clamp(max=1.0)).to(torch.float64)
        uv = m.uv[sel].to(torch.float64)
        tr = track_pose(_sim3(T0), X_f, X_k, w, self.config.block, self.config.tracking, self.fixed_scale, uv, self.K_t)
        self._times["tracking"] += time.perf_counter() - t1
        out.update(T=tr.T_CkCf, inliers=tr.num_inliers, sel=sel, qi=qi, p=p, X_f=X_f, X_k=X_k, w=w, uv=uv,
                   inlier=tr.inlier)
        return out

    def _ok(self, res, min_fraction: float) -> bool:
        return (res is not None and res["T"] is not None and res["inliers"] >= self.config.tracking.min_matches
                and res["fraction"] >= min_fraction)

    def _track_frame(self, fid: int, frame, inputs, pair=None) -> FrameStatus:
        kf = self._kf
        res = self._track_against(kf, fid, self._T_kf, self._uv_prev, pair)
        events = []
        if not self._ok(res, self.config.tracking.min_valid_fraction) and self._promote_last():
            events.append(f"keyframe {self._kf.fid} (look-back)")  # the last good frame became the keyframe
            kf = self._kf
            res = self._track_against(kf, fid, self._T_kf, None)
        if not self._ok(res, self.config.tracking.min_valid_fraction) and self.kind == "mono":
            status = self._track_pnp(fid, frame)  # no (usable) two-view pointmap: pose by PnP
            status.events[:0] = events
            return status
        if not self._ok(res, self.config.tracking.min_valid_fraction):
            found = self._relocalize(fid, frame)
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
        T = res["T"]
        self._T_kf = _matrix(T)
        t0 = time.perf_counter()
        inl = res["inlier"]
        if self.config.keyframe.fuse and self._pose_fusable(res):
            X_new = T.act(res["X_f"][inl]).to(torch.float32)
            fuse_pointmap(kf.X, kf.C, res["p"][inl], X_new, res["C_f"][res["qi"][inl]], self.config.keyframe.max_confidence)
            kf.changed()
        self._since_kf += 1
        self._times["bookkeeping"] += time.perf_counter() - t0
        new_kf = res["fraction"] < self.config.keyframe.new_fraction or (
            self.config.keyframe.max_gap > 0 and self._since_kf >= self.config.keyframe.max_gap)
        self._last_good = None
        if new_kf:
            self._make_keyframe(kf, fid, frame, inputs, res)
            events.append(f"keyframe {fid}")
        else:
            self._records[fid] = RelativePose(kf.fid, self._T_kf.copy())
            if source == "tracked":  # a keyframe candidate when the next frame no longer tracks against kf
                self._last_good = (fid, frame, inputs, res, self._T_kf.copy())
        return self._status(fid, frame, source, new_kf, res["inliers"], events)

    def _make_keyframe(self, kf: PointmapKeyframe, fid: int, frame, inputs, res) -> None:
        """Frame ``fid`` (tracked against ``kf`` with result ``res``, relative pose ``self._T_kf``) becomes the
        current keyframe, with an edge from ``kf`` made of the tracking's inlier matches."""
        T_WC = self._keyframe_T_WC(kf.fid) @ self._T_kf
        new = self._new_keyframe(fid, frame, inputs, res["X_ff"], res["C_f"], T_WC, res["D_f"])
        keep = even_subset(res["inlier"].nonzero().squeeze(1), self.config.graph.max_edge_matches)
        edge = PointmapEdge(self.backend_key(kf.fid), self.backend_key(fid), res["X_k"][keep], res["X_f"][keep],
                            res["w"][keep], res["uv"][keep])
        self._kf, self._T_kf, self._uv_prev, self._since_kf = new, np.eye(4), None, 0
        self._after_keyframe(new, (kf.fid, edge))

    def _promote_last(self) -> bool:
        """Look-back keyframe: when a frame no longer tracks against the keyframe (the source's flow or the
        two-view pair lost the overlap), the last frame that did becomes the keyframe (its records follow)
        and the frame is tracked against it. False when there is no such frame."""
        last, self._last_good = self._last_good, None
        if last is None or last[0] not in self._in_source:
            return False
        pfid, pframe, pinputs, pres, T_kp = last
        kf = self._kf
        self._T_kf = T_kp
        self._make_keyframe(kf, pfid, pframe, pinputs, pres)
        self._records[pfid] = KeyframePose()
        self._T_kf = np.linalg.inv(T_kp) @ T_kp  # the frame is predicted at the new keyframe's pose
        self._prev_fid, self._prev_kf = pfid, pfid
        return True

    def _pose_fusable(self, res) -> bool:
        return res["inliers"] >= self.config.tracking.min_matches

    def _track_pnp(self, fid: int, frame) -> FrameStatus:
        """Monocular frame without a two-view pointmap: PnP on the flow against the canonical pointmap."""
        kf = self._kf
        t0 = time.perf_counter()
        T = self.source.pnp_pose(kf.fid, fid, kf.X.view(kf.H, kf.W, 3).numpy(), kf.C.view(kf.H, kf.W).numpy())
        self._times["tracking"] += time.perf_counter() - t0
        if T is None:
            found = self._relocalize(fid, frame)
            if found is None:
                return self._fail(fid, frame, "tracking lost: no two-view pointmap and no PnP pose")
            kf, res = found
            self._kf, self._uv_prev, self._since_kf = kf, None, 0
            self._T_kf = _matrix(res["T"])
            self._records[fid] = RelativePose(kf.fid, self._T_kf.copy())
            return self._status(fid, frame, "relocalized", num_valid=res["inliers"])
        self._T_kf = np.asarray(T, np.float64)
        self._uv_prev = None
        self._records[fid] = RelativePose(kf.fid, self._T_kf.copy())
        self._counts["pnp_tracked"] += 1
        return self._status(fid, frame, "tracked", events=["pnp: little parallax"])

    def _fail(self, fid: int, frame, reason: str) -> FrameStatus:
        self._failures += 1
        self._counts["failed"] += 1
        logger.info("pointmap frame %d: %s", frame.index, reason)
        if self._kf is None:
            return self._status(fid, frame, "initializing", events=[reason])
        self._records[fid] = RelativePose(self._kf.fid, self._T_kf.copy())  # the last tracked relative pose
        self._uv_prev = None
        return self._status(fid, frame, "motion_model", events=[reason])

    # ------------------------------------------------------------------ relocalisation
    def _relocalize(self, fid: int, frame):
        """(keyframe, tracking result) of the first candidate that tracks with ``relocalization.min_valid_fraction``
        valid matches: the loop service's retrieval first, then the newest keyframes; None otherwise."""
        rc = self.config.relocalization
        T_WC_pred = self._keyframe_T_WC(self._kf.fid) @ self._T_kf
        candidates: list[tuple[int, np.ndarray]] = []
        found = self.loops.relocalize(self.cam.image(frame.image), self.cam.K)
        if found is not None and int(found[0]) in self._kfs:
            candidates.append((int(found[0]), np.asarray(found[1], np.float64)))
        for kid in reversed(list(self._kfs)[-rc.recent_keyframes:] if rc.recent_keyframes else []):
            if kid != self._kf.fid and all(kid != c for c, _ in candidates):
                candidates.append((kid, T_WC_pred))
        for kid, T_WC in candidates:
            kf = self._kfs[kid]
            T_pred = np.linalg.inv(self._keyframe_T_WC(kid)) @ T_WC
            try:
                res = self._track_against(kf, fid, T_pred, None)
            except (RuntimeError, DataError) as exc:
                logger.info("pointmap relocalisation against keyframe %d failed: %s", kid, exc)
                continue
            if self._ok(res, rc.min_valid_fraction):
                self._counts["relocalized"] += 1
                logger.info("pointmap frame %d relocalised on keyframe %d (%d inliers)", frame.index, kid, res["inliers"])
                return kf, res
        return None

    # ------------------------------------------------------------------ graph
    def _after_keyframe(self, kf: PointmapKeyframe, edge) -> None:
        if edge is not None:
            prev, e = edge
            self._edges.append(e)
            self._edge_pairs.add((prev, kf.fid))
            self._optimize()
        t0 = time.perf_counter()
        prev_ids = list(self._kfs)[-2:-1]
        self.loops.add_keyframe(kf.fid, prev_ids)
        if self.loops.enabled:
            self.loops.update_poses({k: self._keyframe_T_WC(k) for k in self._kfs})
        self._times["bookkeeping"] += time.perf_counter() - t0

    def _set_block(self) -> None:
        edges = [e for e in self._edges if self.backend.has_key(e.key_i) and self.backend.has_key(e.key_j)]
        self.backend.set_blocks(self.name, [PointmapBlock(edges, self.config.block, self.cam.K)] if edges else [])

    def _optimize(self) -> None:
        t0 = time.perf_counter()
        self._set_block()
        ids = list(self._kfs)
        window = self.config.graph.window
        free = ids if window == 0 else ids[-window:]
        try:
            report = self.backend.optimize_window(free, self.config.graph.iterations)
            logger.debug("pointmap optimisation over %d keyframes: %s", len(free), report)
        except (OptimizationError, RuntimeError, np.linalg.LinAlgError) as exc:
            logger.warning("pointmap optimisation failed (%s); poses kept", exc)
        self._times["optimization"] += time.perf_counter() - t0

    def _loop_edges(self) -> None:
        """A pointmap edge for each loop the loop service accepted since the last call."""
        if not self.loops.classical:
            return
        loops = self.loops.verified_loops()
        new = loops[self._loops_seen:]
        self._loops_seen = len(loops)
        added = False
        for rec in new:
            if rec.status != "accepted":
                continue
            a, b = int(rec.candidate_id), int(rec.query_id)
            if a not in self._kfs or b not in self._kfs or (a, b) in self._edge_pairs:
                continue
            T_ab = np.linalg.inv(self._keyframe_T_WC(a)) @ self._keyframe_T_WC(b)
            cfg = self.config
            meas = measure_edge(self._kfs[a], self._kfs[b], T_ab, self.cam.K, cfg.block, cfg.tracking, cfg.graph,
                                cfg.matching, cfg.source.descriptor, self.fixed_scale, cfg.query_stride)
            if meas is None:
                continue
            self._edges.append(meas.edge)
            self._edge_pairs.add((a, b))
            self._counts["loop_edges"] += 1
            logger.info("pointmap loop edge %d <-> %d: %d inliers", a, b, meas.num_inliers)
            added = True
        if added:
            self._optimize()
