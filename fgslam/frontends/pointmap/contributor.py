"""The pointmap frontend's contributor contract (:mod:`fgslam.contracts.contributor`), which the frontend
delegates to: keyframe images and poses for the loop service, and its corrections applied."""

from __future__ import annotations

import numpy as np

from ...backend.keys import pose_key
from ...contracts.contributor import KeyframeImage, PoseCorrection
from .edges import PointmapGraph
from .state import PointmapState


class PointmapLoopContributor:
    """Keyframe images and poses of the shared state for the loop service, and its corrections applied
    (to the keyframes, the pose records and the edges of ``graph``); ``name``: the family's."""

    def __init__(self, state: PointmapState, graph: PointmapGraph, name: str):
        self.state = state
        self.graph = graph
        self.name = name

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> dict | None:
        return None  # no proximity loops in this family (loop edges come from the classical service)

    def keyframe_image(self, kf_id: int) -> KeyframeImage | None:
        st = self.state
        kf = st.kfs.get(int(kf_id))
        if kf is None:
            return None
        return KeyframeImage(kf.grey, st.cam.K.copy(), kf.timestamp, kf.depth)

    def keyframe_pose(self, kf_id: int) -> np.ndarray | None:
        st = self.state
        return st.keyframe_T_WC(int(kf_id)) if int(kf_id) in st.kfs else None

    def apply_correction(self, correction: PoseCorrection) -> None:
        """Every keyframe moved by its update (a folded scale multiplies its canonical pointmap and its
        edges' points); non-keyframe records re-expressed, the current relative pose rescaled."""
        st = self.state
        for fid, kf in st.kfs.items():
            T_WC_new, s = correction.apply_pose(fid, st.keyframe_T_WC(fid))
            st.backend.set_pose(fid, T_WC_new)
            if s != 1.0:
                kf.X *= s
                kf.changed()
                self.graph.scale_keyframe(pose_key(fid), s)
        for fid, rec in list(st.records.items()):
            if rec is not None:
                st.records[fid] = rec.corrected(fid, correction)
        if correction.fold_scale and st.kf is not None:
            st.T_CkCf = PoseCorrection.fold_relative(st.T_CkCf, correction.update_for(st.kf.fid)[1])
