"""MASt3R-SLAM pointmap residuals with analytic Jacobians, batched over matches.

Murai, Dexheimer & Davison, "MASt3R-SLAM", CVPR 2025. A match pairs a canonical point
``X_f_in_f`` of frame f (its pointmap, in camera frame f) with ``X_k_in_k`` of keyframe k.
Every residual here is a function of the predicted point ``Y = T_CkCf X_f_in_f`` (frame k):

================================  ===========================  =========================
function                          residual rows (h(T) - z)     paper (main / supp. sec. 7)
================================  ===========================  =========================
:func:`point_residuals`           ``Y - X_k`` (3)              eq. 6 / eqs. 14-15
:func:`ray_dist_residuals`        ``psi(Y) - psi(X_k)`` (3),   eqs. 7, 10 / eqs. 16-22
                                  ``||Y|| - ||X_k||`` (1)
:func:`calibrated_residuals`      ``pi(Y) - uv_k`` (2),        eq. 11 / eqs. 23-25
                                  ``log z(Y) - log z(X_k)`` (1)
:func:`relative_to_global`        chain rule T_CkCf ->         eq. 10 / eqs. 26-30
                                  (T_WCk, T_WCf) by adjoint
================================  ===========================  =========================

Conventions
-----------
* Sim(3) ``T = (R, t, s)`` acts as ``X -> s R X + t`` (the ``fgslam.core.lie.Sim3`` contract). A pose
  argument is a ``fgslam.core.lie.Sim3``, any object with tensor attributes ``.R (...,3,3)``,
  ``.t (...,3)``, ``.s (...)``, or a tuple ``(R, t, s)`` of such tensors.
* Tangent ``xi = [w(3), u(3), lambda]`` in gtsam's ``Similarity3`` order, RIGHT perturbation:
  ``T (+) xi = T @ Exp(xi)``. Every Jacobian ``J`` is ``d r(T (+) xi) / d xi`` at ``xi = 0``.
* Shapes: poses have batch shape ``...`` (e.g. one per edge); points ``(..., N, 3)`` (N matches
  per pose); residuals ``(..., N, m)``; Jacobians ``(..., N, m, 7)``.
* Sign: residual = prediction minus measurement, ``h(T) - z``, like gtsam's
  ``NoiseModelFactor`` (the opposite sign ``z - h`` gives the same cost and Gauss-Newton step).
* Weights: ``weight (..., N) >= 0`` is the per-match information multiplier (the paper's
  confidence ``q`` in ``w(q, sigma^2)``); row ``i`` is whitened by
  ``sqrt_info = sqrt(weight) / sigma_i``. Robust (IRLS) weights belong to
  ``fgslam.factors.robust`` and are applied by the caller to :meth:`MatchResiduals.whitened`.
* Degenerate matches (non-finite inputs, zero-norm points, calibrated points at or behind the
  camera) are masked: residual, Jacobian and ``sqrt_info`` are exactly zero there, never NaN,
  and :attr:`MatchResiduals.num_masked` counts them.

Why log depth in the calibrated residual: the pointmaps' depth noise grows with depth and each
two-view prediction has its own arbitrary scale; ``log z`` makes the residual relative
(dimensionless), so one ``sigma_log_depth`` serves every scene scale just as ``sigma_pixel``
does for the pixel rows. The authors' released configuration likewise uses log depth.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.camera import project
from ..core.errors import DataError
from ..core.lie import Sim3
from .configs import RAY_DIST_ROWS, SIM3_DOF, PointmapResidualConfig  # torch-free (a run's config loads without torch)

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MatchResiduals:
    """Residuals of N matches with their Jacobians w.r.t. the relative pose ``T_CkCf``.

    r: ``(..., N, m)`` residual ``h(T) - z``, zero where masked.
    J: ``(..., N, m, 7)`` ``d r / d xi`` of ``T_CkCf (+) xi`` (right, gtsam order), zero where masked.
    sqrt_info: ``(..., N, m)`` per-row whitening ``sqrt(weight) / sigma``, zero where masked.
    valid: ``(..., N)`` bool, False for masked (degenerate) matches.
    """

    r: Tensor
    J: Tensor | None  # None when asked for the residuals alone (cost evaluations)
    sqrt_info: Tensor
    valid: Tensor

    @property
    def num_masked(self) -> int:
        """Number of masked (degenerate) matches."""
        return int((~self.valid).sum())

    def whitened(self) -> tuple[Tensor, Tensor | None]:
        """Whitened residuals ``(..., N, m)`` and Jacobians ``(..., N, m, 7)`` (None without Jacobians)."""
        return self.sqrt_info * self.r, None if self.J is None else self.sqrt_info[..., None] * self.J


def as_sim3(T) -> Sim3:
    """A checked ``Sim3`` from a ``Sim3``, an object with ``.R/.t/.s`` or a tuple ``(R, t, s)``.

    Raises ``DataError`` for non-finite entries or a non-positive scale (a broken state, not a
    degenerate measurement).
    """
    if isinstance(T, (tuple, list)):
        T = Sim3(*T)
    elif not isinstance(T, Sim3):
        T = Sim3(T.R, T.t, T.s)
    if not (torch.isfinite(T.R).all() and torch.isfinite(T.t).all() and torch.isfinite(T.s).all()):
        raise DataError("pointmap residual: the relative pose T_CkCf has non-finite entries")
    if not bool((T.s > 0).all()):
        raise DataError("pointmap residual: the relative pose T_CkCf has a non-positive scale")
    return T


def _per_match(T: Sim3) -> Sim3:
    """The pose batch ``...`` viewed as ``(..., 1)`` so that it broadcasts over the N matches."""
    return Sim3(T.R[..., None, :, :], T.t[..., None, :], T.s[..., None])


def _check_weight(weight: Tensor | None, like: Tensor) -> Tensor:
    """Per-match weights ``(..., N)`` (ones when None); negative weights are a caller error."""
    if weight is None:
        return torch.ones_like(like[..., 0])
    weight = torch.as_tensor(weight, dtype=like.dtype, device=like.device).expand(like.shape[:-1])
    if bool((weight < 0).any()):
        raise DataError("pointmap residual: match weights must be >= 0 (got a negative weight)")
    return weight


def _sanitise(X: Tensor, ok: Tensor) -> Tensor:
    """Replace masked points by the unit optical axis so no NaN/inf reaches the maths."""
    safe = torch.zeros_like(X)
    safe[..., 2] = 1.0
    return torch.where(ok[..., None], X, safe)


@dataclass(frozen=True)
class PreparedMatches:
    """What N matches' residuals need that does not depend on the pose (made once per edge by
    :func:`prepare_matches`, reused at every linearisation and cost evaluation).

    X_f / X_k: ``(..., N, 3)`` the canonical points, masked rows replaced by the optical axis;
    weight: ``(..., N)`` checked weights; valid: ``(..., N)`` finite inputs with ``||X_f||`` and
    ``||X_k||`` above ``min_norm``; sqrt_w: ``sqrt(weight)``, zero where not valid; psi_k / norm_k:
    ``psi(X_k)`` and ``||X_k||`` (rays of the sanitised points); min_norm: the threshold used.
    """

    X_f: Tensor
    X_k: Tensor
    weight: Tensor
    valid: Tensor
    sqrt_w: Tensor
    psi_k: Tensor
    norm_k: Tensor
    min_norm: float


def prepare_matches(X_f_in_f: Tensor, X_k_in_k: Tensor, weight: Tensor | None = None,
                    min_norm: float = 0.0) -> PreparedMatches:
    """The pose-free part of every residual here (:class:`PreparedMatches`). The mask covers
    non-finite inputs and zero-norm canonical points (``||X_f||`` or ``||X_k||`` <= ``min_norm``:
    MASt3R's invalid predictions); negative weights raise ``DataError``."""
    weight = _check_weight(weight, X_f_in_f)
    valid = (
        torch.isfinite(X_f_in_f).all(-1) & torch.isfinite(X_k_in_k).all(-1) & torch.isfinite(weight)
    )
    X_f = _sanitise(X_f_in_f, valid)
    X_k = _sanitise(X_k_in_k, valid)
    norm_k = torch.linalg.vector_norm(X_k, dim=-1)
    valid = valid & (torch.linalg.vector_norm(X_f, dim=-1) > min_norm) & (norm_k > min_norm)
    norm_k = torch.where(valid, norm_k, torch.ones((), dtype=norm_k.dtype, device=norm_k.device))
    psi_k = X_k / norm_k[..., None]
    sqrt_w = torch.sqrt(torch.where(valid, weight, torch.zeros((), dtype=weight.dtype, device=weight.device)))
    return PreparedMatches(X_f, X_k, weight, valid, sqrt_w, psi_k, norm_k, float(min_norm))


def _posed(T_CkCf, prep: PreparedMatches):
    """The checked pose and the predicted points ``Y = T X_f`` of prepared matches."""
    T = as_sim3(T_CkCf)
    return T, _per_match(T).act(prep.X_f)


def _chain(dr_dY: Tensor, T: Sim3) -> Tensor:
    """``A = dr/dY s R`` (``(..., N, m, 3)``, one batched matmul per pose)."""
    sR = T.s[..., None, None] * T.R
    return (dr_dY.flatten(-3, -2) @ sR).unflatten(-2, dr_dY.shape[-3:-1])


def _log_masked(valid: Tensor) -> None:
    num_masked = int((~valid).sum())
    if num_masked:
        logger.debug("pointmap residual: masked %d of %d matches", num_masked, valid.numel())


def _finish(
    r: Tensor,
    A: Tensor | None,
    X_f: Tensor,
    sigmas: Tensor,
    sqrt_w: Tensor,
    valid: Tensor,
) -> MatchResiduals:
    """Chain rule, whitening, and zeroing of the masked matches (NaN there is dropped); ``A`` is
    ``dr/dY s R`` (:func:`_chain`), None for a cost evaluation (``J`` is None then).

    ``J = dr/dY s R [-[X_f]x, I, X_f]`` in fused form: with the rows ``a^T`` of ``A``,
    ``J`` rows are ``[X_f x a, a, a . X_f]`` (since ``a^T (-[X]x) = (X x a)^T``).
    """
    zero = torch.zeros((), dtype=r.dtype, device=r.device)
    J = None
    if A is not None:
        X = X_f[..., None, :].expand_as(A)
        J = torch.cat((torch.linalg.cross(X, A, dim=-1), A, (A * X).sum(-1, keepdim=True)), dim=-1)
        J = torch.where(valid[..., None, None], J, zero)
    r = torch.where(valid[..., None], r, zero)
    sqrt_info = torch.where(valid, sqrt_w, zero)[..., None] / sigmas
    if logger.isEnabledFor(logging.DEBUG):
        _log_masked(valid)
    return MatchResiduals(r=r, J=J, sqrt_info=sqrt_info, valid=valid)


def point_residuals(
    T_CkCf,
    X_f_in_f: Tensor,
    X_k_in_k: Tensor,
    weight: Tensor | None = None,
    config: PointmapResidualConfig | None = None,
    jacobians: bool = True,
) -> MatchResiduals:
    """3-D point residual ``r = T_CkCf X_f_in_f - X_k_in_k`` (m = 3; paper eqs. 6, 14-15).

    Jacobian ``J = s R [-[X_f]x, I, X_f]`` w.r.t. the right perturbation of ``T_CkCf``.
    Masked: non-finite inputs, ``||X_f||`` or ``||X_k||`` <= ``min_norm``. Rows whitened by
    ``sqrt(weight) / sigma_point``.
    """
    cfg = config or PointmapResidualConfig()
    prep = prepare_matches(X_f_in_f, X_k_in_k, weight, cfg.min_norm)
    T, Y = _posed(T_CkCf, prep)
    A = None
    if jacobians:
        A = (T.s[..., None, None] * T.R)[..., None, :, :].expand(*Y.shape[:-1], 3, 3)
    sigmas = Y.new_tensor([cfg.sigma_point] * 3)
    return _finish(Y - prep.X_k, A, prep.X_f, sigmas, prep.sqrt_w, prep.valid)


def ray_dist_residuals(
    T_CkCf,
    X_f_in_f: Tensor,
    X_k_in_k: Tensor,
    weight: Tensor | None = None,
    config: PointmapResidualConfig | None = None,
    jacobians: bool = True,
) -> MatchResiduals:
    """Ray and distance residuals of the generic central camera (m = 4; eqs. 7, 10, 16-22).

    With ``Y = T_CkCf X_f_in_f`` and ``psi(X) = X / ||X||`` (``fgslam.core.camera.normalize_rays``):
    rows 0-2: ``psi(Y) - psi(X_k_in_k)``, ``d psi/dY = (I - psi psi^T) / ||Y||``;
    row 3: ``||Y|| - ||X_k_in_k||``, ``d||Y||/dY = psi(Y)^T``;
    chained with ``dY/dxi = s R [-[X_f]x, I, X_f]``.

    The ray rows are invariant to a uniform scaling of the relative pose (left perturbation
    ``Exp([0, 0, lambda]) T_CkCf``, i.e. the right tangent ``Ad(T_CkCf^-1) e_lambda``), so
    their Jacobian along that direction is zero; the distance row's is ``||Y||``. The right
    tangent's own ``lambda`` column of the ray rows vanishes only when ``t = 0``.

    Masked: non-finite inputs, ``||X_f||``, ``||X_k||`` or ``||Y||`` <= ``min_norm``.
    Whitening: ``sqrt(weight) / sigma_ray`` (rows 0-2), ``sqrt(weight) / sigma_dist`` (row 3).
    """
    cfg = config or PointmapResidualConfig()
    return ray_dist_prepared(T_CkCf, prepare_matches(X_f_in_f, X_k_in_k, weight, cfg.min_norm), cfg, jacobians)


def ray_dist_prepared(T_CkCf, prep: PreparedMatches, config: PointmapResidualConfig | None = None,
                      jacobians: bool = True) -> MatchResiduals:
    """:func:`ray_dist_residuals` of :func:`prepare_matches`' output (blocks prepare each edge once): the
    compiled kernel :func:`fgslam.factors.pointmap_jit.ray_dist_rows` is the one implementation, in
    float64 on the CPU (the results are cast back to the points' dtype; no autograd: tensors that
    require gradients or live on another device are refused). ``A = dr/dY s R`` in closed form: ray
    rows ``(sR - psi (psi^T sR)) / ||Y||``, distance row ``psi^T sR``."""
    from .pointmap_jit import ray_dist_rows  # deferred: numba (compiled kernel, core/jit.py)

    cfg = config or PointmapResidualConfig()
    T = as_sim3(T_CkCf)
    inputs = (T.R, T.t, T.s, prep.X_f, prep.psi_k)
    if any(x.requires_grad or x.device.type != "cpu" for x in inputs):
        raise DataError("ray residual: the compiled kernel takes CPU tensors without gradients")
    dtype = prep.X_f.dtype
    batch = tuple(torch.broadcast_shapes(T.shape, prep.X_f.shape[:-2]))
    n = int(prep.X_f.shape[-2])
    rows = math.prod(batch)

    def flat(x: Tensor, tail: tuple[int, ...]):
        return x.expand(batch + tail).reshape((rows,) + tail).to(torch.float64).contiguous().numpy()

    r, J, sqrt_info, valid = ray_dist_rows(
        flat(T.R, (3, 3)), flat(T.t, (3,)), flat(T.s, ()), flat(prep.X_f, (n, 3)), flat(prep.psi_k, (n, 3)),
        flat(prep.norm_k, (n,)), flat(prep.sqrt_w, (n,)), prep.valid.expand(batch + (n,)).reshape(rows, n).contiguous().numpy(),
        float(prep.min_norm), float(cfg.sigma_ray), float(cfg.sigma_dist), bool(jacobians))
    valid_t = torch.from_numpy(valid).reshape(batch + (n,))
    if logger.isEnabledFor(logging.DEBUG):
        _log_masked(valid_t)
    return MatchResiduals(
        r=torch.from_numpy(r).reshape(batch + (n, RAY_DIST_ROWS)).to(dtype),
        J=torch.from_numpy(J).reshape(batch + (n, RAY_DIST_ROWS, SIM3_DOF)).to(dtype) if jacobians else None,
        sqrt_info=torch.from_numpy(sqrt_info).reshape(batch + (n, RAY_DIST_ROWS)).to(dtype), valid=valid_t)


def calibrated_residuals(
    T_CkCf,
    X_f_in_f: Tensor,
    X_k_in_k: Tensor,
    uv_k: Tensor,
    K: Tensor,
    weight: Tensor | None = None,
    config: PointmapResidualConfig | None = None,
    jacobians: bool = True,
) -> MatchResiduals:
    """Calibrated pixel + log-depth residuals (m = 3; paper eqs. 11, 23-25).

    With ``Y = T_CkCf X_f_in_f`` and the pinhole ``pi`` of ``K = [fx, fy, cx, cy]`` (shape
    ``(4,)`` or the pose batch ``(..., 4)``; ``fgslam.core.camera.project``):
    rows 0-1: ``pi(Y) - uv_k`` where ``uv_k (..., N, 2)`` is the matched pixel in keyframe k;
    row 2: ``log z(Y) - log z(X_k_in_k)``.
    ``d pi/dY = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]``, ``d log z/dY = [0, 0, 1/z]``.

    Masked: non-finite inputs, ``||X_f||`` or ``||X_k||`` <= ``min_norm``, and points at or
    behind the camera (``z(Y)`` or ``z(X_k)`` <= ``min_depth``). Whitening:
    ``sqrt(weight) / sigma_pixel`` (rows 0-1), ``sqrt(weight) / sigma_log_depth`` (row 2).
    """
    cfg = config or PointmapResidualConfig()
    return calibrated_prepared(T_CkCf, prepare_matches(X_f_in_f, X_k_in_k, weight, cfg.min_norm), uv_k, K, cfg,
                               jacobians)


def calibrated_prepared(T_CkCf, prep: PreparedMatches, uv_k: Tensor, K: Tensor,
                        config: PointmapResidualConfig | None = None, jacobians: bool = True) -> MatchResiduals:
    """:func:`calibrated_residuals` of :func:`prepare_matches`' output (the one implementation)."""
    cfg = config or PointmapResidualConfig()
    K = torch.as_tensor(K, dtype=prep.X_f.dtype, device=prep.X_f.device)
    if K.shape[-1] != 4:
        raise DataError(f"calibrated residual: K must be [fx, fy, cx, cy], got shape {tuple(K.shape)}")
    uv_ok = torch.isfinite(uv_k).all(-1)
    T, Y = _posed(T_CkCf, prep)
    X_k = prep.X_k
    uv_Y, duv_dY, valid_Y = project(Y, K[..., None, :], cfg.min_depth)
    z_Y = torch.where(valid_Y, Y[..., 2], torch.ones_like(Y[..., 2]))
    z_k = X_k[..., 2]
    valid = prep.valid & uv_ok & valid_Y & (z_k > cfg.min_depth)
    z_k = torch.where(valid, z_k, torch.ones_like(z_k))
    uv_k = torch.where(uv_ok[..., None], uv_k, torch.zeros_like(uv_k))
    r = torch.cat((uv_Y - uv_k, torch.log(z_Y / z_k)[..., None]), dim=-1)
    A = None
    if jacobians:
        dlogz_dY = torch.zeros_like(Y)
        dlogz_dY[..., 2] = 1.0 / z_Y
        A = _chain(torch.cat((duv_dY, dlogz_dY[..., None, :]), dim=-2), T)
    sigmas = Y.new_tensor([cfg.sigma_pixel] * 2 + [cfg.sigma_log_depth])
    return _finish(r, A, prep.X_f, sigmas, prep.sqrt_w, valid)


def relative_to_global(J_CkCf: Tensor, T_CkCf) -> tuple[Tensor, Tensor]:
    """Chain rule from the relative pose to the two global poses (paper eqs. 10, 26-30).

    ``T_CkCf = T_WCk^-1 T_WCf``. With right perturbations of the global poses,
    ``T_WCf Exp(xi_f)`` gives ``T_CkCf Exp(xi_f)`` and ``T_WCk Exp(xi_k)`` gives
    ``Exp(-xi_k) T_CkCf = T_CkCf Exp(-Ad(T_CkCf^-1) xi_k)``, so::

        J_WCk = -J_CkCf Ad(T_CkCf^-1),    J_WCf = J_CkCf.

    J_CkCf: ``(..., N, m, 7)`` Jacobian of any residual w.r.t. the right perturbation of
    ``T_CkCf`` (pose batch shape ``...``). Returns ``(J_WCk, J_WCf)``, both ``(..., N, m, 7)``;
    ``J_WCf`` is ``J_CkCf`` itself (not a copy).
    """
    Ad_inv = as_sim3(T_CkCf).inverse().adjoint()
    J_WCk = -(J_CkCf.flatten(-3, -2) @ Ad_inv).unflatten(-2, J_CkCf.shape[-3:-1])
    return J_WCk, J_CkCf


def relative_to_global_normal(H_CkCf: Tensor, g_CkCf: Tensor, T_CkCf) -> tuple[Tensor, Tensor]:
    """:func:`relative_to_global` applied to the normal equations of one edge: from ``H = J^T W J``
    ``(7, 7)`` and ``g = J^T W e`` ``(7,)`` over the relative pose to ``(14, 14)`` / ``(14,)`` over
    ``(T_WCk, T_WCf)``. With ``B = Ad(T_CkCf^-1)``, ``J_WCk = -J B`` and ``J_WCf = J``::

        H = [[B^T H B, -B^T H], [-H B, H]],   g = [-B^T g, g]

    exactly what summing ``[J_WCk, J_WCf]^T W [J_WCk, J_WCf]`` over the matches gives, at the cost of
    one 7-column reduction (the batched linearisation of the pointmap blocks)."""
    B = as_sim3(T_CkCf).inverse().adjoint()
    HB = H_CkCf @ B
    top = torch.cat((B.T @ HB, -(B.T @ H_CkCf)), -1)
    bottom = torch.cat((-HB, H_CkCf), -1)
    return torch.cat((top, bottom), -2), torch.cat((-(B.T @ g_CkCf), g_CkCf))
