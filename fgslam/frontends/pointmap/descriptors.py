"""Dense per-pixel descriptors ``D`` with confidences ``Q`` that need no learned weights.

MASt3R's head predicts a descriptor per pixel and a confidence ``Q`` (MASt3R-SLAM section 3.1); the
built-in pointmap sources compute one from the grey image instead (:class:`DescriptorConfig`):

- ``patch``: a normalised local patch: the image smoothed by a Gaussian (``sigma``), sampled on a 4x4
  grid of spacing ``step`` around the pixel, mean removed and scaled to unit norm; the dot product of
  two such descriptors is their normalised cross-correlation.
- ``gradient``: gradient-orientation histograms (a small DAISY): the gradient split into four signed
  orientation channels ``max(0, g . e_k)``, each smoothed by a Gaussian (``sigma``), sampled at 2x2
  cells ``step`` apart, unit norm; tolerant to brightness changes and small misalignments.

Both are 16-dimensional float32, unit norm (zero where the image is flat). ``Q`` in [0, 1] is the
texture evidence ``G / (G + texture^2)`` with ``G`` the local contrast (patch: the patch variance;
gradient: the smoothed squared gradient magnitude), in grey levels.

Which default: measured by ``tools/bench_pointmap.py`` (the ``descriptors`` section; 320x240
room-loop pair, matches whose geometry is wrong by a 1 / 2 degree rotation, i.e. 3.2 / 6.4 px, refined
with the default window, radius 1 at spacings 4, 2, 1): ``patch`` brings them to a median 0.54 / 0.97 px
(79 % / 51 % within 1 px), ``gradient`` to 0.57 / 3.10 px (73 % / 40 %). ``patch`` is the default. It is a
compiled kernel (:mod:`.descriptors_jit`, about 1.5 ms per 320x240 image); ``gradient`` stays array code.
"""

from __future__ import annotations

import cv2
import numpy as np

from ...core.errors import DataError
from .config import PATCH_SIDE, DescriptorConfig  # the config: in .config, torch- and OpenCV-free (a run's config loads without them)

__all__ = ["DescriptorConfig", "dense_descriptors"]

DESCRIPTOR_DIM = 16
NORM_FLOOR = 1e-6  # a descriptor whose norm is at most this (a flat image) is zero


def _stack_shifted(channels: list[np.ndarray], offsets: list[tuple[int, int]]) -> np.ndarray:
    """``(len(offsets) * len(channels), H, W)`` float32: for each offset ``(dx, dy)`` (outer) and channel
    (inner) the channel shifted, ``out[n, v, u] = c[v + dy, u + dx]`` with replicated borders (one
    padding per channel)."""
    H, W = channels[0].shape[:2]
    p = max(max(abs(dx), abs(dy)) for dx, dy in offsets)
    padded = [cv2.copyMakeBorder(c, p, p, p, p, cv2.BORDER_REPLICATE) for c in channels]
    out = np.empty((len(offsets) * len(channels), H, W), np.float32)
    n = 0
    for dx, dy in offsets:
        for c in padded:
            out[n] = c[p + dy:p + dy + H, p + dx:p + dx + W]
            n += 1
    return out


def dense_descriptors(image: np.ndarray, config: DescriptorConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(D (H, W, 16) float32 unit norm, Q (H, W) float32 in [0, 1])`` of a grey image (module docstring)."""
    cfg = config or DescriptorConfig()
    image = np.asarray(image)
    if image.ndim != 2:
        raise DataError(f"dense descriptors need a grey image (H, W), got shape {image.shape}")
    grey = image.astype(np.float32)
    s = cfg.step
    if cfg.kind == "patch":
        from .descriptors_jit import patch_rows  # deferred: numba (compiled kernel, core/jit.py)

        # PATCH_SIDE samples spacing s, centred
        offsets = np.array([(-(PATCH_SIDE - 1) * s + 2 * s * a) // 2 for a in range(PATCH_SIDE)], np.int64)
        smooth = cv2.GaussianBlur(grey, (0, 0), cfg.sigma)
        return patch_rows(smooth, offsets, np.float32(NORM_FLOOR), np.float32(cfg.texture ** 2))
    if cfg.kind != "gradient":
        raise DataError(f"unknown descriptor kind {cfg.kind!r} (expected patch or gradient)")
    # channel-first (C, H, W): the per-pixel reductions below are then sums of whole images
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)
    channels = [cv2.GaussianBlur(np.maximum(c, 0), (0, 0), cfg.sigma) for c in (gx, gy, -gx, -gy)]
    half = max(s // 2, 1)
    D = _stack_shifted(channels, [(dx, dy) for dy in (-half, half) for dx in (-half, half)])
    G = cv2.GaussianBlur(gx * gx + gy * gy, (0, 0), cfg.sigma)
    norm = np.sqrt((D * D).sum(0))
    D *= np.where(norm > NORM_FLOOR, 1.0 / np.maximum(norm, NORM_FLOOR), 0.0).astype(np.float32)
    Q = (G / (G + cfg.texture ** 2)).astype(np.float32)
    D = D.transpose(1, 2, 0)
    return np.ascontiguousarray(D), Q
