"""Compiled kernel of the ``patch`` dense descriptor (:mod:`fgslam.frontends.pointmap.descriptors`), one
pixel at a time, written channel-last (:mod:`fgslam.core.jit`). It is the implementation: the
descriptor's tests call it.

The arithmetic is float32 in the order numpy's channel-first reductions take (a running sum over the 16
samples, from the first), so the bits are those of the former array code.
"""

from __future__ import annotations

import numpy as np

from ...core.jit import kernel
from .config import PATCH_SIDE

PATCH_SAMPLES = PATCH_SIDE * PATCH_SIDE


@kernel
def patch_rows(smooth, offsets, norm_floor, texture_sq):
    """``(D (H, W, 16), Q (H, W))`` float32 of the smoothed grey image ``smooth (H, W)`` float32:
    sample ``n = 4 iy + ix`` of pixel ``(v, u)`` is ``smooth[v + offsets[iy], u + offsets[ix]]`` (borders
    replicated), mean removed; ``G`` the mean of the squared samples; ``D`` scaled to unit norm (zero where
    the norm is at most ``norm_floor``); ``Q = G / (G + texture_sq)``."""
    H, W = smooth.shape
    f32 = np.float32
    n_samples = f32(PATCH_SAMPLES)
    zero = f32(0.0)
    one = f32(1.0)
    D = np.empty((H, W, PATCH_SAMPLES), np.float32)
    Q = np.empty((H, W), np.float32)
    rows = np.empty(PATCH_SIDE, np.int64)
    cols = np.empty(PATCH_SIDE, np.int64)
    for v in range(H):
        for a in range(PATCH_SIDE):
            rows[a] = min(max(v + offsets[a], 0), H - 1)
        for u in range(W):
            for a in range(PATCH_SIDE):
                cols[a] = min(max(u + offsets[a], 0), W - 1)
            d = D[v, u]
            total = smooth[rows[0], cols[0]]
            d[0] = total
            for n in range(1, PATCH_SAMPLES):
                x = smooth[rows[n // PATCH_SIDE], cols[n % PATCH_SIDE]]
                d[n] = x
                total += x
            mean = total / n_samples
            d[0] -= mean
            sq = d[0] * d[0]
            for n in range(1, PATCH_SAMPLES):
                d[n] -= mean
                sq += d[n] * d[n]
            norm = np.sqrt(sq)
            scale = one / max(norm, norm_floor) if norm > norm_floor else zero
            for n in range(PATCH_SAMPLES):
                d[n] *= scale
            G = sq / n_samples
            Q[v, u] = G / (G + texture_sq)
    return D, Q
