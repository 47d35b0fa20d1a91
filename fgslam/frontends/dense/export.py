"""The dense frontend's map outputs: keyframe depth maps at image resolution and confidence-filtered
grid points in the world frame."""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from ...core.lie import sim3_matrix_parts
from .graph import DenseKeyframeState

#: the smallest inverse depth inverted to a depth (guards the division)
_MIN_INV_DEPTH = 1e-12


def keyframe_depths(kfs: list[DenseKeyframeState], T_WC_of: Callable[[int], np.ndarray], size: tuple[int, int],
                    crop: tuple[int, int], min_confidence: float) -> dict[int, tuple[float, np.ndarray, np.ndarray]]:
    """Keyframe id -> (timestamp, depth (H, W) float32 in map units, confidence (H, W) in [0, 1]): the grid
    inverse depths upsampled (bilinear) to the image ``size`` (W, H) over the grid's ``crop`` (H, W) and
    inverted at the keyframe's scale; pixels whose confidence is below ``min_confidence`` are 0 (no depth)."""
    width, height = size
    out = {}
    for kf in kfs:
        T_WC = T_WC_of(kf.fid)
        s = float(sim3_matrix_parts(T_WC)[2])
        H, W = crop
        inv = np.zeros((height, width), np.float32)
        conf = np.zeros((height, width), np.float32)
        inv[:H, :W] = cv2.resize(kf.inv_depth.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
        conf[:H, :W] = cv2.resize(kf.confidence.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
        depth = np.where((inv > 0) & (conf >= min_confidence), s / np.maximum(inv, _MIN_INV_DEPTH), 0.0)
        out[kf.fid] = (kf.timestamp, depth.astype(np.float32), np.clip(conf, 0.0, 1.0))
    return out


def keyframe_points(kfs: list[DenseKeyframeState], T_WC_of: Callable[[int], np.ndarray], K_grid,
                    min_confidence: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Confidence-filtered grid points ``(X_W (M, 3), colour (M, 3) uint8)`` of the keyframes ``kfs``
    (grid intrinsics ``K_grid``), or None without any."""
    chunks_X, chunks_c = [], []
    fx, fy, cx, cy = K_grid
    for kf in kfs:
        ok = (kf.confidence >= min_confidence) & (kf.inv_depth > 0)
        if not ok.any():
            continue
        y, x = np.nonzero(ok)
        z = 1.0 / kf.inv_depth[y, x]
        X_C = np.stack([(x - cx) / fx * z, (y - cy) / fy * z, z], -1)
        T_WC = T_WC_of(kf.fid)
        chunks_X.append(X_C @ T_WC[:3, :3].T + T_WC[:3, 3])
        chunks_c.append(kf.colour[y, x])
    if not chunks_X:
        return None
    return np.concatenate(chunks_X), np.concatenate(chunks_c).astype(np.uint8)
