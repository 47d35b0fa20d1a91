"""The dense frontend's side of loop closure: the hand-over of settled keyframes to the loop port, and
the contributor contract (:mod:`fgslam.services.contributor`) the frontend delegates to."""

from __future__ import annotations

from typing import TYPE_CHECKING, Optional

import numpy as np

from ...services.contributor import KeyframeImage, PoseCorrection

if TYPE_CHECKING:
    from .frontend import DenseFrontend


class DenseLoopContributor:
    """Keyframes, images and poses of ``frontend`` for the loop service, and its corrections applied."""

    def __init__(self, frontend: "DenseFrontend"):
        self.fe = frontend
        self.name = frontend.name

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> Optional[dict]:
        return None  # classical loops only (no proximity edges of this family yet)

    def feed(self, all_keyframes: bool = False) -> None:
        """Hand the keyframes that left the active graph (``all_keyframes``: every keyframe) to the
        classical closer with their neighbours, and every keyframe's pose."""
        fe = self.fe
        if not fe.loops.classical or fe.graph is None:
            return
        g = fe.graph
        active = set(g.active)
        order = g.order()
        for p, fid in enumerate(order):
            if all_keyframes or fid not in active:
                fe.loops.add_keyframe(fid, [order[q] for q in (p - 1, p + 1) if 0 <= q < len(order)])
        fe.loops.update_poses({f: fe._keyframe_T_WC(f) for f in order})

    def keyframe_image(self, kf_id: int) -> Optional[KeyframeImage]:
        fe = self.fe
        kf = fe.graph.keyframes.get(kf_id) if fe.graph is not None else None
        if kf is None or kf.image is None:
            return None
        return KeyframeImage(kf.image, fe.K.copy(), kf.timestamp, kf.depth_image)

    def keyframe_pose(self, kf_id: int) -> Optional[np.ndarray]:
        backend = self.fe.backend
        return backend.pose_matrix(kf_id) if backend.has_keyframe(kf_id) else None

    def apply_correction(self, correction: PoseCorrection) -> None:
        """Keyframe poses ``T_WC <- U_k T_WC`` (the folded scale into their inverse depths), pose records
        re-expressed."""
        fe = self.fe
        for kf in fe._all_keyframes():
            if not fe.backend.has_keyframe(kf.fid):
                continue
            T_WC, s = correction.apply_pose(kf.fid, fe.backend.pose_matrix(kf.fid))
            fe.backend.set_pose(kf.fid, T_WC)
            if s != 1.0:
                kf.inv_depth = kf.inv_depth / s
        for fid, rec in list(fe._records.items()):
            if rec is not None:
                fe._records[fid] = rec.corrected(fid, correction)
