"""The pointmap frontend's map outputs: the keyframes' canonical pointmaps as coloured world points and
as depth maps at the input resolution."""

from __future__ import annotations

from typing import Callable, Iterable

import cv2
import numpy as np
import torch

from .keyframes import PointmapKeyframe, query_grid


def keyframe_points(kfs: Iterable[PointmapKeyframe], T_WC_of: Callable[[int], np.ndarray], stride: int,
                    min_confidence: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Canonical pointmaps in the world (every ``stride``-th pixel with a fused confidence of at least
    ``min_confidence``), coloured by the keyframe image; None without any point."""
    pts, cols = [], []
    for kf in kfs:
        grid = query_grid(kf.H, kf.W, stride)
        ok = grid[(kf.C[grid] >= min_confidence) & torch.isfinite(kf.X[grid]).all(-1)]
        if ok.numel() == 0:
            continue
        T_WC = T_WC_of(kf.fid)
        X = kf.X[ok].numpy().astype(np.float64)
        pts.append(X @ T_WC[:3, :3].T + T_WC[:3, 3])
        if kf.colour is not None:
            cols.append(kf.colour.reshape(-1, 3)[ok.numpy()])
        else:
            cols.append(np.repeat(kf.grey.reshape(-1, 1)[ok.numpy()], 3, axis=1))
    if not pts:
        return None
    return np.concatenate(pts), np.concatenate(cols).astype(np.uint8)


def keyframe_depths(kfs: Iterable[PointmapKeyframe], T_WC_of: Callable[[int], np.ndarray],
                    size: tuple[int, int]) -> dict[int, tuple[float, np.ndarray, np.ndarray]]:
    """kf id -> (timestamp, depth (H, W) float32 in the map's scale at the input ``size`` (W, H),
    confidence (H, W) in [0, 1]): the canonical pointmaps' z times the keyframe's scale (0: no point)."""
    W, H = size
    out = {}
    for kf in kfs:
        s = float(np.cbrt(abs(np.linalg.det(T_WC_of(kf.fid)[:3, :3]))))
        z = (kf.X[:, 2] * s).view(kf.H, kf.W).numpy().astype(np.float32)
        c = kf.C.view(kf.H, kf.W).numpy().astype(np.float32)
        valid = np.isfinite(z) & (z > 0) & (c > 0)
        z = np.where(valid, z, 0.0).astype(np.float32)
        conf = np.where(valid, np.minimum(c, 1.0), 0.0).astype(np.float32)
        if (kf.W, kf.H) != (W, H):
            z = cv2.resize(z, (W, H), interpolation=cv2.INTER_NEAREST)
            conf = cv2.resize(conf, (W, H), interpolation=cv2.INTER_NEAREST)
        out[kf.fid] = (kf.timestamp, z, conf)
    return out
