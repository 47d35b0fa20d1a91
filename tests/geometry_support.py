"""Small pose helpers shared by the loop-closure tests (not a test module)."""

from __future__ import annotations

import math

import numpy as np


def rot_y(angle: float) -> np.ndarray:
    """Rotation (3, 3) by ``angle`` radians about the y axis (the synthetic drives' up axis)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rigid(T: np.ndarray) -> np.ndarray:
    """Rigid part ``[R | t]`` of Sim(3) matrices ``[[s R, t], [0, 1]]`` (any batch shape)."""
    out = np.array(T, dtype=np.float64, copy=True)
    s = np.cbrt(np.linalg.det(out[..., :3, :3]))
    out[..., :3, :3] /= s[..., None, None]
    return out
