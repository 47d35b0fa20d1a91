"""Compiled kernel of the pointmap ray-and-distance residual (:func:`fgslam.factors.pointmap.ray_dist_prepared`),
one match at a time (:mod:`fgslam.core.jit`). It is the implementation: the residual's tests
(finite-difference Jacobians included) call it through ``ray_dist_prepared``.

Float64 throughout; every sum is written out in a fixed order (no FMA contraction, no reordering), so
the bytes do not depend on the CPU.
"""

from __future__ import annotations

import numpy as np

from ..core.jit import kernel
from .configs import RAY_DIST_ROWS, SIM3_DOF


@kernel
def ray_dist_rows(R, t, s, X_f, psi_k, norm_k, sqrt_w, valid_in, min_norm, sigma_ray, sigma_dist, jacobians):
    """Per match ``(b, n)`` of the pose batch ``R (B, 3, 3)``, ``t (B, 3)``, ``s (B,)`` and the prepared
    matches ``X_f``, ``psi_k`` ``(B, N, 3)``, ``norm_k``, ``sqrt_w`` ``(B, N)``, ``valid_in (B, N)`` bool:
    ``Y = s (R X_f) + t``; rows ``psi(Y) - psi_k`` and ``||Y|| - norm_k``; with ``jacobians`` the rows
    ``[X_f x a, a, a . X_f]`` of ``A = dr/dY s R`` (ray rows ``(sR - psi (psi^T sR)) / ||Y||``, distance
    row ``psi^T sR``); whitening ``sqrt_w / sigma``. A match whose input is not valid or whose ``||Y||`` is
    at most ``min_norm`` gets zeros everywhere and ``valid`` False. Returns ``(r (B, N, 4), J (B, N, 4, 7)``
    (``(0, 0, 4, 7)`` without ``jacobians``), ``sqrt_info (B, N, 4), valid (B, N))``."""
    B, N = X_f.shape[0], X_f.shape[1]
    r = np.zeros((B, N, RAY_DIST_ROWS))
    J = np.zeros((B, N, RAY_DIST_ROWS, SIM3_DOF)) if jacobians else np.zeros((0, 0, RAY_DIST_ROWS, SIM3_DOF))
    sqrt_info = np.zeros((B, N, RAY_DIST_ROWS))
    valid = np.zeros((B, N), np.bool_)
    Y = np.empty(3)
    psi = np.empty(3)
    sR = np.empty((3, 3))
    A = np.empty((RAY_DIST_ROWS, 3))
    for b in range(B):
        for i in range(3):
            for j in range(3):
                sR[i, j] = s[b] * R[b, i, j]
        for n in range(N):
            x0, x1, x2 = X_f[b, n, 0], X_f[b, n, 1], X_f[b, n, 2]
            for i in range(3):
                Y[i] = s[b] * (R[b, i, 0] * x0 + R[b, i, 1] * x1 + R[b, i, 2] * x2) + t[b, i]
            norm_Y = np.sqrt(Y[0] * Y[0] + Y[1] * Y[1] + Y[2] * Y[2])
            if not (valid_in[b, n] and norm_Y > min_norm):
                continue
            valid[b, n] = True
            inv_n = 1.0 / norm_Y
            for i in range(3):
                psi[i] = Y[i] * inv_n
                r[b, n, i] = psi[i] - psi_k[b, n, i]
                sqrt_info[b, n, i] = sqrt_w[b, n] / sigma_ray
            r[b, n, 3] = norm_Y - norm_k[b, n]
            sqrt_info[b, n, 3] = sqrt_w[b, n] / sigma_dist
            if not jacobians:
                continue
            for j in range(3):
                A[3, j] = psi[0] * sR[0, j] + psi[1] * sR[1, j] + psi[2] * sR[2, j]
            for i in range(3):
                for j in range(3):
                    A[i, j] = (sR[i, j] - psi[i] * A[3, j]) * inv_n
            for m in range(RAY_DIST_ROWS):
                a0, a1, a2 = A[m, 0], A[m, 1], A[m, 2]
                row = J[b, n, m]
                row[0] = x1 * a2 - x2 * a1
                row[1] = x2 * a0 - x0 * a2
                row[2] = x0 * a1 - x1 * a0
                row[3] = a0
                row[4] = a1
                row[5] = a2
                row[6] = a0 * x0 + a1 * x1 + a2 * x2
    return r, J, sqrt_info, valid
