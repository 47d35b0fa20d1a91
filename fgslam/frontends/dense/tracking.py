"""The dense frontend's frame-to-keyframe tracking: the motion-only pose of a frame against a keyframe's
held inverse-depth map (step 1 of :mod:`.frontend`), and the re-tracking of the frames tracked before
the monocular initialisation."""

from __future__ import annotations

import logging
import time

import cv2
import numpy as np
import torch

from ...backend.keys import pose_key
from ...core.errors import OptimizationError
from ...factors.dense import DenseEdge, DenseKeyframe, DenseSourceBlock
from ...factors.reprojection import reproject
from ...factors.schur import POSE_DIM
from ...core.lie import gtsam_matrix, gtsam_sim3, sim3_matrix_components, sim3_matrix_parts
from ..depth_tracking import pose_information
from ..records import RelativePose
from .graph import DenseKeyframeState
from .state import DenseState
from .weights import block_config, huber_weight, information

logger = logging.getLogger(__name__)

#: numerical trouble of one frame's measurement or optimisation: the frame fails, never the run
NUMERICAL_ERRORS = (OptimizationError, RuntimeError, np.linalg.LinAlgError, cv2.error)

#: information added to every inverse depth in the motion-only optimisation (holds the keyframe's map)
_HOLD_DEPTH = 1e12
#: information on the frame's log-scale in the motion-only optimisation (unobservable there)
_HOLD_SCALE = 1e8
_HOLD_SCALE_ONLY = np.array([0.0] * (POSE_DIM - 1) + [_HOLD_SCALE])


class DenseTracker:
    """Motion-only tracking of frames against the keyframes of the shared ``state`` (its graph, source,
    backend, pose records and stage times)."""

    def __init__(self, state: DenseState):
        self.state = state
        self.last_solve = None  # (image block, keyframe key, frame key, T_WCk) of the last motion-only solve

    def track(self, kf_fid: int, fid: int, T_WC_pred: np.ndarray, surface=None) -> tuple[np.ndarray, float, int, bool]:
        """Motion-only pose of frame ``fid`` against keyframe ``kf_fid``: (T_WC, mean measured flow in
        image px over confident pixels, confident grid pixels, success). ``surface``: the frame's depth
        surface (RGB-D depth alignment): a depth block against the keyframe's joins the solve. The
        last solve's image block and values stay in ``last_solve`` (the image information of a frame
        whose confident pixels fall short, :meth:`image_information`)."""
        import gtsam  # deferred: gtsam

        st = self.state
        cfg = st.config.tracking
        g = st.graph
        kf = g.keyframes[kf_fid]
        T_WCk = st.keyframe_T_WC(kf_fid)
        # the frame starts at the keyframe's scale (its scale is unobservable here)
        R, t, _ = sim3_matrix_parts(T_WC_pred, project=True)
        s_kf = float(sim3_matrix_parts(T_WCk)[2])
        T_WC = np.eye(4)
        T_WC[:3, :3] = s_kf * R
        T_WC[:3, 3] = t
        key_kf, key_f = pose_key(kf_fid), pose_key(fid)
        depth_block = None
        if surface is not None and kf.surface is not None:
            depth_block = st.depth.block(key_kf, key_f, kf.surface, surface)
        self.last_solve = None
        flow, n_conf, rev = np.inf, 0, None
        for _ in range(cfg.rounds):
            t0 = time.perf_counter()
            induced = self.induced_to(kf, T_WCk, T_WC)
            (rev,) = st.source.revise([(kf_fid, fid)], induced[None])
            st.times["flow"] += time.perf_counter() - t0
            weight = rev.weight * huber_weight(rev.target - induced, st.config, st.stride)
            conf = rev.weight.mean(-1) > cfg.confident_weight
            n_conf = int(conf.sum())
            if n_conf == 0:
                return T_WC, np.inf, 0, False
            block = DenseSourceBlock(
                DenseKeyframe(key_kf, kf.inv_depth, damping=np.full(g.shape, _HOLD_DEPTH)),
                [DenseEdge(key_kf, key_f, rev.target, weight * information(st.config, st.stride))], st.K_grid,
                block_config(st.config, st.reproj))
            values = gtsam.Values()
            values.insert(key_kf, gtsam_sim3(T_WCk))
            values.insert(key_f, gtsam_sim3(T_WC))
            blocks = [block] if depth_block is None else [block, depth_block]
            result = st.backend.optimize_pose(blocks, values, key_f, cfg.iterations, hold=_HOLD_SCALE_ONLY,
                                              step_tolerance=cfg.step_tolerance)
            T_WC = gtsam_matrix(result.values.atSimilarity3(key_f))
            self.last_solve = (block, key_kf, key_f, T_WCk)
        flow = float(np.linalg.norm(rev.target - g.grid, axis=-1)[conf].mean() * st.stride)
        return T_WC, flow, n_conf, bool(np.isfinite(T_WC).all())

    def image_information(self, T_WC: np.ndarray) -> np.ndarray | None:
        """6x6 information (rotation, translation) of the last solve's image block on the frame at
        ``T_WC`` (None when the last tracking built no block: no confident pixel)."""
        import gtsam  # deferred: gtsam

        if self.last_solve is None:
            return None
        block, key_kf, key_f, T_WCk = self.last_solve
        values = gtsam.Values()
        values.insert(key_kf, gtsam_sim3(T_WCk))
        values.insert(key_f, gtsam_sim3(T_WC))
        return pose_information([block], values, key_f)

    def by_depth(self, kf_fid: int, fid: int, T_WC_pred: np.ndarray, surface, with_image: bool) -> tuple[np.ndarray, float] | None:
        """A frame whose image measurements fall short, tracked by depth (RGB-D depth alignment): its
        prediction aligned to keyframe ``kf_fid`` by depth (with the last solve's image information when
        ``with_image``); ``(T_WC, mean flow in image px the keyframe's map induces)`` when that constrains
        all six rigid directions, else None."""
        st = self.state
        kf = st.graph.keyframes[kf_fid]
        if not st.depth.enabled or surface is None or kf.surface is None:
            return None
        t0 = time.perf_counter()
        T_WCk = st.keyframe_T_WC(kf_fid)
        R, t, _ = sim3_matrix_parts(T_WC_pred, project=True)
        T_WC = np.eye(4)
        T_WC[:3, :3] = float(sim3_matrix_parts(T_WCk)[2]) * R  # at the keyframe's scale, as in track()
        T_WC[:3, 3] = t
        block = st.depth.block(pose_key(kf_fid), pose_key(fid), kf.surface, surface)
        T_WC, constraint = st.depth.hold(block, T_WCk, T_WC, self.image_information if with_image else None)
        ok = constraint.ok
        flow = np.inf
        if ok:
            induced = self.induced_to(kf, T_WCk, T_WC)
            d = np.linalg.norm(induced - st.graph.grid, axis=-1)
            flow = float(np.nanmean(d) * st.stride) if np.isfinite(d).any() else np.inf
        st.times["depth"] += time.perf_counter() - t0
        return (T_WC, flow) if ok and np.isfinite(flow) else None

    def induced_to(self, kf: DenseKeyframeState, T_WCk: np.ndarray, T_WC: np.ndarray) -> np.ndarray:
        """Field (h, w, 2) keyframe ``kf`` (at ``T_WCk``) induces in a camera at ``T_WC`` (NaN: invalid)."""
        Ra, ta, sa = sim3_matrix_components(T_WCk[None])
        Rb, tb, sb = sim3_matrix_components(T_WC[None])
        g = self.state.graph
        uv, ok = reproject(torch.as_tensor(g.grid.reshape(-1, 2)), torch.as_tensor(kf.inv_depth.reshape(-1)),
                           (Ra[0], ta[0], sa[0]), (Rb[0], tb[0], sb[0]), g.K, config=self.state.reproj)
        out = uv.numpy().reshape(*g.shape, 2).copy()
        out[~ok.numpy().reshape(g.shape)] = np.nan
        return out

    def retrack(self, frames: dict[int, tuple[int, np.ndarray]]) -> None:
        """Motion-only poses of non-keyframes ``fid -> (keyframe, image)`` against their keyframe's
        current map (a removed keyframe's: the keyframe it was folded into), from their current pose
        (their records become relative to that keyframe). A frame whose re-tracking fails numerically
        keeps its pose (logged)."""
        st = self.state
        t0 = time.perf_counter()
        flow0 = st.times["flow"]
        for fid, (kf_fid, image) in frames.items():
            T_WC0 = st.pose_of(fid)
            while kf_fid not in st.graph.keyframes and isinstance(st.records.get(kf_fid), RelativePose):
                kf_fid = st.records[kf_fid].ref  # removed by remove_redundant: relative to its neighbour
            if T_WC0 is None or kf_fid not in st.graph.keyframes:
                continue
            st.source.add_frame(fid, image)
            try:
                T_WC, _, n_conf, ok = self.track(kf_fid, fid, T_WC0)
            except NUMERICAL_ERRORS as exc:
                logger.info("frame %d: re-tracking failed (%s); it keeps its pose", fid, exc)
                continue
            finally:
                st.source.remove_frame(fid)
            if ok and n_conf > 0:
                st.records[fid] = RelativePose(kf_fid, np.linalg.inv(st.keyframe_T_WC(kf_fid)) @ T_WC)
        st.times["tracking"] += time.perf_counter() - t0 - (st.times["flow"] - flow0)
