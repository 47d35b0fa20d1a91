"""Compiled kernels of the iterative projective matching (:mod:`fgslam.frontends.pointmap.matching`):
the per-pixel Levenberg-Marquardt on the bilinear ray image and the descriptor refinement, one
query at a time (:mod:`fgslam.core.jit`). :func:`~fgslam.frontends.pointmap.matching.match_pointmaps`
calls them; they are the implementation. The LM runs in float32 as the rest of matching (3-term
sums accumulated in float64); the refinement's dot products in float64, its scores in float32.
"""

from __future__ import annotations

import numpy as np

from ...core.jit import kernel

DAMPING_FLOOR = 1e-12  # added to the damped diagonal: a flat ray image still gives a finite step
DET_FLOOR = 1e-30  # the 2x2 determinant is at least this (>= 0 up to rounding: Cauchy-Schwarz)


@kernel
def _sample(rays, W, H, u, v, out, q):
    """Bilinear ray of the ray image ``rays (3, H W)`` at ``(u, v)`` (float32, inside the image) into
    ``out[0, :, q]``, its exact derivatives along u and v into ``out[1, :, q]``, ``out[2, :, q]``."""
    u0 = min(np.floor(u), np.float32(W - 2))
    v0 = min(np.floor(v), np.float32(H - 2))
    fu = u - u0
    fv = v - v0
    i = int(v0) * W + int(u0)
    for c in range(3):
        c00, c01 = rays[c, i], rays[c, i + 1]
        c10, c11 = rays[c, i + W], rays[c, i + W + 1]
        d_top = c01 - c00
        d_bottom = c11 - c10
        top = c00 + fu * d_top
        dv = (c10 + fu * d_bottom) - top
        out[0, c, q] = top + fv * dv
        out[1, c, q] = d_top + fv * (d_bottom - d_top)
        out[2, c, q] = dv


@kernel
def _dot3(x, y, q):
    """``sum_c x[c, q] y[c, q]`` of float32 rows, accumulated in float64, rounded to float32."""
    return np.float32(np.float64(x[0, q] * y[0, q]) + np.float64(x[1, q] * y[1, q]) + np.float64(x[2, q] * y[2, q]))


@kernel
def lm_rows(rays, W, target, uv, max_iterations, lambda_initial, lambda_factor, step_tolerance):
    """Per query (``target (3, N)`` unit ray, start ``uv (N, 2)`` inside the image, all float32): damped
    Gauss-Newton steps on ``|ray(u, v) - target|^2``, a step kept where it lowers the error (damping /
    factor) and refused otherwise (damping x factor), in float32. The queries step together: a
    query leaves when half of those still stepping have converged (step below ``step_tolerance``
    pixels) and it is one of them; all stop when none moves or after ``max_iterations``. Returns the
    solutions ``(N, 2)`` and their squared ray errors ``(N,)``."""
    f32 = np.float32
    H = rays.shape[1] // W
    W1, H1 = f32(W - 1), f32(H - 1)
    floor_d, floor_det = f32(DAMPING_FLOOR), f32(DET_FLOOR)
    factor, tolerance, zero, one = f32(lambda_factor), f32(step_tolerance), f32(0.0), f32(1.0)
    n = target.shape[1]
    u = uv[:, 0].copy()
    v = uv[:, 1].copy()
    cur = np.empty((3, 3, n), dtype=np.float32)  # ray, d/du, d/dv per query
    new = np.empty((3, 3, n), dtype=np.float32)
    r = np.empty((3, n), dtype=np.float32)
    new_r = np.empty((3, n), dtype=np.float32)
    cost = np.empty(n, dtype=np.float32)
    lam = np.full(n, f32(lambda_initial), dtype=np.float32)
    for q in range(n):
        _sample(rays, W, H, u[q], v[q], cur, q)
        for c in range(3):
            r[c, q] = cur[0, c, q] - target[c, q]
        cost[q] = _dot3(r, r, q)
    active = np.arange(n)
    moving = np.zeros(n, dtype=np.bool_)
    for it in range(max_iterations):
        n_moving = 0
        for q in active:
            a, b, cc = _dot3(cur[1], cur[1], q), _dot3(cur[1], cur[2], q), _dot3(cur[2], cur[2], q)
            gu, gv = _dot3(cur[1], r, q), _dot3(cur[2], r, q)
            damp = one + lam[q]
            a_d = a * damp + floor_d
            c_d = cc * damp + floor_d
            inv_det = one / max(a_d * c_d - b * b, floor_det)
            step_u = (b * gv - c_d * gu) * inv_det
            step_v = (b * gu - a_d * gv) * inv_det
            if not np.isfinite(step_u):  # a degenerate step (flat or missing ray image) is no step
                step_u = zero
            if not np.isfinite(step_v):
                step_v = zero
            new_u = min(max(u[q] + step_u, zero), W1)
            new_v = min(max(v[q] + step_v, zero), H1)
            moving[q] = max(abs(new_u - u[q]), abs(new_v - v[q])) > tolerance
            n_moving += moving[q]
            _sample(rays, W, H, new_u, new_v, new, q)
            for c in range(3):
                new_r[c, q] = new[0, c, q] - target[c, q]
            new_cost = _dot3(new_r, new_r, q)
            if new_cost < cost[q]:
                u[q], v[q], cost[q] = new_u, new_v, new_cost
                for c in range(3):
                    r[c, q] = new_r[c, q]
                    for k in range(3):
                        cur[k, c, q] = new[k, c, q]
                lam[q] = lam[q] / factor
            else:
                lam[q] = lam[q] * factor
        if it + 1 == max_iterations or n_moving == 0:
            break
        if 2 * n_moving <= active.shape[0]:  # half have converged: only the moving ones go on
            active = active[moving[active]]
    uv_out = np.empty((n, 2), dtype=np.float32)
    uv_out[:, 0] = u
    uv_out[:, 1] = v
    return uv_out, cost


@kernel
def refine_rows(index, D_i, D_j, H, W, radius, dilations):
    """Per query: the reference pixel of the best descriptor dot product ``D_j[q] . D_i[p]`` within the
    ``(2 radius + 1)^2`` window (spacing ``dilation``, clamped to the image) around its flat index,
    once per dilation (coarse to fine, each around the last one's best). Returns the indices and
    their scores (NaN without dilations)."""
    n = index.shape[0]
    d = D_j.shape[1]
    out_index = index.copy()
    score = np.full(n, np.nan, dtype=np.float32)
    for q in range(n):
        best_index = index[q]
        for dilation in dilations:
            u0 = best_index % W
            v0 = best_index // W
            best = -np.inf
            for dy in range(-radius, radius + 1):
                row = min(max(v0 + dy * dilation, 0), H - 1) * W
                for dx in range(-radius, radius + 1):
                    cand = min(max(u0 + dx * dilation, 0), W - 1) + row
                    s = 0.0
                    for k in range(d):
                        s += np.float64(D_i[cand, k]) * np.float64(D_j[q, k])
                    if s > best:
                        best = s
                        best_index = cand
            score[q] = best
        out_index[q] = best_index
    return out_index, score
