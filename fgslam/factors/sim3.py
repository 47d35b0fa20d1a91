"""Sim(3) relative-pose (odometry / loop-closure) residual of DPV-SLAM eqs. 5-6, batched, with Jacobians.

Poses are keyframe-to-world similarities ``T_i = T_WCi``, ``T_j = T_WCj`` and the measurement is
``Z_ij``, the measured ``T_CiCj`` (frame j expressed in frame i; a perfect measurement has
``Z_ij = T_i^-1 T_j``). The residual is the one of ``gtsam.BetweenFactorSimilarity3``::

    r = Log(Z_ij^-1 T_i^-1 T_j)                      (7,)  tangent [w, u, lambda]

Right perturbations ``T <- T Exp(d)`` give the exact Jacobians::

    dr/dd_j =  Jr^-1(r)
    dr/dd_i = -Jr^-1(r) Ad(T_j^-1 T_i)

where ``Jr^-1`` is the inverse right Jacobian of Sim(3) (:meth:`fgslam.core.lie.Sim3.right_jacobian_inv`).
gtsam 4.3.0's BetweenFactorSimilarity3 uses the first-order form without ``Jr^-1``
(``I`` and ``-Ad(T_j^-1 T_i)``, exact only at r = 0; the error is O(|r|) relative), available here
with ``exact=False``. Both give the same optimum (the residual is the same); the exact one converges
faster when residuals are large (loop closures before correction).

Pitfall (measured, see tests): with gtsam's first-order Jacobians, an LM whose acceptance uses the
true cost stops at a non-stationary point of the cost when the optimum has non-zero residuals (an
inconsistent loop): on a 6-pose loop gtsam's LM ended at cost 25.395 where the optimum is 25.387.
gtsam's PriorFactorSimilarity3 likewise linearises with the identity. A Python-driven solver should
take the between factors' linearisation from :func:`between_jacobian_factors` (exact).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import torch

from ..core.lie import Sim3
from .configs import SIM3_DOF  # defined with the torch-free configs (the loop configs load without torch)
from .robust import kernel_weight

logger = logging.getLogger(__name__)


def sim3_between_residual(
    T_i: Sim3, T_j: Sim3, Z_ij: Sim3, exact: bool = True
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Residual and Jacobians of ``r = Log(Z_ij^-1 T_i^-1 T_j)`` for broadcastable batches ``...``.

    Returns ``r`` (..., 7), ``J_i`` = dr/dd_i (..., 7, 7), ``J_j`` = dr/dd_j (..., 7, 7) for right
    perturbations ``T_i Exp(d_i)``, ``T_j Exp(d_j)``. ``exact=False`` returns gtsam's first-order
    Jacobians (``-Ad(T_j^-1 T_i)`` and ``I``).
    """
    T_ij = T_i.inverse() @ T_j
    r = (Z_ij.inverse() @ T_ij).log()
    Ad_ji = T_ij.inverse().adjoint()
    if exact:
        J_j = Sim3.right_jacobian_inv(r)
    else:
        J_j = torch.eye(SIM3_DOF, dtype=r.dtype, device=r.device).expand(r.shape + (SIM3_DOF,))
    J_i = -J_j @ Ad_ji
    return r, J_i, J_j


def make_between_factors(
    keys_i: Sequence[int],
    keys_j: Sequence[int],
    Z_ij: Sim3,
    *,
    sigmas: np.ndarray | torch.Tensor | None = None,
    information: np.ndarray | torch.Tensor | None = None,
    huber_k: float | None = None,
) -> list:
    """``gtsam.BetweenFactorSimilarity3`` factors for N measurements ``Z_ij`` (shape (N,)).

    Give exactly one of ``sigmas`` ((7,) or (N, 7), tangent order [w, u, lambda]) or ``information``
    ((7, 7) or (N, 7, 7), symmetric positive definite). ``huber_k`` (whitened-residual threshold)
    wraps each noise model in gtsam's Huber m-estimator. Measurements or noise with non-finite
    values, non-positive sigmas or a non-positive-definite information are left out (never NaN into
    the graph) and counted in a warning; the returned list holds the valid factors in input order.
    Inconsistent argument shapes raise ValueError.
    """
    import gtsam  # deferred: gtsam

    noise, ok = _checked_noise("make_between_factors", keys_i, keys_j, Z_ij, sigmas, information)
    measurements = Z_ij.to_gtsam()
    factors = []
    for k in np.flatnonzero(ok):
        if sigmas is not None:
            model = gtsam.noiseModel.Diagonal.Sigmas(np.ascontiguousarray(noise[k]))
        else:
            model = gtsam.noiseModel.Gaussian.Information(0.5 * (noise[k] + noise[k].T))
        if huber_k is not None:
            model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k), model)
        factors.append(gtsam.BetweenFactorSimilarity3(int(keys_i[k]), int(keys_j[k]), measurements[k], model))
    _warn_skipped("make_between_factors", ok)
    return factors


def between_jacobian_factors(
    keys_i: Sequence[int],
    keys_j: Sequence[int],
    T_i: Sim3,
    T_j: Sim3,
    Z_ij: Sim3,
    *,
    sigmas: np.ndarray | torch.Tensor | None = None,
    information: np.ndarray | torch.Tensor | None = None,
    huber_k: float | None = None,
    exact: bool = True,
) -> list:
    """Linearisations at poses ``T_i``, ``T_j`` (shape (N,)) of the factors :func:`make_between_factors`
    builds, as whitened ``gtsam.JacobianFactor`` (unit noise): ``||A_i d_i + A_j d_j - b||^2`` with
    ``A = sqrt(w) S J``, ``b = -sqrt(w) S r``, ``S^T S`` the information and ``w`` the Huber weight of
    ``||S r||`` (gtsam's Robust reweighting). With ``exact=True`` (default) J are the exact
    Jacobians, so a Python-driven Gauss-Newton / LM converges to a true stationary point; with
    ``exact=False`` the result equals gtsam's own ``factor.linearize`` (same quadratic form).
    Degenerate measurements, noise or poses are left out and counted in a warning.
    """
    import gtsam  # deferred: gtsam

    noise, ok = _checked_noise("between_jacobian_factors", keys_i, keys_j, Z_ij, sigmas, information)
    n = len(keys_i)
    dtype = torch.float64
    r, J_i, J_j = sim3_between_residual(T_i.to(dtype), T_j.to(dtype), Z_ij.to(dtype), exact=exact)
    if sigmas is not None:
        S = np.zeros((n, SIM3_DOF, SIM3_DOF))
        S[:, range(SIM3_DOF), range(SIM3_DOF)] = 1.0 / np.where(ok[:, None], noise, 1.0)
    else:
        info = np.where(ok[:, None, None], 0.5 * (noise + noise.transpose(0, 2, 1)), np.eye(SIM3_DOF))
        S = np.linalg.cholesky(info).transpose(0, 2, 1)  # upper triangular, S^T S = information
    S_t = torch.as_tensor(S, dtype=dtype)
    r_w = (S_t @ r.detach().cpu()[..., None])[..., 0]
    A_i = S_t @ J_i.detach().cpu()
    A_j = S_t @ J_j.detach().cpu()
    if huber_k is not None:
        sqrt_w = torch.sqrt(kernel_weight(torch.linalg.vector_norm(r_w, dim=-1), "huber", huber_k))
        r_w, A_i, A_j = sqrt_w[:, None] * r_w, sqrt_w[:, None, None] * A_i, sqrt_w[:, None, None] * A_j
    finite = torch.isfinite(r_w).all(-1) & torch.isfinite(A_i).all((-2, -1)) & torch.isfinite(A_j).all((-2, -1))
    ok = ok & finite.numpy()
    unit = gtsam.noiseModel.Unit.Create(SIM3_DOF)
    r_np, Ai_np, Aj_np = r_w.numpy(), A_i.numpy(), A_j.numpy()
    factors = [
        gtsam.JacobianFactor(int(keys_i[k]), Ai_np[k], int(keys_j[k]), Aj_np[k], -r_np[k], unit)
        for k in np.flatnonzero(ok)
    ]
    _warn_skipped("between_jacobian_factors", ok)
    return factors


def _checked_noise(name, keys_i, keys_j, Z_ij: Sim3, sigmas, information) -> tuple[np.ndarray, np.ndarray]:
    """Broadcast noise to (N, 7) sigmas or (N, 7, 7) information and flag the usable measurements:
    finite Z_ij with s > 0, finite positive sigmas or a finite positive-definite information."""
    if (sigmas is None) == (information is None):
        raise ValueError(f"{name}: give exactly one of sigmas or information")
    n = len(keys_i)
    if len(keys_j) != n or Z_ij.shape != (n,):
        raise ValueError(f"{name}: {n} keys_i, {len(keys_j)} keys_j, Z_ij of shape {tuple(Z_ij.shape)}")
    Zm = Z_ij.matrix().detach().to(torch.float64).cpu().numpy()
    ok = np.isfinite(Zm).all(axis=(-2, -1)) & (Z_ij.s.detach().cpu().numpy() > 0)
    if sigmas is not None:
        noise = np.broadcast_to(np.asarray(sigmas, dtype=np.float64), (n, SIM3_DOF))
        return noise, ok & np.isfinite(noise).all(-1) & (noise > 0).all(-1)
    noise = np.broadcast_to(np.asarray(information, dtype=np.float64), (n, SIM3_DOF, SIM3_DOF))
    finite = np.isfinite(noise).all(axis=(-2, -1))
    sym = 0.5 * (noise + noise.transpose(0, 2, 1))
    pd = np.linalg.eigvalsh(np.where(finite[:, None, None], sym, np.eye(SIM3_DOF))).min(-1) > 0
    return noise, ok & finite & pd


def _warn_skipped(name: str, ok: np.ndarray) -> None:
    skipped = int((~ok).sum())
    if skipped:
        logger.warning("%s: left out %d of %d degenerate Sim(3) measurements", name, skipped, ok.size)
