"""Depth-sensor terms for inverse-depth keyframes: RGB-D depth prior and calibrated stereo.

Units and scale. The stereo baseline (``StereoRig.T_CLCR``) and sensor depths are metric. fgslam
reads a Sim(3) keyframe pose ``X_W = s R X_C + t`` as "camera frames are metric, ``s`` is world
units per metre": camera-frame coordinates and inverse depths ``d`` of a keyframe are metric, and
the fixed extrinsics act in the camera frame (see ``fgslam.factors.reprojection``). Stereo and RGB-D
frontends hold every ``s = 1`` (world in metres); then nothing here depends on the scale. With a
free ``s`` the stereo term still is consistent: its Jacobian w.r.t. the target keyframe's
``lambda`` is non-zero (a metric baseline observes scale), and intra-keyframe stereo
(left and right image of the same keyframe) depends on ``d`` only.

RGB-D prior: the one implementation of the sensor noise model (:func:`inv_depth_sigma`, relative
or inverse), of the priors' selection and weights (:func:`depth_priors`) and of their residual and
Jacobian (:func:`depth_prior`); the patch frontend's local (``frontends/patch/ba.py``) and global
(``backend/global_ba.py``) bundle adjustments both use it.

Tangent conventions as in ``fgslam.factors.reprojection``: right perturbation, gtsam Similarity3
order ``[w, u, lambda]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..core.camera import StereoRig
from ..core.errors import ConfigError
from .configs import DepthPriorConfig  # the config: torch-free (a run's config loads without torch)
from .reprojection import PoseLike, ReprojectionConfig, ReprojectionResult, reproject_inv_depth

__all__ = [
    "DepthPriorConfig",
    "DepthPriorResult",
    "DepthPriors",
    "depth_prior",
    "depth_priors",
    "inv_depth_sigma",
    "reproject_stereo",
]


def inv_depth_sigma(sensor_inv_depth, config: DepthPriorConfig):
    """Standard deviation (1/m) of sensor inverse depths ``sensor_inv_depth`` (numpy array or torch
    tensor, any shape; same type back) under ``config.noise``."""
    if config.noise == "inverse":
        if isinstance(sensor_inv_depth, torch.Tensor):
            return torch.full_like(sensor_inv_depth, config.sigma)
        return np.full(np.shape(sensor_inv_depth), config.sigma)
    if config.noise == "relative":
        if isinstance(sensor_inv_depth, torch.Tensor):
            return config.sigma * sensor_inv_depth
        return config.sigma * np.asarray(sensor_inv_depth)
    raise ConfigError(f"depth noise model must be relative|inverse, got {config.noise!r}")


@dataclass
class DepthPriors:
    """Inverse-depth priors ``d[idx] ~ value`` of ``M`` patches with weights ``1 / sigma_d^2``.

    Attributes:
        idx: ``(M,)`` int64 patch (structure) index of each prior.
        value: ``(M,)`` sensor inverse depth (1/m), finite and positive.
        weight: ``(M,)`` ``1 / inv_depth_sigma(value)^2``.
    """

    idx: np.ndarray
    value: np.ndarray
    weight: np.ndarray

    def kwargs(self) -> dict:
        """``prior_idx``, ``prior_value``, ``prior_weight`` (the keyword arguments of the patch
        frontend's local and global bundle adjustments)."""
        return dict(prior_idx=self.idx, prior_value=self.value, prior_weight=self.weight)


def depth_priors(sensor_inv_depth: np.ndarray, config: DepthPriorConfig) -> DepthPriors:
    """The priors of the patches with a sensor reading.

    Args:
        sensor_inv_depth: ``(P,)`` sensor inverse depth of each patch (NaN, inf or ``<= 0``: none).
        config: noise model.
    """
    sens = np.asarray(sensor_inv_depth, dtype=np.float64)
    has = np.isfinite(sens) & (sens > 0)
    value = sens[has]
    return DepthPriors(idx=np.nonzero(has)[0], value=value, weight=1.0 / inv_depth_sigma(value, config) ** 2)


@dataclass
class DepthPriorResult:
    """Inverse-depth prior for ``N`` (any batch shape ``...``) patches.

    Attributes:
        residual: ``(...)`` ``d - d_sensor``; zero where invalid.
        weight: ``(...)`` the prior's weight where valid, else 0.
        J_d: ``(...)`` d(residual)/dd: 1 where valid, else 0.
        valid: ``(...)`` bool.
    The cost of a row is ``0.5 * weight * residual^2``.
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
    inv_depth: torch.Tensor, prior_value: torch.Tensor, prior_weight: torch.Tensor | float
) -> DepthPriorResult:
    """RGB-D term of DROID-SLAM section 3.4: the inverse-depth variable's distance to the sensor's.

    Args:
        inv_depth: ``(...)`` inverse-depth variables ``d`` of a keyframe's patches (metric, 1/m).
        prior_value: ``(...)`` sensor inverse depths at the same patches (NaN, inf or ``<= 0``: no
            reading, the row is invalid).
        prior_weight: ``(...)`` or scalar weight, ``1 / sigma_d^2`` (:func:`depth_priors`).

    Returns:
        :class:`DepthPriorResult` with residual ``d - prior_value``.
    """
    value = torch.as_tensor(prior_value, dtype=inv_depth.dtype, device=inv_depth.device)
    valid = torch.isfinite(value) & (value > 0) & torch.isfinite(inv_depth)
    one = torch.ones((), dtype=inv_depth.dtype, device=inv_depth.device)
    zero = torch.zeros((), dtype=inv_depth.dtype, device=inv_depth.device)
    weight = torch.as_tensor(prior_weight, dtype=inv_depth.dtype, device=inv_depth.device)
    residual = torch.where(valid, inv_depth - value, zero)
    return DepthPriorResult(residual=residual, weight=torch.where(valid, weight, zero),
                            J_d=torch.where(valid, one, zero), valid=valid)


def reproject_stereo(
    uv_left_i: torch.Tensor,
    inv_depth: torch.Tensor,
    T_WCi: PoseLike,
    T_WCj: PoseLike | None,
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
