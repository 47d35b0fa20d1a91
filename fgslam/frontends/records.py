"""Pose records of the frontends: how each input frame's pose is obtained (typed, immutable).

Shared by the patch, dense and pointmap families, with the
Sim(3) matrix helpers they use (:func:`rigid`, :func:`sim3_power`, :func:`sim3_interp`).

Every input frame id maps to a record, or to None while it has no pose (before initialisation, a
dropped initialisation attempt):

- :class:`KeyframePose`: a keyframe: its pose is the frontend's keyframe pose (the backend's);
- :class:`AbsolutePose`: a pose of its own (a relocalised frame);
- :class:`RelativePose`: ``T_WC = T_WC(ref) T_ref_frame`` (a removed keyframe, a stationary frame, a
  tracking failure: relative to the frame it was predicted from);
- :class:`InterpolatedPose`: ``T_WC(a) Exp(alpha Log(T_WC(a)^-1 T_WC(b)))`` (a stationary frame placed
  by its flow, a frame dropped from the initialisation buffer).

:func:`resolve_pose` follows the references (with a cache); :meth:`PoseRecord.corrected` re-expresses
a record under a :class:`~fgslam.contracts.contributor.PoseCorrection` (loop closure, global BA).
Poses are 4x4 Sim(3) matrices ``[[s R, t], [0, 1]]``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from ..core.lie import gtsam_matrix, gtsam_sim3, sim3_rigid
from ..loop.records import PoseCorrection

logger = logging.getLogger(__name__)

_RESOLVING = object()  # in the cache while a frame's references are followed (a cycle finds it there)


rigid = sim3_rigid  # the rigid part [R | t] of a Sim(3) matrix, under the name the frontends use


def per_frame_motion(T_prev: np.ndarray, T_new: np.ndarray, steps: int) -> np.ndarray:
    """The constant per-frame motion ``(T_prev^-1 T_new)^(1 / steps)`` of a camera that went from
    ``T_prev`` to ``T_new`` (Sim(3) ``T_WC``) over ``steps >= 1`` frames: a motion model's velocity."""
    V = np.linalg.inv(T_prev) @ T_new
    return V if steps <= 1 else sim3_power(V, 1.0 / steps)


def sim3_interp(Ta: np.ndarray, Tb: np.ndarray, alpha: float) -> np.ndarray:
    """``Ta Exp(alpha Log(Ta^-1 Tb))`` on Sim(3) matrices."""
    return Ta @ sim3_power(np.linalg.inv(Ta) @ Tb, alpha)


def sim3_power(M: np.ndarray, alpha: float) -> np.ndarray:
    """``Exp(alpha Log(M))`` of a Sim(3) matrix, through gtsam's ``Similarity3`` Logmap/Expmap (whose
    tangent is ``fgslam.core.lie.Sim3``'s ``[w, u, lambda]``); per-frame motion model without torch."""
    import gtsam  # deferred: gtsam

    return gtsam_matrix(gtsam.Similarity3.Expmap(alpha * gtsam.Similarity3.Logmap(gtsam_sim3(M))))


class PoseRecord:
    """Base of the pose records (module docstring)."""

    def pose(self, resolve: Callable[[int], Optional[np.ndarray]],
             keyframe_pose: Callable[[int], np.ndarray], fid: int) -> Optional[np.ndarray]:
        """``T_WC`` of frame ``fid`` (None when a reference has no pose); ``resolve(fid)`` gives other
        frames' poses, ``keyframe_pose(fid)`` a keyframe's."""
        raise NotImplementedError

    def corrected(self, fid: int, correction: PoseCorrection) -> "PoseRecord":
        """The record after ``correction`` was applied to every keyframe (itself when unaffected)."""
        return self


@dataclass(frozen=True)
class KeyframePose(PoseRecord):
    """The frame is a keyframe (in the patch graph or finalised)."""

    def pose(self, resolve, keyframe_pose, fid):
        return keyframe_pose(fid)


@dataclass(frozen=True)
class AbsolutePose(PoseRecord):
    """A pose of its own (4x4 ``T_WC``); corrected like a keyframe of the same id."""

    T_WC: np.ndarray

    def pose(self, resolve, keyframe_pose, fid):
        return self.T_WC

    def corrected(self, fid, correction):
        return AbsolutePose(correction.apply_pose(fid, self.T_WC)[0])


@dataclass(frozen=True)
class RelativePose(PoseRecord):
    """``T_WC = T_WC(ref) T_ref_frame``; with a folded correction scale ``s`` of ``ref`` the relative
    pose is re-expressed in the folded units (translation times ``s``)."""

    ref: int
    T_ref_frame: np.ndarray

    def pose(self, resolve, keyframe_pose, fid):
        T_ref = resolve(self.ref)
        return None if T_ref is None else T_ref @ self.T_ref_frame

    def corrected(self, fid, correction):
        if not correction.fold_scale:
            return self
        return RelativePose(self.ref, PoseCorrection.fold_relative(self.T_ref_frame, correction.update_for(self.ref)[1]))


@dataclass(frozen=True)
class InterpolatedPose(PoseRecord):
    """Between frames ``a`` and ``b`` at ``alpha`` (0: a, 1: b) on Sim(3); follows both end poses."""

    a: int
    b: int
    alpha: float

    def pose(self, resolve, keyframe_pose, fid):
        Ta, Tb = resolve(self.a), resolve(self.b)
        return None if Ta is None or Tb is None else sim3_interp(Ta, Tb, self.alpha)


def resolve_pose(fid: int, records: dict, keyframe_pose: Callable[[int], np.ndarray],
                 cache: dict) -> Optional[np.ndarray]:
    """``T_WC`` of frame ``fid`` from ``records`` (fid -> :class:`PoseRecord` or None), following
    references; ``cache`` (fid -> pose) is filled on the way. A record whose references lead back to
    itself (a frontend's bug) gives None, logged, never an endless recursion."""
    if fid in cache:
        T = cache[fid]
        if T is _RESOLVING:
            logger.warning("the pose record of frame %d refers back to itself: no pose", fid)
            return None
        return T
    cache[fid] = _RESOLVING
    rec = records.get(fid)
    try:
        T = None if rec is None else rec.pose(lambda other: resolve_pose(other, records, keyframe_pose, cache),
                                              keyframe_pose, fid)
    except BaseException:  # not left marked as in progress: a later lookup would take it for a cycle
        cache.pop(fid, None)
        raise
    cache[fid] = T
    return T
