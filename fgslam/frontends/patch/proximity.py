"""Pieces of proximity loop closure (DPV-SLAM section 3.2) that need no frontend state: the bounded
keyframe image store, the candidate test on current poses, and the geometric check of measured
loop correspondences. :class:`fgslam.frontends.patch.PatchFrontend` runs the loop itself
(``_prox_*`` methods): it owns the poses, patches and edges.

Conventions: poses ``T_WC`` are 4x4 Sim(3) camera-to-world ``[[s R, t], [0, 1]]``; the camera
centre is ``t`` and the optical axis the third column of ``R``; pixels use OpenCV's convention.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ...core.lie import sim3_matrix_parts

logger = logging.getLogger(__name__)


class KeyframeStore:
    """Packed measurement-source features of settled keyframes (insertion order = keyframe order),
    at most ``capacity``; the oldest are dropped first (they can no longer get loop edges)."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self._items: OrderedDict[int, object] = OrderedDict()
        self.order: list[int] = []  # every keyframe ever added, in order (also the dropped ones)
        self._ordinal: dict[int, int] = {}
        self.dropped = 0

    def add(self, fid: int, packed) -> None:
        self._items[fid] = packed
        self._ordinal[fid] = len(self.order)
        self.order.append(fid)
        while len(self._items) > self.capacity:
            self._items.popitem(last=False)
            self.dropped += 1

    def get(self, fid: int):
        return self._items.get(fid)

    def __contains__(self, fid: int) -> bool:
        return fid in self._items

    def ordinal(self, fid: int) -> int:
        return self._ordinal[fid]

    @property
    def last(self) -> int | None:
        return self.order[-1] if self.order else None

    def neighbours(self, fid: int, count: int) -> list[int]:
        """Up to ``count`` stored keyframes on each side of ``fid`` in keyframe order, nearest first."""
        k = self._ordinal[fid]
        out = []
        for step in range(1, count + 1):
            for j in (k - step, k + step):
                if 0 <= j < len(self.order) and self.order[j] in self._items:
                    out.append(self.order[j])
        return out


@dataclass
class Candidate:
    """A proximity candidate: keyframe ``fid`` with its mean reprojected displacement ``flow`` (px)
    in the query and the share ``overlap`` of its patches that land in the query image."""

    fid: int
    distance: float
    angle_deg: float
    flow: float
    overlap: float


def pose_filter(T_q: np.ndarray, T_c: np.ndarray, radius: float, max_angle_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which of the candidate poses ``T_c`` (M, 4, 4) are within ``radius`` (map units) of the query
    pose ``T_q`` (4, 4) with optical axes at most ``max_angle_deg`` apart: ``(ok, distance, angle_deg)``."""
    distance = np.linalg.norm(T_c[:, :3, 3] - T_q[:3, 3], axis=1)
    R_q = sim3_matrix_parts(T_q)[0]
    z_c = T_c[:, :3, 2] / np.linalg.norm(T_c[:, :3, 2], axis=1, keepdims=True)
    cos = np.clip(z_c @ R_q[:, 2], -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    return (distance <= radius) & (angle <= max_angle_deg), distance, angle


def fundamental_inliers(uv_a: np.ndarray, uv_b: np.ndarray, threshold_px: float) -> np.ndarray:
    """RANSAC fundamental-matrix inliers (bool (n,)) of correspondences ``uv_a <-> uv_b``; all False
    with fewer than 8 correspondences or when no model is found."""
    import cv2  # deferred: cv2

    n = len(uv_a)
    if n < 8:
        return np.zeros(n, bool)
    F, mask = cv2.findFundamentalMat(uv_a.astype(np.float64), uv_b.astype(np.float64), cv2.FM_RANSAC,
                                     threshold_px, 0.999)
    if F is None or mask is None or F.shape != (3, 3):
        return np.zeros(n, bool)
    return mask.reshape(-1).astype(bool)


def held_frames(num_frames: int, src: np.ndarray, tgt: np.ndarray, is_loop: np.ndarray, gauge: int) -> np.ndarray:
    """Frames (bool (F,)) a global BA holds fixed: those without a non-loop edge (an old keyframe whose
    edges left the bounded inactive store is held, so that a loop to it moves the recent map rather
    than it) and the ``gauge`` oldest of the others (monocular: two, which also fix the scale)."""
    fixed = np.ones(num_frames, bool)
    fixed[src[~is_loop]] = False
    fixed[tgt[~is_loop]] = False
    fixed[np.nonzero(~fixed)[0][:gauge]] = True
    return fixed
