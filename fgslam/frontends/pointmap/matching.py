"""Iterative projective matching of two pointmaps (MASt3R-SLAM section 3.2, eqs. 2-4), compiled per query.

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

from ...core.errors import DataError
from ...factors.schur import torch_threads
from .config import MatchingConfig  # the config: in .config, torch- and OpenCV-free (a run's config loads without them)

logger = logging.getLogger(__name__)

__all__ = ["MatchingConfig", "PointmapMatches", "RayImage", "match_pointmaps", "pixel_grid_uv"]


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


def _rays(X: Tensor) -> tuple[Tensor, Tensor]:
    ok = torch.isfinite(X.sum(-1))  # (a NaN or inf coordinate makes the sum non-finite; 10x faster than all(-1))
    X = torch.where(ok[:, None], X, torch.zeros((), dtype=X.dtype))
    norm = torch.linalg.vector_norm(X, dim=-1, keepdim=True)
    ok &= norm[:, 0] > 0
    return (X / norm.clamp_min(1e-30)).T.contiguous(), ok


def _lm(ref: RayImage, target: Tensor, uv: Tensor, cfg: MatchingConfig) -> tuple[Tensor, Tensor]:
    """Per-pixel LM on ``|ray_i(uv) - target|^2`` (``target (3, N)``, ``uv (N, 2)`` inside the image;
    the compiled kernel ``matching_jit.lm_rows``); returns the solution ``(N, 2)`` and its squared ray
    error. A pixel stops when its step moves less than ``step_tolerance`` (most do after a step or two
    when warm started)."""
    from .matching_jit import lm_rows  # deferred: numba (compiled kernel, core/jit.py)

    uv_lm, cost = lm_rows(ref.rays.numpy(), ref.W, target.contiguous().numpy(), uv.contiguous().numpy(),
                          int(cfg.max_iterations), float(cfg.lambda_initial), float(cfg.lambda_factor),
                          float(cfg.step_tolerance))
    return torch.from_numpy(uv_lm), torch.from_numpy(cost)


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
            from .matching_jit import refine_rows  # deferred: numba (compiled kernel, core/jit.py)

            index_sel, score_sel = refine_rows(index[sel].numpy(), Di.contiguous().numpy(), Dj[sel].contiguous().numpy(),
                                               H, W, int(cfg.refine_radius), np.asarray(cfg.refine_dilations, np.int64))
            index_sel, score_sel = torch.from_numpy(index_sel), torch.from_numpy(score_sel)
            index = index.index_put((sel,), index_sel)
            score = score.index_put((sel,), score_sel)
            valid &= reference.valid[index]
        uv_int = torch.stack(((index % W).to(torch.float32), (index // W).to(torch.float32)), -1)
    n_valid = int(valid.sum())
    logger.debug("pointmap matching: %d of %d queries matched", n_valid, N)
    return PointmapMatches(uv=uv_int, uv_lm=uv_lm, index=index, valid=valid, ray_error=ray_error, score=score)
