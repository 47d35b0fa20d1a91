"""The pointmap frontend's contributor contract (:mod:`fgslam.contracts.contributor`), which the frontend
delegates to: keyframe images and poses for the loop service, and its corrections applied."""

from __future__ import annotations

from typing import TYPE_CHECKING, Optional

import numpy as np

from ...contracts.contributor import KeyframeImage, PoseCorrection

if TYPE_CHECKING:
    from .frontend import PointmapFrontend


class PointmapLoopContributor:
    """Keyframe images and poses of ``frontend`` for the loop service, and its corrections applied."""

    def __init__(self, frontend: "PointmapFrontend"):
        self.fe = frontend
        self.name = frontend.name

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> Optional[dict]:
        return None  # no proximity loops in this family (loop edges come from the classical service)

    def keyframe_image(self, kf_id: int) -> KeyframeImage | None:
        fe = self.fe
        kf = fe._kfs.get(int(kf_id))
        if kf is None:
            return None
        return KeyframeImage(kf.grey, fe.cam.K.copy(), kf.timestamp, kf.depth)

    def keyframe_pose(self, kf_id: int) -> np.ndarray | None:
        fe = self.fe
        return fe._keyframe_T_WC(int(kf_id)) if int(kf_id) in fe._kfs else None

    def apply_correction(self, correction: PoseCorrection) -> None:
        """Every keyframe moved by its update (a folded scale multiplies its canonical pointmap and its
        edges' points); non-keyframe records re-expressed, the current relative pose rescaled."""
        fe = self.fe
        for fid, kf in fe._kfs.items():
            T_WC_new, s = correction.apply_pose(fid, fe._keyframe_T_WC(fid))
            fe.backend.set_pose(fid, T_WC_new)
            if s != 1.0:
                kf.X *= s
                kf.changed()
                fe.graph.scale_keyframe(fe.backend_key(fid), s)
        for fid, rec in list(fe._records.items()):
            if rec is not None:
                fe._records[fid] = rec.corrected(fid, correction)
        if correction.fold_scale and fe._kf is not None:
            fe._T_CkCf = PoseCorrection.fold_relative(fe._T_CkCf, correction.update_for(fe._kf.fid)[1])
