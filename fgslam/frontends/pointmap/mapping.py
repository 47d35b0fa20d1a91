"""The pointmap frontend's keyframes: the map's start (the first keyframe; monocular: a two-view pair with
enough confident pixels), new keyframes with their edge to the previous one (step 5 of :mod:`.frontend`),
the look-back keyframe, and the fusion of a tracked frame into its keyframe's canonical pointmap (step 4)."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np
import torch

from ...factors.pointmap_block import PointmapEdge
from ..base import FrameStatus
from ..records import InterpolatedPose, KeyframePose
from .keyframes import PointmapKeyframe, even_subset
from .tracking import fuse_pointmap

if TYPE_CHECKING:
    from .frontend import PointmapFrontend

logger = logging.getLogger(__name__)


def _tensor(a) -> torch.Tensor:
    """``a`` as a tensor (a numpy array converted to float32 first)."""
    return torch.as_tensor(np.asarray(a, np.float32) if not isinstance(a, torch.Tensor) else a)


class PointmapKeyframing:
    """Creates the keyframes of ``frontend`` (its keyframes, backend, pose records, motion state, graph
    and counts) and fuses tracked frames into them."""

    def __init__(self, frontend: "PointmapFrontend"):
        self.fe = frontend

    def new_keyframe(self, fid: int, frame, inputs, X: np.ndarray | torch.Tensor, C, T_WC: np.ndarray,
                     D: np.ndarray | None = None, surface=None) -> PointmapKeyframe:
        """Frame ``fid`` becomes a keyframe at ``T_WC`` with the canonical pointmap ``X`` / confidences ``C``
        (non-finite or unconfident points zeroed), descriptors ``D`` and depth surface ``surface`` (RGB-D
        depth alignment); the first one anchors the gauge."""
        fe = self.fe
        grey, colour, depth, right = inputs
        H, W = fe.cam.H, fe.cam.W
        X = _tensor(X).reshape(-1, 3)
        C = _tensor(C).reshape(-1)
        ok = torch.isfinite(X).all(-1) & torch.isfinite(C) & (C > 0)
        X = torch.where(ok[:, None], X, torch.zeros((), dtype=torch.float32)).to(torch.float32).clone()
        C = torch.where(ok, C, torch.zeros((), dtype=torch.float32)).to(torch.float32).clone()
        kf = PointmapKeyframe(fid, float(frame.timestamp), int(frame.index), H, W, X, C, grey, colour, depth, right)
        if D is not None:
            kf.D = _tensor(D).reshape(H * W, -1)
        kf.surface = surface
        fe._kfs[fid] = kf
        fe.backend.add_keyframe(fid, T_WC, float(frame.timestamp))
        if len(fe._kfs) == 1:
            fe.backend.set_gauge(anchor=fid, scale_pair=None)  # first pose fixed (7 dof); the scale is real
        fe._records[fid] = KeyframePose()
        fe._counts["keyframes"] += 1
        return kf

    def initialize(self, fid: int, frame, inputs) -> FrameStatus:
        """The map's first keyframe: metric sources at the first frame with enough points; monocular at the
        first frame of the first pair with ``tracking.init_min_confident`` confident pixels (the frames
        between the two interpolated), then the frame tracked against it."""
        fe = self.fe
        cfg = fe.config.tracking
        if fe.kind in ("rgbd", "stereo"):
            pair = fe.source.predict(fid, fid, np.eye(4))
            frac = float((pair.C_i > 0).mean())
            if frac < cfg.init_min_confident:
                logger.warning("pointmap frame %d: %.0f %% of the pixels have a point (< %.0f %%); not initialised",
                               frame.index, 100 * frac, 100 * cfg.init_min_confident)
                return fe._status(fid, frame, "initializing", events=["init: too few points"])
            fe._kf = self.new_keyframe(fid, frame, inputs, pair.X_i_in_i, pair.C_i, np.eye(4), pair.D_i,
                                       fe._frame_surface)
            fe._T_CkCf, fe._uv_prev, fe._since_kf = np.eye(4), None, 0
            fe.graph.after_keyframe(fe._kf, None)
            return fe._status(fid, frame, "tracked", True, int((pair.C_i > 0).sum()), ["initialised"])
        if fe._init_fid is None:
            fe._init_fid = fid
            fe._init_frame = (frame, inputs)
            return fe._status(fid, frame, "initializing")
        pair = fe.source.predict(fe._init_fid, fid)
        frac = float((pair.C_i >= cfg.min_confidence).mean())
        if pair.T_CiCj is None or frac < cfg.init_min_confident:
            if fid - fe._init_fid >= cfg.init_max_frames:  # the first frame is stale: start over
                logger.info("pointmap: no two-view start from frame %d in %d frames; starting from frame %d",
                            fe._init_frame[0].index, fid - fe._init_fid, frame.index)
                fe._init_fid, fe._init_frame = fid, (frame, inputs)
            return fe._status(fid, frame, "initializing", events=[f"init: {100 * frac:.0f} % confident"])
        f0, inputs0 = fe._init_frame
        i0 = fe._init_fid
        kf = self.new_keyframe(i0, f0, inputs0, pair.X_i_in_i, pair.C_i, np.eye(4), pair.D_i)
        fe._kf = kf
        fe._init_fid = None
        fe.graph.after_keyframe(kf, None)
        for other, _, _ in fe._inputs:  # frames between the two: interpolated
            if i0 < other < fid:
                fe._records[other] = InterpolatedPose(i0, fid, (other - i0) / (fid - i0))
                fe._sources[other] = "tracked"
        fe._T_CkCf, fe._uv_prev, fe._since_kf = pair.T_CiCj, None, 0
        status = fe._track_frame(fid, frame, inputs, pair=pair)
        if fe.features is not None:  # the corners of the map's keyframe, tracked from here on
            fe.tracker.start_features(fid, inputs[0])
        status.events.append("initialised")
        return status

    def make_keyframe(self, kf: PointmapKeyframe, fid: int, frame, inputs, res) -> None:
        """Frame ``fid`` (tracked against ``kf`` with result ``res``, relative pose ``_T_CkCf``) becomes the
        current keyframe, with an edge from ``kf`` made of the tracking's inlier matches."""
        fe = self.fe
        T_WC = fe._keyframe_T_WC(kf.fid) @ fe._T_CkCf
        new = self.new_keyframe(fid, frame, inputs, res["X_ff"], res["C_f"], T_WC, res["D_f"], res.get("surface"))
        if res.get("inlier") is None:  # tracked by depth alone: the depth block is the edge (RGB-D)
            edge = None
        else:
            keep = even_subset(res["inlier"].nonzero().squeeze(1), fe.config.graph.max_edge_matches)
            edge = PointmapEdge(fe.backend_key(kf.fid), fe.backend_key(fid), res["X_k"][keep], res["X_f"][keep],
                                res["w"][keep], res["uv"][keep])
        fe._kf, fe._T_CkCf, fe._uv_prev, fe._since_kf = new, np.eye(4), None, 0
        fe.graph.after_keyframe(new, (kf.fid, edge))

    def promote_last(self) -> bool:
        """Look-back keyframe: when a frame no longer tracks against the keyframe (the source's flow or the
        two-view pair lost the overlap), the last frame that did becomes the keyframe (its records follow)
        and the frame is tracked against it. False when there is no such frame."""
        fe = self.fe
        last, fe._last_good = fe._last_good, None
        if last is None or last[0] not in fe.source_cache:
            return False
        pfid, pframe, pinputs, pres, T_CkCp = last
        kf = fe._kf
        fe._T_CkCf = T_CkCp
        self.make_keyframe(kf, pfid, pframe, pinputs, pres)
        fe._records[pfid] = KeyframePose()
        fe._T_CkCf = np.linalg.inv(T_CkCp) @ T_CkCp  # the frame is predicted at the new keyframe's pose
        fe._prev_fid, fe._prev_kf = pfid, pfid
        return True

    def fuse(self, kf: PointmapKeyframe, T_CkCf, res) -> None:
        """Eq. 9: the tracking's inlier points of the frame, moved into ``kf`` by ``T_CkCf`` (a Sim3), fused
        into its canonical pointmap (when ``keyframe.fuse`` and the pose has enough inliers); ``bookkeeping`` time."""
        fe = self.fe
        t0 = time.perf_counter()
        inl = res["inlier"]
        if fe.config.keyframe.fuse and res["inliers"] >= fe.config.tracking.min_matches:
            X_new = T_CkCf.act(res["X_f"][inl]).to(torch.float32)
            fuse_pointmap(kf.X, kf.C, res["p"][inl], X_new, res["C_f"][res["qi"][inl]], fe.config.keyframe.max_confidence)
            kf.changed()
        fe._times["bookkeeping"] += time.perf_counter() - t0
