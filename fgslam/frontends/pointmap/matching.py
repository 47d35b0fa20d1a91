"""Iterative projective matching of two pointmaps (MASt3R-SLAM section 3.2, eqs. 2-4), vectorised.

Given the reference pointmap ``X_i^i`` (keyframe i, its own frame) and a query pointmap ``X_j^i``
(frame j's pixels predicted in frame i), every query pixel q looks for the pixel p of i whose ray is
closest to its own::

    p*(q) = argmin_p || psi([X_i^i]_p) - psi([X_j^i]_q) ||^2        psi(X) = X / ||X||   (eqs. 2-3)

solved per pixel by Levenberg-Marquardt over the continuous pixel coordinates of the *ray image*
``psi(X_i^i)`` (bilinear; the Jacobian is the exact derivative of the bilinear interpolant), at most
``max_iterations`` steps, started from the previous matches (warm start, e.g. the last frame's matches
to the same keyframe) or from the identity ``p = q``. Each pixel keeps its own damping (Marquardt:
``lambda diag(J^T J)``), lowered after a step that reduced its ray error and raised otherwise
(eq. 4). Matches are then invalidated where

- the query point or the ray image at the solution is missing (zero confidence / no point);
- the two points are far apart in 3-D: ``||[X_i^i]_p - [X_j^i]_q|| > max_distance ||[X_j^i]_q||``
  (occlusions: the ray hits the occluder, whose point is elsewhere); relative, because every
  two-view prediction has its own scale;
- the final ray error stays above ``max_ray_error`` (the ray leaves the reference image).

Finally the integer match is refined by the descriptors: the best dot product ``D_j[q] . D_i[p']``
within a ``(2r+1)^2`` window around the rounded solution, once per dilation in ``refine_dilations``
(coarse to fine; MASt3R-SLAM's feature refinement).

Shapes: the reference ``(H, W, ...)``; queries ``(N, 3)`` (any pixel set, e.g. all ``H2 x W2`` pixels of
j, flattened row-major). Float32 throughout (pixel precision needs no more).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ...core.config import MAX_IMAGE_SIDE, MAX_ITERATIONS, MAX_LAMBDA, MAX_SCALAR, MAX_THREADS, ranged
from ...core.errors import DataError
from ...factors.schur import torch_threads

logger = logging.getLogger(__name__)

__all__ = ["MatchingConfig", "PointmapMatches", "RayImage", "match_pointmaps", "pixel_grid_uv"]


@dataclass
class MatchingConfig:
    """Iterative projective matching and descriptor refinement (defaults: MASt3R-SLAM's where it has one)."""

    max_iterations: int = ranged(10, ge=1, le=MAX_ITERATIONS)  # LM iterations per pixel (paper: 10)
    lambda_initial: float = ranged(1e-3, gt=0, le=MAX_LAMBDA)  # per-pixel Marquardt damping at the start
    lambda_factor: float = ranged(10.0, gt=1, le=MAX_SCALAR)  # damping divided by this after a good step, multiplied after a bad one
    step_tolerance: float = ranged(1e-3, ge=0, le=MAX_SCALAR)  # px: a pixel whose step is below this has converged
    max_distance: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # matched points further apart than this times the query's norm are invalid
    max_ray_error: float = ranged(0.02, gt=0, le=MAX_SCALAR)  # final unit-ray error (~rad) above this: invalid (ray left the image)
    refine_radius: int = ranged(1, ge=0, le=MAX_IMAGE_SIDE)  # px: descriptor search window radius around the LM solution (0: no refinement)
    refine_dilations: list[int] = ranged(default_factory=lambda: [4, 2, 1], ge=1, le=MAX_IMAGE_SIDE)  # window spacings, coarse to fine
    # (radius 1 at spacings 4, 2, 1 reaches 7 px with 27 candidates: measured in tools/bench_pointmap.py)
    compile: bool = False  # fuse the LM step and the refinement with torch.compile (needs a C++ compiler;
    # compiles once per process, ~25 s under load; measured 2.5x less CPU per match: tools/bench_pointmap.py --compile)
    threads: int = ranged(1, ge=0, le=MAX_THREADS)  # torch intra-op threads while matching (0: torch's setting); 1: measured
    # 10x faster than 2 threads on the loaded 2-core machine (tools/bench_pointmap.py)


@dataclass
class PointmapMatches:
    """Matches of N query pixels into the reference image.

    uv: ``(N, 2)`` float32 matched pixel ``(u, v)`` of the reference (integers; refined where valid:
    the descriptor refinement runs only on the queries that passed the LM's checks);
    uv_lm: ``(N, 2)`` the continuous LM solution before refinement (the warm start of the next call);
    index: ``(N,)`` int64 flat index ``v * W + u`` of ``uv`` in the reference;
    valid: ``(N,)`` bool; ray_error: ``(N,)`` final ray error of the LM solution (inf for the queries
    without a ray: non-finite or zero points; their ``uv_lm`` is their start);
    score: ``(N,)`` descriptor dot product at ``uv`` (NaN without descriptors).
    """

    uv: Tensor
    uv_lm: Tensor
    index: Tensor
    valid: Tensor
    ray_error: Tensor
    score: Tensor

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.float().mean()) if self.valid.numel() else 0.0


def pixel_grid_uv(H: int, W: int) -> Tensor:
    """``(H W, 2)`` float32 pixel coordinates ``(u, v)`` of an ``H x W`` image, row-major."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    return torch.stack((u, v), -1).reshape(-1, 2)


def _points(X, name: str) -> Tensor:
    X = torch.as_tensor(np.asarray(X) if not isinstance(X, Tensor) else X).to(torch.float32)
    if X.shape[-1] != 3:
        raise DataError(f"pointmap matching: {name} must have 3 coordinates per pixel, got shape {tuple(X.shape)}")
    return X


class RayImage:
    """The reference side of matching, computed once per reference pointmap (a keyframe) and reused:
    unit rays ``(H W, 3)``, points ``(H W, 3)`` and validity, channel-last for gathers.

    X_i_in_i: ``(H, W, 3)`` pointmap; confidence: ``(H, W)`` or None; pixels with a non-finite point,
    a zero-norm point or a confidence at or below ``min_confidence`` have a zero ray (never matched).
    """

    def __init__(self, X_i_in_i, confidence=None, min_confidence: float = 0.0):
        X = _points(X_i_in_i, "X_i_in_i")
        if X.ndim != 3 or X.shape[0] < 2 or X.shape[1] < 2:
            raise DataError(f"pointmap matching: the reference pointmap must be (H, W, 3), H, W >= 2; got {tuple(X.shape)}")
        self.H, self.W = int(X.shape[0]), int(X.shape[1])
        ok = torch.isfinite(X.sum(-1))
        if confidence is not None:
            C = torch.as_tensor(np.asarray(confidence) if not isinstance(confidence, Tensor) else confidence)
            ok &= torch.isfinite(C) & (C > min_confidence)
        X = torch.where(ok[..., None], X, torch.zeros((), dtype=X.dtype))
        norm = torch.linalg.vector_norm(X, dim=-1, keepdim=True)
        ok &= norm[..., 0] > 0
        self.valid = ok.reshape(-1)
        rays = torch.where(ok[..., None], X / norm.clamp_min(1e-30), torch.zeros((), dtype=X.dtype))
        self.rays = rays.reshape(-1, 3).T.contiguous()  # (3, H W): channel rows for index_select
        self.points = X.reshape(-1, 3).contiguous()

    def sample(self, u: Tensor, v: Tensor):
        """Bilinear ray ``(3, N)`` at pixels ``(u, v)`` (each ``(N,)``, inside the image) and its
        derivatives along u and v (``(3, N)`` each)."""
        return _sample(self.rays, self.W, u, v)


def _sample(rays: Tensor, W: int, u: Tensor, v: Tensor):
    """Bilinear ray image ``rays (3, H W)`` at ``(u, v)`` and its exact derivatives: one gather of the
    four corners."""
    H = rays.shape[1] // W
    u0 = u.floor().clamp_(max=W - 2)
    v0 = v.floor().clamp_(max=H - 2)
    fu = u - u0
    fv = v - v0
    idx = (v0 * W + u0).to(torch.int64)
    corners = rays.index_select(1, torch.cat((idx, idx + 1, idx + W, idx + W + 1)))
    c00, c01, c10, c11 = corners.view(3, 4, -1).unbind(1)
    d_top = c01 - c00
    d_bottom = c11 - c10
    top = c00 + fu * d_top
    dv = (c10 + fu * d_bottom) - top
    ray = top + fv * dv
    du = d_top + fv * (d_bottom - d_top)
    return ray, du, dv


def _rays(X: Tensor) -> tuple[Tensor, Tensor]:
    ok = torch.isfinite(X.sum(-1))  # (a NaN or inf coordinate makes the sum non-finite; 10x faster than all(-1))
    X = torch.where(ok[:, None], X, torch.zeros((), dtype=X.dtype))
    norm = torch.linalg.vector_norm(X, dim=-1, keepdim=True)
    ok &= norm[:, 0] > 0
    return (X / norm.clamp_min(1e-30)).T.contiguous(), ok


def _lm_step(rays: Tensor, W: int, u: Tensor, v: Tensor, r: Tensor, du: Tensor, dv: Tensor, cost: Tensor,
             lam: Tensor, tgt: Tensor, lambda_factor: float, step_tolerance: float):
    """One damped Gauss-Newton step per pixel, kept where it lowers the ray error (else more damping)."""
    W1, H1 = float(W - 1), float(rays.shape[1] // W - 1)
    a = (du * du).sum(0)
    b = (du * dv).sum(0)
    c = (dv * dv).sum(0)
    gu = (du * r).sum(0)
    gv = (dv * r).sum(0)
    damp = 1 + lam
    a_d = a * damp + 1e-12
    c_d = c * damp + 1e-12
    inv_det = 1.0 / (a_d * c_d - b * b).clamp(min=1e-30)  # >= 0 up to rounding (Cauchy-Schwarz)
    # a degenerate step (flat or missing ray image: 0 * inf) is no step
    new_u = (u + torch.nan_to_num((b * gv - c_d * gu) * inv_det, 0.0, 0.0, 0.0)).clamp(0, W1)
    new_v = (v + torch.nan_to_num((b * gu - a_d * gv) * inv_det, 0.0, 0.0, 0.0)).clamp(0, H1)
    moving = torch.maximum((new_u - u).abs(), (new_v - v).abs()) > step_tolerance
    new_ray, new_du, new_dv = _sample(rays, W, new_u, new_v)
    new_r = new_ray - tgt
    new_cost = (new_r * new_r).sum(0)
    better = new_cost < cost
    return (torch.where(better, new_u, u), torch.where(better, new_v, v), torch.where(better, new_r, r),
            torch.where(better, new_du, du), torch.where(better, new_dv, dv), torch.where(better, new_cost, cost),
            torch.where(better, lam / lambda_factor, lam * lambda_factor), moving)


_KERNELS: dict[str, object] = {}  # torch.compile'd kernels, made on first use ("failed": compilation unavailable)


def _call(name: str, compiled: bool, *args):
    """Run kernel ``name`` (``lm_step`` or ``refine_all``) eagerly, or compiled once per process by
    ``torch.compile`` (fused loops); when compilation fails (no C++ compiler, unsupported platform) it
    warns once and every later call runs eagerly."""
    eager = {"lm_step": _lm_step, "refine_all": _refine_all}[name]
    if not compiled or _KERNELS.get("failed"):
        return eager(*args)
    fn = _KERNELS.get(name)
    if fn is None:
        fn = _KERNELS[name] = torch.compile(eager, dynamic=True)
    try:
        return fn(*args)
    except Exception as exc:  # noqa: BLE001 - any compiler failure: the eager kernel computes the same
        logger.warning("pointmap matching: torch.compile failed (%s: %s); matching runs eagerly",
                       type(exc).__name__, exc)
        _KERNELS["failed"] = True
        return eager(*args)


def _lm(ref: RayImage, target: Tensor, uv: Tensor, cfg: MatchingConfig) -> tuple[Tensor, Tensor]:
    """Per-pixel LM on ``|ray_i(uv) - target|^2`` (``target (3, N)``, ``uv (N, 2)`` inside the image);
    returns the solution ``(N, 2)`` and its squared ray error. Converged pixels leave the active set
    (most do after a step or two when warm started), so later iterations cost only what still moves."""
    u_all, v_all = uv[:, 0].contiguous(), uv[:, 1].contiguous()
    ray, du, dv = ref.sample(u_all, v_all)
    r = ray - target
    cost_all = (r * r).sum(0)
    u, v, cost, tgt = u_all, v_all, cost_all, target
    lam = torch.full_like(u, cfg.lambda_initial)
    active = None  # None: every pixel
    for it in range(cfg.max_iterations):
        u, v, r, du, dv, cost, lam, moving = _call("lm_step", cfg.compile, ref.rays, ref.W, u, v, r, du, dv, cost,
                                                   lam, tgt, cfg.lambda_factor, cfg.step_tolerance)
        if active is None:
            u_all, v_all, cost_all = u, v, cost
        else:
            u_all[active] = u
            v_all[active] = v
            cost_all[active] = cost
        if it + 1 == cfg.max_iterations:
            break
        keep = moving.nonzero().squeeze(1)
        if keep.numel() == 0:
            break
        if 2 * keep.numel() <= u.numel():  # compact when half has converged (indexing costs as much as a step)
            if active is None:
                u_all, v_all, cost_all = u_all.clone(), v_all.clone(), cost_all.clone()
                active = keep
            else:
                active = active[keep]
            u, v, cost, lam = u[keep], v[keep], cost[keep], lam[keep]
            r, du, dv, tgt = r[:, keep], du[:, keep], dv[:, keep], tgt[:, keep]
    return torch.stack((u_all, v_all), -1), cost_all


def _refine(index: Tensor, D_i: Tensor, D_j: Tensor, H: int, W: int, radius: int, dilation: int) -> tuple[Tensor, Tensor]:
    """Best descriptor match within the ``(2 radius + 1)^2`` window (spacing ``dilation``) around each flat
    reference index, one candidate offset at a time over all queries (measured: gathering every
    candidate at once is 2-3x slower, memory bound). ``D_i (H W, d)``, ``D_j (N, d)``."""
    u0 = index % W
    v0 = index // W
    best = torch.full((index.shape[0],), -torch.inf, dtype=D_i.dtype)
    best_index = index.clone()
    for dy in range(-radius, radius + 1):
        row = (v0 + dy * dilation).clamp_(0, H - 1).mul_(W)
        for dx in range(-radius, radius + 1):
            cand = (u0 + dx * dilation).clamp_(0, W - 1).add_(row)
            score = torch.einsum("nd,nd->n", D_i.index_select(0, cand), D_j)
            better = score > best
            best = torch.where(better, score, best)
            best_index = torch.where(better, cand, best_index)
    return best_index, best


def _refine_all(index: Tensor, D_i: Tensor, D_j: Tensor, H: int, W: int, radius: int,
                dilations: tuple[int, ...]) -> tuple[Tensor, Tensor]:
    score = torch.full((index.shape[0],), float("nan"))
    for dilation in dilations:
        index, score = _refine(index, D_i, D_j, H, W, radius, dilation)
    return index, score


def match_pointmaps(
    reference: RayImage,
    X_j_in_i,
    init_uv=None,
    D_i=None,
    D_j=None,
    query_valid=None,
    config: MatchingConfig | None = None,
) -> PointmapMatches:
    """Match query points ``X_j_in_i (N, 3)`` (or ``(H2, W2, 3)``) into ``reference`` (module docstring).

    init_uv: ``(N, 2)`` warm start in reference pixels (non-finite rows fall back to the identity);
    None: the identity ``p = q``, which needs the query to be the reference's own pixel grid
    (``N = H W``). D_i ``(H, W, d)`` / D_j ``(N, d)``: descriptors for the refinement (None: none).
    query_valid: ``(N,)`` bool, queries to leave unmatched (e.g. zero confidence).
    """
    cfg = config or MatchingConfig()
    with torch_threads(cfg.threads), torch.no_grad():
        X = _points(X_j_in_i, "X_j_in_i").reshape(-1, 3)
        N = X.shape[0]
        H, W = reference.H, reference.W
        target, ok = _rays(X)
        has_ray = ok.clone()  # the LM runs on these (a query_valid False one may still serve as a warm start)
        if query_valid is not None:
            ok &= torch.as_tensor(np.asarray(query_valid) if not isinstance(query_valid, Tensor) else query_valid,
                                  dtype=torch.bool).reshape(-1)
        identity = pixel_grid_uv(H, W) if N == H * W else None
        if init_uv is None:
            if identity is None:
                raise DataError(f"pointmap matching: {N} queries without init_uv need the reference's {W}x{H} pixel grid")
            uv = identity.clone()
        else:
            uv = torch.as_tensor(np.asarray(init_uv) if not isinstance(init_uv, Tensor) else init_uv,
                                 dtype=torch.float32).reshape(N, 2).clone()
            bad = ~torch.isfinite(uv).all(-1)
            if bool(bad.any()):
                if identity is None:
                    uv[bad] = torch.tensor([(W - 1) / 2, (H - 1) / 2])
                else:
                    uv[bad] = identity[bad]
        uv[:, 0].clamp_(0, W - 1)
        uv[:, 1].clamp_(0, H - 1)
        # LM only on the queries with a ray (non-finite or zero points keep their start and an infinite
        # ray error: nothing to match)
        act = has_ray.nonzero().squeeze(1)
        if act.numel() == N:
            uv_lm, cost = _lm(reference, target, uv, cfg)
        else:
            uv_act, cost_act = _lm(reference, target[:, act], uv[act], cfg)
            uv_lm = uv.index_put((act,), uv_act)
            cost = torch.full((N,), torch.inf).index_put((act,), cost_act)
        ray_error = cost.sqrt()
        index = uv_lm.round().to(torch.int64)
        index = index[:, 1] * W + index[:, 0]
        X_ref = reference.points[index]
        dist = torch.linalg.vector_norm(X_ref - torch.where(ok[:, None], X, torch.zeros((), dtype=X.dtype)), dim=-1)
        norm = torch.linalg.vector_norm(torch.where(ok[:, None], X, torch.zeros((), dtype=X.dtype)), dim=-1)
        valid = (ok & reference.valid[index] & (dist <= cfg.max_distance * norm)
                 & (ray_error <= cfg.max_ray_error))
        score = torch.full((N,), float("nan"))
        if D_i is not None and D_j is not None and cfg.refine_radius > 0:
            Di = torch.as_tensor(np.asarray(D_i) if not isinstance(D_i, Tensor) else D_i, dtype=torch.float32)
            Dj = torch.as_tensor(np.asarray(D_j) if not isinstance(D_j, Tensor) else D_j, dtype=torch.float32)
            Di = Di.reshape(H * W, -1)
            Dj = Dj.reshape(N, -1)
            if Di.shape[1] != Dj.shape[1]:
                raise DataError(f"pointmap matching: descriptor sizes differ ({Di.shape[1]} vs {Dj.shape[1]})")
            # only the matches still valid are refined (the others stay invalid whatever their window holds)
            sel = valid.nonzero().squeeze(1)
            index_sel, score_sel = _call("refine_all", cfg.compile, index[sel], Di, Dj[sel], H, W, cfg.refine_radius,
                                         tuple(cfg.refine_dilations))
            index = index.index_put((sel,), index_sel)
            score = score.index_put((sel,), score_sel)
            valid &= reference.valid[index]
        uv_int = torch.stack(((index % W).to(torch.float32), (index // W).to(torch.float32)), -1)
    n_valid = int(valid.sum())
    logger.debug("pointmap matching: %d of %d queries matched", n_valid, N)
    return PointmapMatches(uv=uv_int, uv_lm=uv_lm, index=index, valid=valid, ray_error=ray_error, score=score)
