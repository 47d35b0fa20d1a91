"""The pointmap frontend's tracking of a frame against a keyframe (steps 1-3 of :mod:`.frontend`): the
pair of pointmaps from the source, projective matching, the relative pose ``T_CkCf`` by
:func:`.tracking.track_pose`, and (RGB-D depth alignment) the depth's hold on a frame the matches lose;
plus :class:`TrackingLost`, what the per-frame steps (:mod:`.pair_tracking`, :mod:`.feature_tracking`)
return for a frame nothing poses."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ...factors.pointmap_block import PointmapBlock, PointmapEdge
from ...core.lie import Sim3
from ..depth_tracking import pose_information
from ..records import rigid
from .cache import SourceCache
from .keyframes import PointmapKeyframe, even_subset, match_frame
from .state import PointmapState
from .tracking import TRACK_KEYS, track_pose

logger = logging.getLogger(__name__)


def sim3_of(M: np.ndarray) -> Sim3:
    """The :class:`~fgslam.core.lie.Sim3` of a 4x4 matrix."""
    return Sim3.from_matrix(torch.as_tensor(np.asarray(M, np.float64)))


def matrix_of(T: Sim3) -> np.ndarray:
    """The 4x4 float64 matrix of a :class:`~fgslam.core.lie.Sim3`."""
    return T.matrix().numpy().astype(np.float64)


@dataclass
class TrackingLost:
    """A frame nothing posed (no match, no PnP pose, not relocalised): why, and the events of the frame
    before the loss (reported first); the frontend gives it the motion model's pose."""

    reason: str
    events: list[str] = field(default_factory=list)


class PointmapTracker:
    """Tracks frames against the keyframes of the shared state (its source, working camera, query grid,
    motion state and stage times), loading them through ``cache``."""

    def __init__(self, state: PointmapState, cache: SourceCache):
        self.state = state
        self.cache = cache
        self.held = None  # the current frame tracked by depth alone: (T_CkCf, share of its depth paired); RGB-D

    def pair_in(self, kf: PointmapKeyframe, fid: int, T_CkCf_pred: np.ndarray, pair=None, surface=None):
        """``(X_f^f (HW, 3), X_f^k (HW, 3), C_f (HW,), D_f, T_CkCf0 (4x4))`` of frame ``fid`` against keyframe
        ``kf`` (module docstring of :mod:`.frontend`, step 1); None when the two-view source found no pose.
        ``surface``: the frame's depth surface (RGB-D depth alignment): a prediction the image could not
        measure (no PnP pose on the flow; always with ``depth_align.prealign``) is aligned by depth first."""
        st = self.state
        t0 = time.perf_counter()
        self.cache.ensure(kf)
        if st.kind in ("rgbd", "stereo"):
            if pair is None:
                T_CkCf_pred, measured = self._measured_prediction(kf, fid, T_CkCf_pred)
                if not measured or st.depth.config.prealign:
                    T_CkCf_pred, held = self._depth_prediction(kf, T_CkCf_pred, surface)
                    self.held = held if not measured else None
                pair = st.source.predict(kf.fid, fid, rigid(T_CkCf_pred))
            T_CkCf0 = pair.T_CiCj
            a = 1.0
        else:
            pair = st.source.predict(kf.fid, fid) if pair is None else pair
            if pair.T_CiCj is None:
                st.times["source"] += time.perf_counter() - t0
                return None
            a = self._pair_scale(kf, pair)
            if a is None:
                st.times["source"] += time.perf_counter() - t0
                return None
            T_CkCf0 = np.array(pair.T_CiCj, dtype=np.float64)
            T_CkCf0[:3, :] *= a
        st.times["source"] += time.perf_counter() - t0
        n = st.cam.H * st.cam.W
        X_ff = torch.from_numpy(np.ascontiguousarray(pair.X_j_in_j, np.float32)).reshape(n, 3)
        X_fk = torch.from_numpy(np.ascontiguousarray(pair.X_j_in_i, np.float32)).reshape(n, 3) * a
        C_f = torch.from_numpy(np.ascontiguousarray(pair.C_j, np.float32)).reshape(n)
        D_f = torch.from_numpy(np.ascontiguousarray(pair.D_j, np.float32)).reshape(n, -1)
        return X_ff, X_fk, C_f, D_f, T_CkCf0

    def _measured_prediction(self, kf: PointmapKeyframe, fid: int, T_CkCf_pred: np.ndarray) -> tuple[np.ndarray, bool]:
        """Metric sources: ``T_CkCf`` with the last step measured by PnP on the dense flow from the previous
        frame (``T_CkCp T_CpCf``; from the keyframe itself right after a keyframe change), which stays
        reliable at video rate where the flow to an older keyframe fails; ``T_CkCf_pred`` when that fails.
        Second: whether the image measured it (``tracking.measure_pose`` off: counted as measured). Where
        the image measures nothing, the motion prior's (IMU) pose of the frame when there is one."""
        st = self.state
        # the motion prior's (IMU) pose of the frame, where the image measures none (else the last pose)
        T_CkCf_imu = st.prior_T_CkCf(kf.fid)
        fallback = T_CkCf_pred if T_CkCf_imu is None else T_CkCf_imu
        if not st.config.tracking.measure_pose:
            return fallback, True
        prev = st.prev_fid
        if prev is None or prev not in self.cache or prev == kf.fid or st.prev_kf != kf.fid:
            T_CkCf = st.source.predict(kf.fid, fid, None).T_CiCj
            return (fallback, False) if T_CkCf is None else (np.asarray(T_CkCf, np.float64), True)
        T_CpCf = st.source.predict(prev, fid, None).T_CiCj
        return (fallback, False) if T_CpCf is None else (T_CkCf_pred @ np.asarray(T_CpCf, np.float64), True)

    def _depth_prediction(self, kf: PointmapKeyframe, T_CkCf_pred: np.ndarray, surface):
        """RGB-D depth alignment: the prediction ``T_CkCf_pred`` aligned to ``kf`` by depth when the depth
        constrains all six rigid directions there, else unchanged; second ``(T_CkCf, share of the frame's
        depth points paired)`` when it does, else None."""
        st = self.state
        block = self.depth_block(kf, surface)
        if block is None:
            return T_CkCf_pred, None
        t0 = time.perf_counter()
        T, constraint = st.depth.hold(block, np.eye(4), rigid(T_CkCf_pred))
        st.times["depth"] += time.perf_counter() - t0
        if not constraint.ok:
            return T_CkCf_pred, None
        return rigid(T), (rigid(T), constraint.pairs / max(block.num_points, 1))

    def _pair_scale(self, kf: PointmapKeyframe, pair) -> float | None:
        """Scale taking the pair's pointmap of k to k's canonical one: median ratio of the norms over the
        pixels confident in both."""
        cfg = self.state.config.tracking
        X_pair = torch.from_numpy(np.ascontiguousarray(pair.X_i_in_i, np.float32)).reshape(-1, 3)
        C_pair = torch.from_numpy(np.ascontiguousarray(pair.C_i, np.float32)).reshape(-1)
        ok = (C_pair >= cfg.min_confidence) & (kf.C > 0)
        if int(ok.sum()) < cfg.min_matches:
            logger.info("pointmap: pair (%d, %d) shares %d confident pixels with the canonical pointmap; no scale",
                        kf.fid, pair.j, int(ok.sum()))
            return None
        ratio = torch.linalg.vector_norm(kf.X[ok], dim=-1) / torch.linalg.vector_norm(X_pair[ok], dim=-1).clamp_min(1e-9)
        return float(ratio.median())

    def depth_block(self, kf: PointmapKeyframe, surface):
        """The depth block of a frame with depth ``surface`` against ``kf`` over the tracking problem's keys
        (RGB-D depth alignment; None without it or without both surfaces)."""
        depth = self.state.depth
        if not depth.enabled or surface is None or kf.surface is None:
            return None
        return depth.block(*TRACK_KEYS, kf.surface, surface)

    def track_against(self, kf: PointmapKeyframe, fid: int, T_CkCf_pred: np.ndarray, warm: torch.Tensor | None,
                      pair=None, surface=None, fixed_scale: bool | None = None):
        """Match and track frame ``fid`` against ``kf``; returns a dict with the result, or None (no pair).
        ``surface``: the frame's depth surface (RGB-D depth alignment): a depth block against the
        keyframe's joins the pose solve; kept in the result (``surface``). ``fixed_scale``: SE(3) tracking
        (None: the state's)."""
        st = self.state
        cfg = st.config
        self.held = None
        got = self.pair_in(kf, fid, T_CkCf_pred, pair, surface)
        if got is None:
            return None
        X_ff, X_fk, C_f, D_f, T_CkCf0 = got
        if self.held is not None:  # no confident flow (the image measured nothing) but the depth holds the frame
            return {"n_valid": 0, "fraction": 0.0, "X_ff": X_ff, "C_f": C_f, "D_f": D_f, "T": None, "inliers": 0,
                    "surface": surface, "held": self.held}
        q = st.query
        qvalid = (C_f[q] >= cfg.tracking.min_confidence) & torch.isfinite(X_fk[q]).all(-1)
        t0 = time.perf_counter()
        if cfg.tracking.warm_start == "projection":
            warm = None  # match_frame starts from the projection of the query points
        m = match_frame(kf, X_fk[q], qvalid, D_f[q], warm, st.cam.K, cfg.matching, cfg.source.descriptor)
        t1 = time.perf_counter()
        st.times["matching"] += t1 - t0
        n_points = max(int(qvalid.sum()), 1)
        n_valid = int(m.valid.sum())
        out = {"matches": m, "n_valid": n_valid, "fraction": n_valid / n_points, "X_ff": X_ff, "C_f": C_f,
               "D_f": D_f, "T": None, "inliers": 0, "surface": surface}
        if n_valid < cfg.tracking.min_matches:
            return out
        sel = even_subset(m.valid.nonzero().squeeze(1), cfg.tracking.max_query_points)
        qi, p = q[sel], m.index[sel]
        X_f = X_ff[qi].to(torch.float64)
        X_k = kf.X[p].to(torch.float64)
        w = torch.sqrt(C_f[qi].clamp(max=1.0) * kf.C[p].clamp(max=1.0)).to(torch.float64)
        uv = m.uv[sel].to(torch.float64)
        depth = self.depth_block(kf, surface)
        fixed = st.fixed_scale if fixed_scale is None else fixed_scale
        tr = track_pose(sim3_of(T_CkCf0), X_f, X_k, w, cfg.block, cfg.tracking, fixed, uv, st.K_t,
                        () if depth is None else (depth,))
        st.times["tracking"] += time.perf_counter() - t1
        out.update(T=tr.T_CkCf, inliers=tr.num_inliers, sel=sel, qi=qi, p=p, X_f=X_f, X_k=X_k, w=w, uv=uv,
                   inlier=tr.inlier)
        return out

    def by_depth(self, kf: PointmapKeyframe, res, surface):
        """A frame whose matches fall short, tracked by depth (RGB-D depth alignment): the predicted
        ``T_CkCf`` aligned to ``kf`` by depth, with the information of the frame's matches when the
        tracking got as far as a pose; ``(T_CkCf 4x4, share of the frame's depth points paired)`` when
        that constrains all six rigid directions, else None."""
        st = self.state
        block = self.depth_block(kf, surface)
        if block is None or res is None:
            return None
        t0 = time.perf_counter()
        H_image = None
        if res.get("sel") is not None:
            edge = PointmapEdge(*TRACK_KEYS, res["X_k"], res["X_f"], res["w"],
                                res["uv"] if st.config.block.mode == "calibrated" else None)
            image = PointmapBlock([edge], st.config.block, st.cam.K)

            def image_information(T):
                import gtsam  # deferred: gtsam

                values = gtsam.Values()
                values.insert(TRACK_KEYS[0], gtsam.Similarity3())
                values.insert(TRACK_KEYS[1], sim3_of(T).to_gtsam())
                return pose_information([image], values, TRACK_KEYS[1])

            H_image = image_information
        T, constraint = st.depth.hold(block, np.eye(4), rigid(st.T_CkCf), H_image)
        st.times["depth"] += time.perf_counter() - t0
        if not constraint.ok:
            return None
        return rigid(T), constraint.pairs / max(block.num_points, 1)

    def ok(self, res, min_fraction: float) -> bool:
        """Whether the tracking result ``res`` has a pose, enough inliers and ``min_fraction`` valid matches."""
        return (res is not None and res["T"] is not None and res["inliers"] >= self.state.config.tracking.min_matches
                and res["fraction"] >= min_fraction)
