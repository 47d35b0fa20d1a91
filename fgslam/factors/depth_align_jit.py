"""Compiled row kernels of the point-to-plane depth alignment (:mod:`fgslam.factors.depth_align`):
the depth surface of each pyramid level (vertices, normals, discontinuity gates: :func:`surface_rows`),
and the residual, its Jacobians and the projective association, one pass over the frame's vertices
(:mod:`fgslam.core.jit`). :meth:`fgslam.factors.depth_align.DepthSurface.from_depth`,
:func:`fgslam.factors.depth_align.point_to_plane` and :class:`~fgslam.factors.depth_align.DepthAlignBlock`
call these; they are the implementation.

Jacobian columns: ``[J_k (7), J_f (7)]`` w.r.t. right perturbations ``[w, u, lambda]`` of ``T_WCk`` and
``T_WCf`` (the derivation is in :func:`~fgslam.factors.depth_align.point_to_plane`).
"""

from __future__ import annotations

import numpy as np

from ..core.jit import kernel

JACOBIAN_COLUMNS = 14  # [J_k, J_f], 7 each


@kernel
def _p2p_row(A, X_f, Y, X_k, n_k, J, row, jacobians):
    """Residual ``n_k . (Y - X_k)`` of one vertex; its Jacobian row written into ``J[row]``."""
    r = n_k[0] * (Y[0] - X_k[0]) + n_k[1] * (Y[1] - X_k[1]) + n_k[2] * (Y[2] - X_k[2])
    if not jacobians:
        return r
    a0 = n_k[0] * A[0, 0] + n_k[1] * A[1, 0] + n_k[2] * A[2, 0]  # a = A^T n_k
    a1 = n_k[0] * A[0, 1] + n_k[1] * A[1, 1] + n_k[2] * A[2, 1]
    a2 = n_k[0] * A[0, 2] + n_k[1] * A[1, 2] + n_k[2] * A[2, 2]
    J[row, 0] = n_k[1] * Y[2] - n_k[2] * Y[1]  # J_k = [n_k x Y, -n_k, -n_k . Y]
    J[row, 1] = n_k[2] * Y[0] - n_k[0] * Y[2]
    J[row, 2] = n_k[0] * Y[1] - n_k[1] * Y[0]
    J[row, 3] = -n_k[0]
    J[row, 4] = -n_k[1]
    J[row, 5] = -n_k[2]
    J[row, 6] = -(n_k[0] * Y[0] + n_k[1] * Y[1] + n_k[2] * Y[2])
    J[row, 7] = X_f[1] * a2 - X_f[2] * a1  # J_f = [X_f x a, a, a . X_f]
    J[row, 8] = X_f[2] * a0 - X_f[0] * a2
    J[row, 9] = X_f[0] * a1 - X_f[1] * a0
    J[row, 10] = a0
    J[row, 11] = a1
    J[row, 12] = a2
    J[row, 13] = a0 * X_f[0] + a1 * X_f[1] + a2 * X_f[2]
    return r


@kernel
def point_to_plane_rows(A, X_f, Y, X_k, n_k, jacobians):
    """Residuals ``(N,)`` and Jacobians ``(N, 14)`` (zeros without ``jacobians``) of vertex rows."""
    n = X_f.shape[0]
    r = np.zeros(n)
    J = np.zeros((n, JACOBIAN_COLUMNS))
    for i in range(n):
        r[i] = _p2p_row(A, X_f[i], Y[i], X_k[i], n_k[i], J, i, jacobians)
    return r, J


@kernel
def associate_rows(A, b, X_f, n_f, ref_V, ref_N, ref_valid, K, shape, min_depth, max_distance, min_agree,
                   jacobians):
    """Every frame vertex ``X_f`` moved by ``Y = A X_f + b`` into the reference camera, projected to its
    nearest reference grid pixel (intrinsics ``K = (fx, fy, cx, cy)``, grid ``shape = (h, w)``) and paired
    with the reference vertex there when one exists (``seen``), lies within ``max_distance`` of ``Y`` and
    the normals agree (``(A n_f) . n_k >= min_agree``). Returns ``seen``, ``paired`` ``(N,)`` bool and,
    on paired rows (zeros elsewhere), the residuals ``(N,)`` and Jacobians ``(N, 14)`` (``(0, 14)``
    without ``jacobians``)."""
    fx, fy, cx, cy = K[0], K[1], K[2], K[3]
    h, w = shape[0], shape[1]
    n = X_f.shape[0]
    seen = np.zeros(n, dtype=np.bool_)
    paired = np.zeros(n, dtype=np.bool_)
    r = np.zeros(n)
    J = np.zeros((n if jacobians else 0, JACOBIAN_COLUMNS))  # no rows for a cost alone
    Y = np.empty(3)
    for i in range(n):
        for c in range(3):
            Y[c] = A[c, 0] * X_f[i, 0] + A[c, 1] * X_f[i, 1] + A[c, 2] * X_f[i, 2] + b[c]
        if not Y[2] > min_depth:
            continue
        u = np.rint(fx * Y[0] / Y[2] + cx)
        v = np.rint(fy * Y[1] / Y[2] + cy)
        if not (u >= 0 and u <= w - 1 and v >= 0 and v <= h - 1):
            continue
        idx = int(v) * w + int(u)
        if not ref_valid[idx]:
            continue
        seen[i] = True
        d0, d1, d2 = Y[0] - ref_V[idx, 0], Y[1] - ref_V[idx, 1], Y[2] - ref_V[idx, 2]
        if not np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) <= max_distance:
            continue
        agree = 0.0
        for c in range(3):
            agree += (A[c, 0] * n_f[i, 0] + A[c, 1] * n_f[i, 1] + A[c, 2] * n_f[i, 2]) * ref_N[idx, c]
        if not agree >= min_agree:
            continue
        paired[i] = True
        r[i] = _p2p_row(A, X_f[i], Y, ref_V[idx], ref_N[idx], J, i, jacobians)
    return seen, paired, r, J


@kernel
def surface_rows(depth, off, stride, K, min_depth, max_depth, max_discontinuity):
    """One surface level of a depth image (:meth:`fgslam.factors.depth_align.DepthSurface.from_depth`):
    grid pixel ``(a, b)`` is image pixel ``(off + stride b, off + stride a)`` with grid intrinsics
    ``K = [fx, fy, cx, cy]``. Returns the vertices ``V (h, w, 3)`` (zero without depth in
    ``[min_depth, max_depth]``), the unit normals ``N (h, w, 3)`` by central differences, pointing to the
    camera, and where they exist, ``good (h, w)``: the pixel and its four neighbours have depth, no
    neighbour's depth differs by more than ``max_discontinuity`` of the pixel's, and the normal is not
    degenerate. Sums in numpy's order (the bits of the former array code)."""
    H, W = depth.shape
    h = (H - off + stride - 1) // stride
    w = (W - off + stride - 1) // stride
    z = np.zeros((h, w))
    ok = np.zeros((h, w), np.bool_)
    V = np.zeros((h, w, 3))
    N = np.zeros((h, w, 3))
    good = np.zeros((h, w), np.bool_)
    for a in range(h):
        y = (a - K[3]) / K[1]
        for b in range(w):
            d = np.float64(depth[off + stride * a, off + stride * b])
            if np.isfinite(d) and d >= min_depth and d <= max_depth:
                ok[a, b] = True
                z[a, b] = d
            x = (b - K[2]) / K[0]
            V[a, b, 0] = x * z[a, b]
            V[a, b, 1] = y * z[a, b]
            V[a, b, 2] = z[a, b]
    if h < 3 or w < 3:
        return V, N, good
    for a in range(1, h - 1):
        for b in range(1, w - 1):
            if not (ok[a, b] and ok[a, b + 1] and ok[a, b - 1] and ok[a + 1, b] and ok[a - 1, b]):
                continue
            c = z[a, b]
            limit = max_discontinuity * c
            if (abs(z[a, b + 1] - c) > limit or abs(z[a, b - 1] - c) > limit or abs(z[a + 1, b] - c) > limit
                    or abs(z[a - 1, b] - c) > limit):
                continue
            du0 = V[a, b + 1, 0] - V[a, b - 1, 0]
            du1 = V[a, b + 1, 1] - V[a, b - 1, 1]
            du2 = V[a, b + 1, 2] - V[a, b - 1, 2]
            dv0 = V[a + 1, b, 0] - V[a - 1, b, 0]
            dv1 = V[a + 1, b, 1] - V[a - 1, b, 1]
            dv2 = V[a + 1, b, 2] - V[a - 1, b, 2]
            n0 = du1 * dv2 - du2 * dv1
            n1 = du2 * dv0 - du0 * dv2
            n2 = du0 * dv1 - du1 * dv0
            norm = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            if not norm > 0:
                continue
            n0, n1, n2 = n0 / norm, n1 / norm, n2 / norm
            if n0 * V[a, b, 0] + n1 * V[a, b, 1] + n2 * V[a, b, 2] > 0:  # towards the camera: n . X < 0
                n0, n1, n2 = -n0, -n1, -n2
            N[a, b, 0], N[a, b, 1], N[a, b, 2] = n0, n1, n2
            good[a, b] = True
    return V, N, good
