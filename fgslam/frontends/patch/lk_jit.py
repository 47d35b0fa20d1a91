"""Compiled row kernel of the Lucas-Kanade source (:mod:`fgslam.frontends.patch.lk`): a track's
forward-backward error, the image-border and finiteness checks and its confidence, one pass over the
tracks of a request (:mod:`fgslam.core.jit`). :meth:`LKSource.measure_batch` calls it; it is the
implementation.
"""

from __future__ import annotations

import numpy as np

from ...core.jit import kernel

ERROR_CAP = 1e6  # photometric and forward-backward errors are clipped to [0, ERROR_CAP] (non-finite: 0)


@kernel
def _capped(x):
    if not np.isfinite(x):
        return 0.0
    return min(max(x, 0.0), ERROR_CAP)


@kernel
def finish_tracks(uv_fwd, ok_fwd, err, p_src, uv_back, ok_back, uv_pred, scale, half, width, height,
                  fb_threshold, error_sigma, fb_sigma, min_confidence):
    """Per track (LK-resolution forward result ``uv_fwd``, its status and photometric error ``err``,
    source ``p_src`` and backward result ``uv_back``): the target in input pixels (``uv_pred`` where
    rejected), the confidence (0 where rejected) and the forward-backward error in input pixels.
    A track is kept when both OpenCV statuses hold, it lies ``half`` input pixels inside the
    ``width`` x ``height`` image, everything is finite, the forward-backward error is at most
    ``fb_threshold`` and the confidence reaches ``min_confidence``."""
    n = uv_fwd.shape[0]
    uv_out = np.empty((n, 2))
    confidence = np.zeros(n)
    fb_out = np.empty(n)
    for i in range(n):
        dx = np.float64(uv_back[i, 0]) - np.float64(p_src[i, 0])
        dy = np.float64(uv_back[i, 1]) - np.float64(p_src[i, 1])
        fb = np.sqrt(dx * dx + dy * dy) / scale
        u = (np.float64(uv_fwd[i, 0]) + 0.5) / scale - 0.5
        v = (np.float64(uv_fwd[i, 1]) + 0.5) / scale - 0.5
        e = np.float64(err[i])
        inside = u >= half and u <= width - 1 - half and v >= half and v <= height - 1 - half
        finite = np.isfinite(u) and np.isfinite(v) and np.isfinite(fb) and np.isfinite(e)
        ok = ok_fwd[i] and ok_back[i] and inside and finite and fb <= fb_threshold
        e = _capped(e)
        fb = _capped(fb)
        fb_out[i] = fb
        c = 1.0 / (1.0 + (e / error_sigma) ** 2) / (1.0 + (fb / fb_sigma) ** 2)
        if ok and c >= min_confidence:
            confidence[i] = c
        if ok:
            uv_out[i, 0] = u
            uv_out[i, 1] = v
        else:
            uv_out[i, 0] = uv_pred[i, 0]
            uv_out[i, 1] = uv_pred[i, 1]
    return uv_out, confidence, fb_out
