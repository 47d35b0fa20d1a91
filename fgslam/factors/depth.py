"""Depth-sensor terms for inverse-depth keyframes: RGB-D depth prior and calibrated stereo.

Units and scale. The stereo baseline (``StereoRig.T_CLCR``) and sensor depths are metric. fgslam
reads a Sim(3) keyframe pose ``X_W = s R X_C + t`` as "camera frames are metric, ``s`` is world
units per metre": camera-frame coordinates and inverse depths ``d`` of a keyframe are metric, and
the fixed extrinsics act in the camera frame (see ``fgslam.factors.reprojection``). Stereo and RGB-D
frontends hold every ``s = 1`` (world in metres); then nothing here depends on the scale. With a
free ``s`` the stereo term still is consistent: its Jacobian w.r.t. the target keyframe's
``lambda`` is non-zero (a metric baseline observes scale), and intra-keyframe stereo
(left and right image of the same keyframe) depends on ``d`` only.

Tangent conventions as in ``fgslam.factors.reprojection``: right perturbation, gtsam Similarity3
order ``[w, u, lambda]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from ..camera import StereoRig
from ..config import ranged
from .reprojection import ReprojectionConfig, ReprojectionResult, reproject_inv_depth

__all__ = [
    "DepthPriorConfig",
    "DepthPriorResult",
    "depth_prior",
    "reproject_stereo",
]


@dataclass
class DepthPriorConfig:
    """Tunables of the RGB-D inverse-depth prior (DROID-SLAM section 3.4)."""

    weight: float = ranged(0.05, ge=0)  # weight of (d - 1/z_sensor)^2 relative to a unit-weight pixel residual
    min_depth: float = ranged(0.1, ge=0)  # sensor depths (metres) at or below this are invalid (0 = "no reading")
    max_depth: float = ranged(math.inf, gt=0)  # sensor depths above this (metres) are invalid (beyond sensor range)


@dataclass
class DepthPriorResult:
    """Inverse-depth prior for ``N`` (any batch shape ``...``) pixels.

    Attributes:
        residual: ``(...)`` ``d - 1 / z_sensor``; zero where invalid.
        weight: ``(...)`` ``config.weight`` where the sensor reading is valid, else 0.
        J_d: ``(...)`` d(residual)/dd: 1 where valid, else 0.
        valid: ``(...)`` bool.
    The cost of a row is ``weight * residual^2``.
    """

    residual: torch.Tensor
    weight: torch.Tensor
    J_d: torch.Tensor
    valid: torch.Tensor

    @property
    def n_invalid(self) -> int:
        """Number of rows without a usable sensor reading (or with a non-finite ``d``)."""
        return int(self.valid.numel() - int(self.valid.sum()))


def depth_prior(
    inv_depth: torch.Tensor, sensor_depth: torch.Tensor, config: DepthPriorConfig | None = None
) -> DepthPriorResult:
    """RGB-D term of DROID-SLAM section 3.4: penalise the inverse-depth variable's distance to the sensor.

    Args:
        inv_depth: ``(...)`` inverse-depth variables ``d`` of a keyframe's pixels (metric, 1/m).
        sensor_depth: ``(...)`` sensor z-depth in metres at the same pixels (0, NaN, inf, negative or
            outside ``[min_depth, max_depth]``: no reading).
        config: weight and valid sensor range.

    Returns:
        :class:`DepthPriorResult` with residual ``d - 1 / z_sensor``.
    """
    config = config or DepthPriorConfig()
    z = sensor_depth.to(inv_depth.dtype)
    valid = torch.isfinite(z) & (z > config.min_depth) & (z <= config.max_depth) & torch.isfinite(inv_depth)
    one = torch.ones((), dtype=inv_depth.dtype, device=inv_depth.device)
    zero = torch.zeros((), dtype=inv_depth.dtype, device=inv_depth.device)
    inv_z = 1.0 / torch.where(valid, z, one)
    residual = torch.where(valid, inv_depth - inv_z, zero)
    weight = torch.where(valid, config.weight * one, zero)
    return DepthPriorResult(residual=residual, weight=weight, J_d=torch.where(valid, one, zero), valid=valid)


def reproject_stereo(
    uv_left_i: torch.Tensor,
    inv_depth: torch.Tensor,
    T_WCi: Any,
    T_WCj: Any | None,
    rig: StereoRig,
    uv_right_target: torch.Tensor,
    *,
    config: ReprojectionConfig | None = None,
) -> ReprojectionResult:
    """Stereo term: a left pixel of keyframe ``i`` with inverse depth ``d``, seen in the right image of ``j``.

    ``residual = pi_R(T_CRCL T_WCj^-1 T_WCi X_i) - uv_right_target`` with ``X_i`` the left-camera
    point of ``uv_left_i`` at inverse depth ``d`` (metric) and ``T_CRCL`` the rig's fixed
    left-to-right extrinsics (metric, applied in keyframe ``j``'s camera frame).

    Args:
        uv_left_i: ``(..., 2)`` pixels in keyframe ``i``'s left image.
        inv_depth: ``(...)`` their inverse depths.
        T_WCi: pose of keyframe ``i``'s left camera (Sim3/SE3-like or ``(R, t, s)``); not used
            when ``T_WCj`` is None.
        T_WCj: pose of keyframe ``j``'s left camera, or None for the right image of keyframe ``i``
            itself; the residual then depends on ``d`` only and ``J_Ti``, ``J_Tj`` are zero.
            (Passing ``T_WCj = T_WCi`` instead gives ``J_Ti + J_Tj = 0`` up to rounding.)
        rig: calibrated stereo rig (intrinsics of both cameras, ``T_CLCR``).
        uv_right_target: ``(..., 2)`` observed pixels in the right image.
        config: validity threshold (minimum depth in the right camera).

    Returns:
        :class:`ReprojectionResult` (Jacobians w.r.t. right perturbations, order [w, u, lambda]).
    """
    dtype, device = uv_left_i.dtype, uv_left_i.device
    K_left = rig.left.K_tensor(dtype, device)
    K_right = rig.right.K_tensor(dtype, device)
    T_CRCL = torch.as_tensor(rig.T_CRCL, dtype=dtype, device=device)
    if T_WCj is not None:
        return reproject_inv_depth(
            uv_left_i, inv_depth, T_WCi, T_WCj, K_left, uv_right_target, K_right, T_CtCj=T_CRCL, config=config
        )
    identity = (
        torch.eye(3, dtype=dtype, device=device),
        torch.zeros(3, dtype=dtype, device=device),
        torch.ones((), dtype=dtype, device=device),
    )
    result = reproject_inv_depth(
        uv_left_i, inv_depth, identity, identity, K_left, uv_right_target, K_right, T_CtCj=T_CRCL, config=config
    )
    result.J_Ti = torch.zeros_like(result.J_Ti)
    result.J_Tj = torch.zeros_like(result.J_Tj)
    return result
