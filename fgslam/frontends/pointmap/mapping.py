"""The pointmap frontend's keyframes: the map's start (the first keyframe; monocular: a two-view pair with
enough confident pixels), new keyframes with their edge to the previous one (step 5 of :mod:`.frontend`),
the look-back keyframe, and the fusion of a tracked frame into its keyframe's canonical pointmap (step 4)."""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from ...backend.keys import pose_key
from ...factors.pointmap_block import PointmapEdge
from ..base import FrameStatus
from ..records import InterpolatedPose, KeyframePose
from .cache import SourceCache
from .edges import PointmapGraph
from .keyframes import PointmapKeyframe, even_subset
from .source import PointmapPair
from .state import PointmapState
from .tracking import fuse_pointmap

logger = logging.getLogger(__name__)


def _tensor(a) -> torch.Tensor:
    """``a`` as a tensor (a numpy array converted to float32 first)."""
    return torch.as_tensor(np.asarray(a, np.float32) if not isinstance(a, torch.Tensor) else a)


class PointmapKeyframing:
    """Creates the keyframes of the shared state (its keyframes, backend, pose records, motion state and
    counts), hands each to the keyframe ``graph`` and fuses tracked frames into them; ``cache``: the
    frames the source holds (the look-back keyframe needs its frame there)."""

    def __init__(self, state: PointmapState, cache: SourceCache, graph: PointmapGraph):
        self.state = state
        self.cache = cache
        self.graph = graph

    def new_keyframe(self, fid: int, frame, inputs, X: np.ndarray | torch.Tensor, C, T_WC: np.ndarray,
                     D: np.ndarray | None = None, surface=None) -> PointmapKeyframe:
        """Frame ``fid`` becomes a keyframe at ``T_WC`` with the canonical pointmap ``X`` / confidences ``C``
        (non-finite or unconfident points zeroed), descriptors ``D`` and depth surface ``surface`` (RGB-D
        depth alignment); the first one anchors the gauge."""
        st = self.state
        grey, colour, depth, right = inputs
        H, W = st.cam.H, st.cam.W
        X = _tensor(X).reshape(-1, 3)
        C = _tensor(C).reshape(-1)
        ok = torch.isfinite(X).all(-1) & torch.isfinite(C) & (C > 0)
        X = torch.where(ok[:, None], X, torch.zeros((), dtype=torch.float32)).to(torch.float32).clone()
        C = torch.where(ok, C, torch.zeros((), dtype=torch.float32)).to(torch.float32).clone()
        kf = PointmapKeyframe(fid, float(frame.timestamp), int(frame.index), H, W, X, C, grey, colour, depth, right)
        if D is not None:
            kf.D = _tensor(D).reshape(H * W, -1)
        kf.surface = surface
        st.kfs[fid] = kf
        st.backend.add_keyframe(fid, T_WC, float(frame.timestamp))
        if len(st.kfs) == 1:
            st.backend.set_gauge(anchor=fid, scale_pair=None)  # first pose fixed (7 dof); the scale is real
        st.records[fid] = KeyframePose()
        st.counts["keyframes"] += 1
        return kf

    def initialize(self, fid: int, frame, inputs) -> FrameStatus | PointmapPair:
        """The map's first keyframe: metric sources at the first frame with enough points (its status);
        monocular at the first frame of the first pair with ``tracking.init_min_confident`` confident
        pixels (the frames between the two interpolated): that pair, with which the frontend tracks frame
        ``fid`` against the new keyframe; the status of a frame that does not start the map."""
        st = self.state
        cfg = st.config.tracking
        if st.kind in ("rgbd", "stereo"):
            pair = st.source.predict(fid, fid, np.eye(4))
            frac = float((pair.C_i > 0).mean())
            if frac < cfg.init_min_confident:
                logger.warning("pointmap frame %d: %.0f %% of the pixels have a point (< %.0f %%); not initialised",
                               frame.index, 100 * frac, 100 * cfg.init_min_confident)
                return st.status(fid, frame, "initializing", events=["init: too few points"])
            st.kf = self.new_keyframe(fid, frame, inputs, pair.X_i_in_i, pair.C_i, np.eye(4), pair.D_i,
                                      st.frame_surface)
            st.T_CkCf, st.uv_prev, st.since_kf = np.eye(4), None, 0
            self.graph.after_keyframe(st.kf, None)
            return st.status(fid, frame, "tracked", True, int((pair.C_i > 0).sum()), ["initialised"])
        if st.init_fid is None:
            st.init_fid = fid
            st.init_frame = (frame, inputs)
            return st.status(fid, frame, "initializing")
        pair = st.source.predict(st.init_fid, fid)
        frac = float((pair.C_i >= cfg.min_confidence).mean())
        if pair.T_CiCj is None or frac < cfg.init_min_confident:
            if fid - st.init_fid >= cfg.init_max_frames:  # the first frame is stale: start over
                logger.info("pointmap: no two-view start from frame %d in %d frames; starting from frame %d",
                            st.init_frame[0].index, fid - st.init_fid, frame.index)
                st.init_fid, st.init_frame = fid, (frame, inputs)
            return st.status(fid, frame, "initializing", events=[f"init: {100 * frac:.0f} % confident"])
        f0, inputs0 = st.init_frame
        i0 = st.init_fid
        kf = self.new_keyframe(i0, f0, inputs0, pair.X_i_in_i, pair.C_i, np.eye(4), pair.D_i)
        st.kf = kf
        st.init_fid = None
        self.graph.after_keyframe(kf, None)
        for other, _, _ in st.inputs:  # frames between the two: interpolated
            if i0 < other < fid:
                st.records[other] = InterpolatedPose(i0, fid, (other - i0) / (fid - i0))
                st.sources[other] = "tracked"
        st.T_CkCf, st.uv_prev, st.since_kf = pair.T_CiCj, None, 0
        return pair

    def make_keyframe(self, kf: PointmapKeyframe, fid: int, frame, inputs, res) -> None:
        """Frame ``fid`` (tracked against ``kf`` with result ``res``, relative pose ``T_CkCf``) becomes the
        current keyframe, with an edge from ``kf`` made of the tracking's inlier matches."""
        st = self.state
        T_WC = st.keyframe_T_WC(kf.fid) @ st.T_CkCf
        new = self.new_keyframe(fid, frame, inputs, res["X_ff"], res["C_f"], T_WC, res["D_f"], res.get("surface"))
        if res.get("inlier") is None:  # tracked by depth alone: the depth block is the edge (RGB-D)
            edge = None
        else:
            keep = even_subset(res["inlier"].nonzero().squeeze(1), st.config.graph.max_edge_matches)
            edge = PointmapEdge(pose_key(kf.fid), pose_key(fid), res["X_k"][keep], res["X_f"][keep],
                                res["w"][keep], res["uv"][keep])
        st.kf, st.T_CkCf, st.uv_prev, st.since_kf = new, np.eye(4), None, 0
        self.graph.after_keyframe(new, (kf.fid, edge))

    def promote_last(self) -> bool:
        """Look-back keyframe: when a frame no longer tracks against the keyframe (the source's flow or the
        two-view pair lost the overlap), the last frame that did becomes the keyframe (its records follow)
        and the frame is tracked against it. False when there is no such frame."""
        st = self.state
        last, st.last_good = st.last_good, None
        if last is None or last[0] not in self.cache:
            return False
        pfid, pframe, pinputs, pres, T_CkCp = last
        kf = st.kf
        st.T_CkCf = T_CkCp
        self.make_keyframe(kf, pfid, pframe, pinputs, pres)
        st.records[pfid] = KeyframePose()
        st.T_CkCf = np.linalg.inv(T_CkCp) @ T_CkCp  # the frame is predicted at the new keyframe's pose
        st.prev_fid, st.prev_kf = pfid, pfid
        return True

    def fuse(self, kf: PointmapKeyframe, T_CkCf, res) -> None:
        """Eq. 9: the tracking's inlier points of the frame, moved into ``kf`` by ``T_CkCf`` (a Sim3), fused
        into its canonical pointmap (when ``keyframe.fuse`` and the pose has enough inliers); ``bookkeeping`` time."""
        st = self.state
        t0 = time.perf_counter()
        inl = res["inlier"]
        if st.config.keyframe.fuse and res["inliers"] >= st.config.tracking.min_matches:
            X_new = T_CkCf.act(res["X_f"][inl]).to(torch.float32)
            fuse_pointmap(kf.X, kf.C, res["p"][inl], X_new, res["C_f"][res["qi"][inl]], st.config.keyframe.max_confidence)
            kf.changed()
        st.times["bookkeeping"] += time.perf_counter() - t0
