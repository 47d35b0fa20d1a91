"""Tracking of the patch frontend (:class:`Tracker`): one frame after initialisation.

1. predict the pose (:class:`~.motion.MotionModel`); motion filter (DROID-SLAM's): the newest
   keyframe's patches are measured in the frame first (these edges are reused in step 3); a median
   flow below ``motion_filter_flow`` means a stationary camera: the frame stays out of the graph, takes
   that keyframe's pose (placed later by its share of the next keyframe's flow), the velocity is reset;
2. add the frame to the patch graph with new patches and connect it (forward, backward, stereo edges);
3. measure / optimise rounds of the local BA (:class:`~.window.LocalBA`);
4. too few valid measurements into the frame, or less than ``min_inlier_ratio`` of them BA inliers,
   or motion the motion model contradicts: tracking failure - the frame leaves the graph, the
   window's poses and depths are restored, and the frontend gives it the predicted pose
   (:class:`TrackingFailure`);
5. keyframe removal and retirement (:class:`~.keyframes.Keyframes`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from ...factors.depth_align import RIGID_DIM
from ...factors.reprojection import reproject_inv_depth
from ...core.lie import sim3_matrix_components

from ..base import FrameStatus
from ..records import InterpolatedPose, KeyframePose, RelativePose
from ..records import rigid as _rigid
from .graph import GraphFrame
from .motion import MotionModel
from .state import PatchState
from .window import LocalBA


@dataclass
class TrackingFailure:
    """Why a frame could not be tracked, its predicted pose (``T_WC_pred``, 4x4) and how many of its
    image measurements were valid (``num_valid``: too few, or an implausible motion's)."""

    reason: str
    T_WC_pred: np.ndarray
    num_valid: int = 0


def image_information(state: PatchState, fid: int, T_WC: np.ndarray) -> np.ndarray:
    """6x6 information (rotation, translation) of graph frame ``fid``'s pose at ``T_WC`` from its measured
    left-image edges (other frames' patches observed in it, at their current depths and poses), each
    weighted by its confidence over ``ba.pixel_sigma`` squared; zeros without any."""
    g = state.graph
    e = np.nonzero((g.tgt == fid) & ~g.right & (g.confidence > 0))[0]
    if e.size == 0:
        return np.zeros((RIGID_DIM, RIGID_DIM))
    pos = g.positions(g.src[e])
    uv = torch.as_tensor(np.stack([g.frames[p].uv[k] for p, k in zip(pos, g.patch[e])]))
    d = torch.as_tensor(np.array([g.frames[p].inv_depth[k] for p, k in zip(pos, g.patch[e])]))
    Ri, ti, si = sim3_matrix_components(g.poses(g.src[e]))
    Rj, tj, sj = sim3_matrix_components(T_WC[None])
    res = reproject_inv_depth(uv, d, (Ri, ti, si), (Rj[0], tj[0], sj[0]), state.K, uv, config=state.reproj)
    J = res.J_Tj[..., :RIGID_DIM] * torch.as_tensor(np.sqrt(g.confidence[e]))[:, None, None] / state.config.ba.pixel_sigma
    J = J.reshape(-1, RIGID_DIM)
    return (J.T @ J).numpy()


class _DepthCheck:
    """Depth alignment of a new frame ``fid`` (surface ``surface``, key ``key_f``) to the newest graph
    frame ``last`` (key ``key_k``): the prediction aligned by depth (``depth_align.prealign``), and,
    asked only when the frame's image measurements fall short, whether the depth with those few
    measurements constrains all of the frame's rigid motion. When first asked, the frame (already in
    the graph) is aligned by depth from its current pose, coarse to fine, so that the window's solve
    starts from the depth's answer; the answer is kept."""

    def __init__(self, state: PatchState, key_k: int, key_f: int, fid: int, last: GraphFrame, surface):
        self.state = state
        self.fid = fid
        self.last = last
        self.block = state.depth.block(key_k, key_f, last.surface, surface)
        self.ok: bool | None = None

    def prealign(self, T_WC_pred: np.ndarray) -> np.ndarray:
        """The predicted pose, aligned by depth when ``depth_align.prealign`` is on."""
        depth = self.state.depth
        if depth.config.prealign:
            T_WC_pred, _ = depth.align(self.block, self.last.T_WC, T_WC_pred)
        return T_WC_pred

    def __call__(self) -> bool:
        if self.ok is None:
            t0 = time.perf_counter()
            st = self.state
            frame = st.graph.frame(self.fid)
            T_WC, constraint = st.depth.hold(self.block, self.last.T_WC, frame.T_WC,
                                             lambda T: image_information(st, self.fid, T))
            frame.T_WC = _rigid(T_WC)
            self.ok = constraint.ok
            st.times["depth"] += time.perf_counter() - t0
        return self.ok


class Tracker:
    """Per-frame tracking on the shared :class:`~.state.PatchState` (module docstring): measures,
    optimises and keeps keyframes through the local BA ``window`` (its measurer and keyframes);
    ``motion`` predicts."""

    def __init__(self, state: PatchState, window: LocalBA, motion: MotionModel):
        self.state = state
        self.window = window
        self.measurer, self.keyframes = window.measurer, window.keyframes  # the window's own
        self.motion = motion
        self.still: list[tuple[int, int, float]] = []  # stationary frames since the newest keyframe: (fid, keyframe fid, flow px)

    def track(self, fid: int, frame) -> FrameStatus | TrackingFailure:
        """Track frame ``fid``: its status, or a :class:`TrackingFailure` (the frame left the graph)."""
        st = self.state
        cfg = st.config
        motion = self.motion
        T_WC_pred = motion.predict(frame.timestamp)
        feats, _ = self.measurer.prepare(frame, right=False)
        last = st.graph.frames[-1]
        surface, depth_holds = None, None
        if st.depth.enabled:  # RGB-D: the frame's surface; with prealign its prediction aligned by depth first
            t0 = time.perf_counter()
            surface = st.depth.surface(frame.depth)
            if surface is not None and last.surface is not None:
                depth_holds = _DepthCheck(st, self.window.key(last.fid), self.window.key(fid), fid, last, surface)
                T_WC_pred = depth_holds.prealign(T_WC_pred)
            st.times["depth"] += time.perf_counter() - t0
        flow, kf_uv, kf_conf, kf_uv_pred = self._keyframe_flow(last, feats, T_WC_pred)
        if flow < cfg.tracking.motion_filter_flow:
            return self._stationary(fid, frame, last.fid, flow, int((kf_conf > 0).sum()))
        _, feats_right = self.measurer.prepare(frame, left=False)  # stereo: the right image only for a moving frame
        t0 = time.perf_counter()
        gf = self.measurer.new_graph_frame(fid, frame, T_WC_pred, feats, feats_right, surface)
        self.keyframes.enter(gf)
        st.records[fid] = KeyframePose()
        g = st.graph
        idx = g.connect_new_frame(st.sensor_mode == "stereo", cfg.ba.stereo_cross_edges)
        done = idx[(g.src[idx] == last.fid) & (g.tgt[idx] == fid) & ~g.right[idx]]  # measured by the motion filter
        g.uv[done] = kf_uv[g.patch[done]]
        g.confidence[done] = kf_conf[g.patch[done]]
        if cfg.ba.measured_huber:
            self.measurer.huber_from(done, kf_uv_pred[g.patch[done]])
        saved = [(f.T_WC.copy(), f.inv_depth.copy()) for f in g.frames[:-1]], g.robust[: g.num_edges - len(idx)].copy()
        # the motion the implausible-motion check expects (undamped: the camera's last motion, or the one a
        # rejected frame contradicted), relative to the newest keyframe before the BA moves it
        T_WC_ref = motion.predict(frame.timestamp, motion.reference, damping=1.0)
        T_CkCref = np.linalg.inv(last.T_WC) @ T_WC_ref
        st.times["bookkeeping"] += time.perf_counter() - t0
        valid = self.window.rounds(idx, cfg.ba.rounds, cfg.ba.iterations, init=False, new_fid=fid, premeasured=done,
                                   held_by_depth=depth_holds)
        by_depth = valid < cfg.tracking.min_valid_edges and depth_holds is not None and depth_holds()  # the image lost it, the depth holds it
        implausible = None if valid < cfg.tracking.min_valid_edges else self._implausible(fid, last, T_CkCref)
        if (valid < cfg.tracking.min_valid_edges and not by_depth) or implausible is not None:
            self._drop_new_frame(fid, saved)
            if implausible is not None and motion.reference is None:
                motion.reference = motion.velocity.copy()
            reason = f"tracking lost: {valid} valid measurements" if implausible is None else implausible
            return TrackingFailure(reason, T_WC_pred, valid)
        st.lost = 0
        motion.reference = None
        t0 = time.perf_counter()
        events = [f"tracked by depth alone ({valid} valid image measurements)"] if by_depth else []
        self._place_still(fid, flow)
        removed = self.keyframes.remove_redundant()
        if removed is not None:
            events.append(f"keyframe {removed} removed")
        self.keyframes.retire()
        motion.update(fid)
        st.times["bookkeeping"] += time.perf_counter() - t0
        return st.status(fid, frame, "tracked", is_keyframe=True, num_valid=valid, events=events)

    def _implausible(self, fid: int, kf: GraphFrame, T_CkCref: np.ndarray) -> str | None:
        """Why the motion of the BA'd new frame ``fid`` is implausible, or None: too few of its
        measurements are BA inliers, or its tracked motion contradicts the expected motion
        ``T_CkCref`` (relative to the newest keyframe ``kf`` as it was before the BA; the motion
        model's prediction, or with the motion reference held after a rejected frame, the prediction
        with that motion; :meth:`_motion_contradiction`). The caller drops such a frame: it never
        becomes a keyframe, moves the window or sets the velocity, and takes the motion model's pose."""
        tcfg = self.state.config.tracking
        ratio = self._inlier_ratio(fid)
        if ratio < tcfg.min_inlier_ratio:
            return f"implausible motion: {ratio:.0%} of the measurements are inliers after BA"
        T_CkCnew = np.linalg.inv(kf.T_WC) @ self.state.graph.frame(fid).T_WC
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
        (uv_pred, uv_new), (ok_pred, ok_new) = self.state.reproject_to(kf, kf.T_WC @ np.stack([T_CkCpred, T_CkCnew]))
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
        g = self.state.graph
        new = ((g.tgt == fid) | (g.src == fid)) & ~g.right & (g.confidence > 0)
        n = int(new.sum())
        return float((g.robust[new] > 0).sum()) / n if n else 1.0

    def _drop_new_frame(self, fid: int, saved) -> None:
        """A rejected new frame leaves the graph, and the window gets back the poses, depths and
        robust weights it had before that frame's BA."""
        g = self.state.graph
        self.keyframes.leave(g.remove_frame(fid))
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
        st = self.state
        t0 = time.perf_counter()
        K = len(last.uv)
        uv = np.full((K, 2), np.nan)
        conf = np.zeros(K)
        uv_pred, ok = st.reproject_to(last, T_WC)
        ok &= st.inside(uv_pred)
        if ok.any() and last.features is not None:
            m = st.source.measure(last.features, feats, last.uv[ok], uv_pred[ok])
            uv[ok] = m.uv
            conf[ok] = m.confidence
        st.times["flow"] += time.perf_counter() - t0
        good = conf > 0
        if good.sum() < st.config.tracking.min_valid_edges:
            return float("inf"), uv, conf, uv_pred
        return float(np.median(np.linalg.norm(uv[good] - last.uv[good], axis=1))), uv, conf, uv_pred

    def _stationary(self, fid: int, frame, kf_fid: int, flow: float, n_valid: int) -> FrameStatus:
        """A frame whose image barely moved from the newest keyframe's: it does not enter the graph
        (no keyframe, no BA; depths and scale stay untouched) and takes the keyframe's pose until the
        next keyframe places it by its flow (:meth:`_place_still`); the motion model restarts from rest."""
        st = self.state
        st.records[fid] = RelativePose(kf_fid, np.eye(4))
        self.still.append((fid, kf_fid, flow))
        self.motion.rest(fid)
        st.lost = 0
        return st.status(fid, frame, "tracked", num_valid=n_valid, events=["stationary"])

    def clear_stationary(self) -> None:
        """Forget the stationary frames since the newest keyframe (they keep that keyframe's pose)."""
        self.still = []

    def _place_still(self, fid: int, flow: float) -> None:
        """Stationary frames since the previous keyframe get a pose between it and the new keyframe
        ``fid``, interpolated by their flow relative to the new keyframe's (``flow`` px)."""
        for still_fid, kf_fid, still_flow in self.still:
            alpha = min(still_flow / flow, 1.0) if np.isfinite(flow) and flow > 0 else 0.0
            self.state.records[still_fid] = InterpolatedPose(kf_fid, fid, float(alpha))
        self.still = []
