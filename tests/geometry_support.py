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


def transfer_pixels(depth_i: np.ndarray, K, T_WCi: np.ndarray, T_WCj: np.ndarray):
    """Every pixel of view i with its z-depth ``depth_i`` (H, W) moved into view j (pinhole ``K`` =
    fx, fy, cx, cy; camera-to-world poses): ``(u_j, v_j, z_j)`` (H, W) each, z_j the depth in view j."""
    fx, fy, cx, cy = K
    H, W = depth_i.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    z = depth_i.astype(np.float64)
    X = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1)
    T = np.linalg.inv(T_WCj) @ T_WCi
    Xj = X @ T[:3, :3].T + T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):  # pixels without depth or behind view j
        return fx * Xj[..., 0] / Xj[..., 2] + cx, fy * Xj[..., 1] / Xj[..., 2] + cy, Xj[..., 2]
