"""Initialisation of the patch frontend's map (:class:`Initialiser`).

Monocular waits until the median rotation-compensated flow of tracked reference patches exceeds
``init_min_parallax`` and an essential matrix explains the tracks, then builds the graph from the
buffered frames (poses from the essential matrix, interpolated in between) and optimises with the
first keyframe fixed and the distance to the last one as world scale; it never initialises on a
static or purely rotating camera. Stereo and RGB-D initialise on the first frame with metric depth
(stereo: right-image edges through the calibrated ``T_CLCR``; RGB-D: depth prior, or with
``ba.depth_model: observation`` the sensor depth of every observation as a virtual right-camera pixel).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from ..base import FrameStatus
from ..records import InterpolatedPose, KeyframePose
from ..records import sim3_interp as _interp
from .patches import FALLBACK_INV_DEPTH
from .motion import MotionModel
from .state import PatchState
from .window import LocalBA

logger = logging.getLogger(__name__)

#: the shortest time span (s) an interpolation between two frames divides by
MIN_INTERPOLATION_SPAN_S = 1e-9
#: the RANSAC confidence of the essential matrix
ESSENTIAL_RANSAC_CONFIDENCE = 0.999


@dataclass
class _InitState:
    """Monocular initialisation: a reference frame and the frames buffered since."""

    ref_fid: int
    ref_frame: object
    ref_features: object
    ref_uv: np.ndarray
    buffer: list = field(default_factory=list)  # (fid, frame, features, tracked uv, valid)


class Initialiser:
    """The initialisation state machine on the shared :class:`~.state.PatchState` (module docstring);
    measures, optimises and keeps keyframes through the local BA ``window`` (its measurer and
    keyframes); sets ``state.initialized`` and ``state.map_start_fid`` when a map starts."""

    def __init__(self, state: PatchState, window: LocalBA, motion: MotionModel):
        self.state = state
        self.window = window
        self.measurer, self.keyframes = window.measurer, window.keyframes  # the window's own
        self.motion = motion
        self.pending: _InitState | None = None  # monocular: the reference and the buffered frames

    def buffered_fids(self) -> set[int] | None:
        """Frames held by a pending monocular initialisation (reference and buffer), or None."""
        if self.pending is None:
            return None
        return {self.pending.ref_fid} | {b[0] for b in self.pending.buffer}

    def initialize(self, fid: int, frame) -> FrameStatus:
        """Feed frame ``fid`` to the initialisation (the map starts on it, or it waits)."""
        if self.state.sensor_mode in ("stereo", "rgbd"):
            T_WC = np.eye(4) if self.motion.last_fid is None else self.motion.predict()
            return self._initialize_metric(fid, frame, T_WC)
        return self._initialize_mono(fid, frame)

    def abandon(self) -> None:
        """After a failed initialisation: the frames it put in the graph (or buffered) get no pose and
        leave; the next frame starts a new initialisation (keyframes of an earlier map stay final)."""
        st = self.state
        for f in st.graph.clear():
            self.keyframes.leave(f)
            st.records[f.fid] = None
        if self.pending is not None:
            for b in [(self.pending.ref_fid,)] + self.pending.buffer:
                st.records[b[0]] = None
        self.pending = None

    def _start_map(self, map_start_fid: int) -> None:
        st = self.state
        st.initialized = True
        st.map_start_fid = map_start_fid
        st.lost = 0

    def _initialize_metric(self, fid: int, frame, T_WC: np.ndarray) -> FrameStatus:
        st = self.state
        g = st.graph
        feats, feats_right = self.measurer.prepare(frame)
        t0 = time.perf_counter()
        gf = self.measurer.new_graph_frame(fid, frame, T_WC, feats, feats_right)
        self.keyframes.enter(gf)
        st.records[fid] = KeyframePose()
        st.times["bookkeeping"] += time.perf_counter() - t0
        if st.sensor_mode == "stereo":
            idx = g.connect_all(stereo=True)
            self.measurer.measure(idx)
            ok = g.confidence[idx] > 0
            self.window.refine_depths_fixed(idx[ok], st.config.ba.stereo_init_steps)
            valid = int(ok.sum())
            g._select(g.confidence > 0)
        else:
            valid = int(np.isfinite(gf.sensor_inv_depth).sum())
        if valid < st.config.tracking.min_valid_edges:
            for f in g.clear():
                self.keyframes.leave(f)
            st.records[fid] = None
            return st.status(fid, frame, "initializing", events=[f"waiting for depth ({valid} valid patches)"])
        self._start_map(fid)
        self.motion.update(fid)
        return st.status(fid, frame, "tracked", is_keyframe=True, num_valid=valid, events=["initialised"])

    def _initialize_mono(self, fid: int, frame) -> FrameStatus:
        st = self.state
        tcfg = st.config.tracking
        feats, _ = self.measurer.prepare(frame)
        pending = self.pending
        if pending is None:
            self.pending = _InitState(fid, frame, feats, self.measurer.select(frame.image))
            return st.status(fid, frame, "initializing", events=["initialisation reference"])
        last_uv = pending.buffer[-1][3] if pending.buffer else pending.ref_uv
        last_valid = pending.buffer[-1][4] if pending.buffer else np.ones(len(pending.ref_uv), bool)
        t0 = time.perf_counter()
        m = st.source.measure(pending.ref_features, feats, pending.ref_uv, last_uv)
        st.times["flow"] += time.perf_counter() - t0
        valid = last_valid & (m.confidence > 0)
        pending.buffer.append((fid, frame, feats, m.uv, valid))
        if int(valid.sum()) < tcfg.init_min_tracks:
            # lost the reference: the buffered frames never get a pose; restart from this frame
            for b in pending.buffer[:-1]:
                st.records[b[0]] = None
            self.pending = _InitState(fid, frame, feats, self.measurer.select(frame.image))
            return st.status(fid, frame, "initializing", events=["initialisation reference reset (tracks lost)"])
        if len(pending.buffer) >= tcfg.init_max_frames:
            # subsample: drop the second-newest frame every other time, interpolated later
            drop = len(pending.buffer) - 2 if len(pending.buffer) % 2 else 0
            dropped = pending.buffer.pop(drop)
            prev = pending.ref_fid if drop == 0 else pending.buffer[drop - 1][0]
            nxt = pending.buffer[drop][0]
            alpha = (dropped[1].timestamp - st.stamp(prev)) / max(st.stamp(nxt) - st.stamp(prev), MIN_INTERPOLATION_SPAN_S)
            st.records[dropped[0]] = InterpolatedPose(prev, nxt, float(alpha))
        if len(pending.buffer) + 1 < tcfg.init_min_frames:
            return st.status(fid, frame, "initializing", events=["collecting initialisation frames"])
        ok, T_C0Cn, depths, parallax = self._two_view(pending.ref_uv[valid], m.uv[valid])
        if not ok:
            return st.status(fid, frame, "initializing", events=[f"waiting for parallax ({parallax:.1f} px)"])
        return self._build_initial_map(fid, frame, valid, T_C0Cn, depths)

    def _two_view(self, uv0: np.ndarray, uv1: np.ndarray):
        """Essential-matrix test: (ok, T_C0C1 (4, 4) with |t| = 1, inverse depths of uv0 (NaN: none), parallax px)."""
        import cv2  # deferred: cv2

        tcfg = self.state.config.tracking
        K = self.state.K.numpy()
        flow = np.linalg.norm(uv1 - uv0, axis=1)
        if np.median(flow) < tcfg.init_min_parallax:
            return False, None, None, float(np.median(flow))
        Kmat = np.array([[K[0], 0, K[2]], [0, K[1], K[3]], [0, 0, 1]], dtype=np.float64)
        E, mask = cv2.findEssentialMat(uv0, uv1, Kmat, cv2.RANSAC, ESSENTIAL_RANSAC_CONFIDENCE, tcfg.init_ransac_threshold)
        if E is None or E.shape != (3, 3):
            return False, None, None, 0.0
        _, R_C1C0, t_C1C0, mask = cv2.recoverPose(E, uv0, uv1, Kmat, mask=mask)
        inl = mask.reshape(-1) > 0
        if inl.mean() < tcfg.init_min_inlier_ratio:
            return False, None, None, 0.0
        rays0 = np.stack([(uv0[:, 0] - K[2]) / K[0], (uv0[:, 1] - K[3]) / K[1], np.ones(len(uv0))], 1)
        rot = rays0 @ R_C1C0.T
        uv_rot = np.stack([K[0] * rot[:, 0] / rot[:, 2] + K[2], K[1] * rot[:, 1] / rot[:, 2] + K[3]], 1)
        parallax = float(np.median(np.linalg.norm(uv1[inl] - uv_rot[inl], axis=1)))
        if parallax < tcfg.init_min_parallax:
            return False, None, None, parallax
        P0 = Kmat @ np.hstack([np.eye(3), np.zeros((3, 1))])
        P1 = Kmat @ np.hstack([R_C1C0, t_C1C0.reshape(3, 1)])
        Xh = cv2.triangulatePoints(P0, P1, uv0.T.astype(np.float64), uv1.T.astype(np.float64))
        z0 = Xh[2] / Xh[3]
        z1 = (R_C1C0 @ (Xh[:3] / Xh[3]) + t_C1C0.reshape(3, 1))[2]
        good = inl & (z0 > 0) & (z1 > 0) & np.isfinite(z0)
        inv_depth = np.where(good, 1.0 / np.where(good, z0, 1.0), np.nan)
        T_C1C0 = np.eye(4)
        T_C1C0[:3, :3] = R_C1C0
        T_C1C0[:3, 3] = t_C1C0.reshape(3) / np.linalg.norm(t_C1C0)
        inv_depth = inv_depth * np.linalg.norm(t_C1C0)
        return True, np.linalg.inv(T_C1C0), inv_depth, parallax

    def _build_initial_map(self, fid: int, frame, valid: np.ndarray, T_C0Cn: np.ndarray, depths: np.ndarray) -> FrameStatus:
        st = self.state
        g = st.graph
        pending = self.pending
        T_WC0 = np.eye(4) if self.motion.last_fid is None else st.pose_of(self.motion.last_fid)
        t_ref, t_last = st.stamp(pending.ref_fid), st.stamp(fid)
        members = [(pending.ref_fid, pending.ref_frame, pending.ref_features)] + [(b[0], b[1], b[2]) for b in pending.buffer]
        T_WCn = T_WC0 @ T_C0Cn
        for mfid, mframe, mfeats in members:
            alpha = (float(mframe.timestamp) - t_ref) / max(t_last - t_ref, MIN_INTERPOLATION_SPAN_S)
            T_WC = _interp(T_WC0, T_WCn, alpha) if mfid != pending.ref_fid else T_WC0
            gf = self.measurer.new_graph_frame(mfid, mframe, T_WC, mfeats, None)
            if mfid == pending.ref_fid:
                gf.uv = pending.ref_uv.copy()
                d = np.full(len(gf.uv), np.nan)
                d[np.nonzero(valid)[0]] = depths
                med = float(np.nanmedian(d)) if np.isfinite(d).any() else FALLBACK_INV_DEPTH
                gf.inv_depth = np.where(np.isfinite(d), d, med)
            else:
                ref_d = g.frames[0].inv_depth
                gf.inv_depth[:] = float(np.median(ref_d))
            self.keyframes.enter(gf)
            st.records[mfid] = KeyframePose()
        idx = g.connect_all(stereo=False)
        ba = st.config.ba
        self.window.rounds(idx, ba.init_rounds, ba.init_iterations, init=True, new_fid=None)
        n_valid = int(((g.confidence > 0) & (g.robust > 0)).sum())
        if n_valid < st.config.tracking.min_valid_edges * len(members):
            logger.info("initialisation at frame %d rejected (%d valid edges); waiting", frame.index, n_valid)
            for f in g.clear():
                self.keyframes.leave(f)
                st.records[f.fid] = None
            self.pending = None
            return st.status(fid, frame, "initializing", events=["initialisation rejected"])
        self._start_map(g.frames[0].fid)
        self.pending = None
        self.motion.last_fid = None
        for mfid, _, _ in members:
            self.motion.update(mfid)
        logger.info("initialised at frame %d with %d frames, %d edges", frame.index, len(members), g.num_edges)
        return st.status(fid, frame, "tracked", is_keyframe=True, num_valid=n_valid, events=["initialised"])
