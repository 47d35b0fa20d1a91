"""Frame-to-keyframe tracking of the pointmap frontend (MASt3R-SLAM section 3.3), and pointmap fusion (eq. 9).

:func:`track_pose` estimates the relative pose ``T_CkCf`` of a frame f to its keyframe k from N matches
(the frame's own points ``X_f^f`` at the query pixels, the keyframe's canonical points ``X_k^k`` at the
matched pixels) by Gauss-Newton with iteratively reweighted least squares:

- residuals of :mod:`fgslam.factors.pointmap` (one implementation each): ``ray`` mode, the unit-ray rows
  and the weak distance row (eqs. 7-8; the distance row keeps a pure rotation well posed), or
  ``calibrated`` mode (section 3.7), pixel rows and the log-depth row;
- every row group whitened by ``sqrt(q) / sigma`` with the match confidence ``q`` (eq. 6) and weighted
  by the robust kernel (Huber) of its whitened norm (:mod:`fgslam.factors.robust`), as the backend's
  :class:`~fgslam.factors.pointmap_block.PointmapBlock` does for the same residuals;
- Sim(3) (7 dof) or, for metric pointmaps, SE(3) (the scale column dropped).

:func:`fuse_pointmap` is eq. 9: the keyframe's canonical pointmap becomes the confidence-weighted
running average of its own points and the tracked frame's points moved into it (``T_CkCf X_f^f``) at the
matched pixels (several queries matched to one pixel all count).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from ...factors.pointmap import calibrated_residuals, ray_dist_residuals
from ...factors.pointmap_block import PointmapBlockConfig
from ...factors.robust import kernel_cost, kernel_weight
from ...lie import Sim3
from .config import TrackingConfig

logger = logging.getLogger(__name__)

__all__ = ["TrackResult", "fuse_pointmap", "track_pose"]

# row groups of each residual mode: (ray 3-vector, distance) / (pixel 2-vector, log depth)
GROUPS = {"ray": ((0, 3), (3, 4)), "calibrated": ((0, 2), (2, 3))}


@dataclass
class TrackResult:
    """Outcome of :func:`track_pose`: the relative pose, per-match inlier flags (the whitened norm of the
    ray / pixel rows at most ``tracking.inlier_threshold``), the cost ``sum rho`` before and after, the iterations run and whether the step
    fell below the tolerance."""

    T_CkCf: Sim3
    inlier: torch.Tensor
    initial_cost: float
    final_cost: float
    iterations: int
    converged: bool

    @property
    def num_inliers(self) -> int:
        return int(self.inlier.sum())


def _terms(T: Sim3, X_f, X_k, weight, uv_k, K, block: PointmapBlockConfig):
    if block.mode == "ray":
        res = ray_dist_residuals(T, X_f, X_k, weight, block.residual)
    else:
        res = calibrated_residuals(T, X_f, X_k, uv_k, K, weight, block.residual)
    e, J = res.whitened()
    norms = torch.stack([torch.linalg.vector_norm(e[:, a:b], dim=-1) for a, b in GROUPS[block.mode]], -1)
    return e, J, norms, res.valid


def track_pose(T_init: Sim3, X_f_in_f: torch.Tensor, X_k_in_k: torch.Tensor, weight: torch.Tensor,
               block: PointmapBlockConfig, config: TrackingConfig, fixed_scale: bool,
               uv_k: torch.Tensor | None = None, K: torch.Tensor | None = None) -> TrackResult:
    """``T_CkCf`` from N matches (module docstring). ``X_f_in_f`` / ``X_k_in_k`` ``(N, 3)``, ``weight``
    ``(N,)`` match confidences q, ``uv_k`` ``(N, 2)`` matched keyframe pixels and ``K`` ``(4,)`` for the
    calibrated mode; all float64. ``fixed_scale``: SE(3) (the scale of ``T_init`` is kept)."""
    rb = block.robust
    n = 6 if fixed_scale else 7
    T = T_init
    initial = final = float("nan")
    converged = False
    it = 0
    for it in range(1, config.iterations + 1):
        e, J, norms, valid = _terms(T, X_f_in_f, X_k_in_k, weight, uv_k, K, block)
        cost = float(kernel_cost(norms, rb.kind, rb.delta).sum())
        if it == 1:
            initial = cost
        w = kernel_weight(norms, rb.kind, rb.delta)
        row_w = torch.cat([w[:, g:g + 1].expand(-1, b - a) for g, (a, b) in enumerate(GROUPS[block.mode])], -1)
        Jr = J.reshape(-1, 7)[:, :n]
        wr = row_w.reshape(-1)
        H = Jr.T @ (wr[:, None] * Jr)
        g = Jr.T @ (wr * e.reshape(-1))
        diag = torch.diagonal(H)
        H = H + torch.diag(config.damping * diag + 1e-12 * diag.max().clamp_min(1.0))  # Marquardt: scale-invariant
        try:
            delta = -torch.linalg.solve(H, g)
        except RuntimeError:  # singular (no valid match): no step
            logger.debug("pointmap tracking: singular system at iteration %d", it)
            break
        if not bool(torch.isfinite(delta).all()):
            break
        xi = torch.zeros(7, dtype=delta.dtype)
        xi[:n] = delta
        T = T.retract(xi)
        if float(delta.abs().max()) < config.step_tolerance:
            converged = True
            break
    e, J, norms, valid = _terms(T, X_f_in_f, X_k_in_k, weight, uv_k, K, block)
    final = float(kernel_cost(norms, rb.kind, rb.delta).sum())
    if it == 0 or initial != initial:
        initial = final
    inlier = valid & (weight > 0) & (norms[:, 0] <= config.inlier_threshold)
    return TrackResult(T, inlier, initial, final, it, converged)


def fuse_pointmap(X_canon: torch.Tensor, C_canon: torch.Tensor, index: torch.Tensor, X_new: torch.Tensor,
                  C_new: torch.Tensor, max_confidence: float) -> None:
    """Eq. 9 in place: ``X <- (C X + sum c x) / (C + sum c)``, ``C <- min(C + sum c, max_confidence)`` at the
    flat pixel ``index (M,)`` of ``X_canon (H W, 3)`` / ``C_canon (H W,)`` (float32 views of the keyframe's
    canonical pointmap), with the new points ``X_new (M, 3)`` (in the keyframe's frame) and confidences
    ``C_new (M,)``; non-finite new points are skipped."""
    ok = torch.isfinite(X_new).all(-1) & torch.isfinite(C_new) & (C_new > 0)
    index, X_new, C_new = index[ok], X_new[ok].to(X_canon.dtype), C_new[ok].to(C_canon.dtype)
    if index.numel() == 0:
        return
    num = torch.zeros_like(X_canon).index_add_(0, index, C_new[:, None] * X_new)
    den = torch.zeros_like(C_canon).index_add_(0, index, C_new)
    hit = den > 0
    total = C_canon[hit] + den[hit]
    X_canon[hit] = (C_canon[hit, None] * X_canon[hit] + num[hit]) / total[:, None]
    C_canon[hit] = total.clamp(max=max_confidence)
