"""The pointmap frontend's relocalisation (MASt3R-SLAM section 3.6, step 7 of :mod:`.frontend`): a lost
frame tracked against the loop service's retrieval and the newest keyframes."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from ...errors import DataError

if TYPE_CHECKING:
    from .frontend import PointmapFrontend

logger = logging.getLogger(__name__)


def relocalize(fe: "PointmapFrontend", fid: int, frame):
    """(keyframe, tracking result) of the first candidate against which frame ``fid`` of ``fe`` tracks with
    ``relocalization.min_valid_fraction`` valid matches: the loop service's retrieval first, then the
    newest keyframes; None otherwise (an accepted candidate is counted)."""
    rc = fe.config.relocalization
    T_WC_pred = fe._keyframe_T_WC(fe._kf.fid) @ fe._T_CkCf
    candidates: list[tuple[int, np.ndarray]] = []
    found = fe.loops.relocalize(fe.cam.image(frame.image), fe.cam.K)
    if found is not None and int(found[0]) in fe._kfs:
        candidates.append((int(found[0]), np.asarray(found[1], np.float64)))
    for kid in reversed(list(fe._kfs)[-rc.recent_keyframes:] if rc.recent_keyframes else []):
        if kid != fe._kf.fid and all(kid != c for c, _ in candidates):
            candidates.append((kid, T_WC_pred))
    for kid, T_WC in candidates:
        kf = fe._kfs[kid]
        T_CkCf_pred = np.linalg.inv(fe._keyframe_T_WC(kid)) @ T_WC
        try:
            res = fe.tracker.track_against(kf, fid, T_CkCf_pred, None)
        except (RuntimeError, DataError) as exc:
            logger.info("pointmap relocalisation against keyframe %d failed: %s", kid, exc)
            continue
        if fe.tracker.ok(res, rc.min_valid_fraction):
            fe._counts["relocalized"] += 1
            logger.info("pointmap frame %d relocalised on keyframe %d (%d inliers)", frame.index, kid, res["inliers"])
            return kf, res
    return None
