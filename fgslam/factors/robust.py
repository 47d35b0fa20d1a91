"""Confidence weighting and robust kernels for iteratively reweighted least squares (IRLS), batched torch.

MASt3R-SLAM (eq. 6 and its tracking / backend solvers) weights each residual ``r`` (a vector of
dimension d, e.g. a ray difference, or a scalar) by its match confidence ``q`` and a noise scale
``sigma`` and applies a Huber norm to the whitened residual; the problem is solved by IRLS.
Here, per measurement::

    sqrt_info = sqrt(q) / sigma            (0 when q < min_confidence or anything is non-finite)
    e         = sqrt_info * ||r||           whitened residual norm
    weight    = sqrt_info^2 * w_kernel(e)   IRLS weight on the raw residual: H += J^T weight J,
                                            g += J^T weight r, the minimised cost is sum rho(e)
    cost      = rho(e)

Kernels use gtsam's ``noiseModel.mEstimator`` conventions (``rho(e) = e^2/2`` near 0 and
``w(e) = rho'(e)/e``): Huber, Cauchy, Tukey; ``none`` is plain least squares. Apply the kernel to
each component instead of the vector norm by giving residuals a trailing dimension of size 1.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from ..core.errors import ConfigError
from .configs import KernelKind, RobustConfig  # the config: torch-free (a run's config loads without torch)


class RobustWeights(NamedTuple):
    """Output of :func:`irls_weights`; every tensor has the measurement batch shape ``...``."""

    weight: torch.Tensor  # IRLS weight on the raw residual (confidence x kernel), 0 for invalid
    cost: torch.Tensor  # rho(e) per measurement, 0 for invalid
    whitened_norm: torch.Tensor  # e = sqrt(q)/sigma * ||r||, 0 for invalid
    valid: torch.Tensor  # bool: finite residual and confidence, confidence >= min_confidence


def kernel_weight(e: torch.Tensor, kind: KernelKind, delta: float) -> torch.Tensor:
    """IRLS weight ``w(e) = rho'(e)/e`` of a whitened residual norm ``e >= 0``."""
    if kind == "none":
        return torch.ones_like(e)
    if kind == "huber":
        return torch.where(e <= delta, torch.ones_like(e), delta / torch.clamp(e, min=delta))
    if kind == "cauchy":
        return 1 / (1 + (e / delta) ** 2)
    if kind == "tukey":
        return torch.where(e <= delta, (1 - (e / delta) ** 2) ** 2, torch.zeros_like(e))
    raise ValueError(f"unknown robust kernel kind {kind!r} (expected none, huber, cauchy or tukey)")


def kernel_cost(e: torch.Tensor, kind: KernelKind, delta: float) -> torch.Tensor:
    """Robust cost ``rho(e)`` of a whitened residual norm ``e >= 0`` (``e^2/2`` near 0)."""
    if kind == "none":
        return 0.5 * e * e
    if kind == "huber":
        return torch.where(e <= delta, 0.5 * e * e, delta * e - 0.5 * delta * delta)
    if kind == "cauchy":
        return 0.5 * delta * delta * torch.log1p((e / delta) ** 2)
    if kind == "tukey":
        inside = delta * delta / 6 * (1 - (1 - (e / delta) ** 2) ** 3)
        return torch.where(e <= delta, inside, torch.full_like(e, delta * delta / 6))
    raise ValueError(f"unknown robust kernel kind {kind!r} (expected none, huber, cauchy or tukey)")


def confidence_sqrt_information(
    confidence: torch.Tensor, sigma: float | torch.Tensor, min_confidence: float = 0.0
) -> torch.Tensor:
    """``sqrt(q) / sigma``, zero where ``q < min_confidence`` or q / sigma is not finite or q < 0."""
    sigma = torch.as_tensor(sigma, dtype=confidence.dtype, device=confidence.device)
    ok = torch.isfinite(confidence) & torch.isfinite(sigma) & (sigma > 0)
    ok = ok & (confidence >= min_confidence) & (confidence >= 0)
    q = torch.where(ok, confidence, torch.zeros_like(confidence))
    s = torch.where(ok, sigma, torch.ones_like(sigma))
    return torch.sqrt(q) / s


def irls_weights(
    residual: torch.Tensor,
    confidence: torch.Tensor | None,
    sigma: float | torch.Tensor,
    cfg: RobustConfig,
) -> RobustWeights:
    """Per-measurement IRLS weights for residuals (..., d), confidences (...) (None: all 1), noise sigma.

    Invalid measurements (non-finite residual or confidence, confidence below ``cfg.min_confidence``)
    get weight 0, cost 0 and ``valid = False``; count them with ``(~valid).sum()``.
    """
    if not cfg.delta > 0:
        raise ConfigError(f"RobustConfig.delta must be > 0, got {cfg.delta!r}")
    if confidence is None:
        confidence = torch.ones(residual.shape[:-1], dtype=residual.dtype, device=residual.device)
    finite_r = torch.isfinite(residual).all(-1)
    sqrt_info = confidence_sqrt_information(confidence, sigma, cfg.min_confidence)
    valid = finite_r & (sqrt_info > 0)
    norm = torch.linalg.vector_norm(torch.where(finite_r[..., None], residual, torch.zeros_like(residual)), dim=-1)
    sqrt_info = torch.where(valid, sqrt_info, torch.zeros_like(sqrt_info))
    e = sqrt_info * norm
    weight = sqrt_info * sqrt_info * kernel_weight(e, cfg.kind, cfg.delta)
    cost = torch.where(valid, kernel_cost(e, cfg.kind, cfg.delta), torch.zeros_like(e))
    return RobustWeights(weight=weight, cost=cost, whitened_norm=e, valid=valid)
