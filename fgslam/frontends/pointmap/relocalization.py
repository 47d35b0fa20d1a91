"""The pointmap frontend's relocalisation (MASt3R-SLAM section 3.6, step 7 of :mod:`.frontend`): a lost
frame tracked against the loop service's retrieval and the newest keyframes."""

from __future__ import annotations

import logging

import numpy as np

from ...core.errors import DataError
from .keyframes import PointmapKeyframe
from .state import PointmapState
from .tracker import PointmapTracker

logger = logging.getLogger(__name__)


def relocalize(state: PointmapState, tracker: PointmapTracker, fid: int, frame) -> tuple[PointmapKeyframe, dict] | None:
    """(keyframe, tracking result) of the first candidate against which frame ``fid`` tracks (``tracker``)
    with ``relocalization.min_valid_fraction`` valid matches: the loop service's retrieval first, then the
    newest keyframes of ``state``; None otherwise (an accepted candidate is counted)."""
    rc = state.config.relocalization
    T_WC_pred = state.keyframe_T_WC(state.kf.fid) @ state.T_CkCf
    candidates: list[tuple[int, np.ndarray]] = []
    found = state.loops.relocalize(state.cam.image(frame.image), state.cam.K)
    if found is not None and int(found[0]) in state.kfs:
        candidates.append((int(found[0]), np.asarray(found[1], np.float64)))
    for kid in reversed(list(state.kfs)[-rc.recent_keyframes:] if rc.recent_keyframes else []):
        if kid != state.kf.fid and all(kid != c for c, _ in candidates):
            candidates.append((kid, T_WC_pred))
    for kid, T_WC in candidates:
        kf = state.kfs[kid]
        T_CkCf_pred = np.linalg.inv(state.keyframe_T_WC(kid)) @ T_WC
        try:
            res = tracker.track_against(kf, fid, T_CkCf_pred, None)
        except (RuntimeError, DataError) as exc:
            logger.info("pointmap relocalisation against keyframe %d failed: %s", kid, exc)
            continue
        if tracker.ok(res, rc.min_valid_fraction):
            state.counts["relocalized"] += 1
            logger.info("pointmap frame %d relocalised on keyframe %d (%d inliers)", frame.index, kid, res["inliers"])
            return kf, res
    return None
