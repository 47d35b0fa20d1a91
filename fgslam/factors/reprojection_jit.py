"""The row arithmetic of the inverse-depth reprojection (:mod:`fgslam.factors.reprojection`) and its
compiled loop over rows (:mod:`fgslam.core.jit`).

The row functions are the one implementation of the residual's arithmetic. Each is plain arithmetic on
its arguments, so it runs on two kinds of operands:

- inside :func:`transfer_rows` (numba, one row at a time in float64): the path of every frontend, on the
  CPU without gradients;
- through ``.py_func`` on torch tensors (element-wise over a batch, any dtype and device, differentiable
  by autograd): the learned networks' training graph (:mod:`fgslam.nets.dba`) and tensors on a GPU.

Both evaluate the same operations in the same order, and IEEE arithmetic rounds each operation alike
(element-wise torch operators contract nothing; :data:`fgslam.core.jit.KERNEL_OPTIONS` has no
fastmath), so the two give the same bytes (``tests/test_factors_reprojection.py``).

Notation as in the residual's module docstring: ``M = s_i R_j^T R_i`` (``R_tj M`` with an extrinsic)
maps the source unit-depth ray ``p = [px, py, 1]`` to the target direction and ``b`` is the source
centre seen from the target, so ``Q = M p + d b``.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.jit import kernel
from .configs import PIXEL_DIM, SIM3_DOF

#: :func:`target_rows` gives per image axis the entries of these columns of ``J_Tj`` (the rest are zero)
TARGET_U_COLUMNS = (0, 1, 2, 3, 5)
TARGET_V_COLUMNS = (0, 1, 2, 4, 5)
TARGET_ROW_ENTRIES = len(TARGET_U_COLUMNS)


@kernel
def target_point(m00, m01, m02, m10, m11, m12, m20, m21, m22, b0, b1, b2, px, py, d):
    """``Q = M p + d b`` (the homogeneous target-camera point)."""
    Qx = m00 * px + m01 * py + m02 + d * b0
    Qy = m10 * px + m11 * py + m12 + d * b1
    Qz = m20 * px + m21 * py + m22 + d * b2
    return Qx, Qy, Qz


@kernel
def projection(Qx, Qy, inv_z, fx, fy, cx, cy):
    """The normalised coordinates ``xn = Q_x / Q_z``, ``yn = Q_y / Q_z`` and the pixel ``(u, v)``."""
    xn = Qx * inv_z
    yn = Qy * inv_z
    return xn, yn, fx * xn + cx, fy * yn + cy


@kernel
def projection_rows(fx_iz, fy_iz, xn, yn, m00, m01, m02, m10, m11, m12, m20, m21, m22, b0, b1, b2):
    """``B = A M`` (``A = d(uv)/dQ``, rows ``fx / Q_z [1, 0, -xn]`` and ``fy / Q_z [0, 1, -yn]``; ``B`` is
    d(uv)/d(source ray)) and ``J_d = A b``: ``(B00, B01, B02, B10, B11, B12, J_d0, J_d1)``."""
    return (fx_iz * (m00 - xn * m20), fx_iz * (m01 - xn * m21), fx_iz * (m02 - xn * m22),
            fy_iz * (m10 - yn * m20), fy_iz * (m11 - yn * m21), fy_iz * (m12 - yn * m22),
            fx_iz * (b0 - xn * b2), fy_iz * (b1 - yn * b2))


@kernel
def source_row(bx, by, bz, px, py, d):
    """One row of ``J_Ti`` from the row ``B_r`` of ``B = A M`` (``A = d(uv)/dQ``):
    ``dQ/dxi_i = M [-[p]x, d I, p]``, so the row is ``[p x B_r, d B_r, B_r . p]``."""
    return (py * bz - by, bx - px * bz, px * by - py * bx, d * bx, d * by, d * bz, bx * px + by * py + bz)


@kernel
def target_rows(fxm, fym, fx_iz, fy_iz, xn, yn, ds_j):
    """The non-zero entries of ``J_Tj`` without an extrinsic (``dQ/dxi_j = [[Q]x, -d s_j I, 0]``):
    row u ``[w0, w1, w2, u0, -, u2]``, row v ``[w0, w1, w2, -, u1, u2]``."""
    xy = xn * yn
    return (fxm * xy, -fxm * (1 + xn * xn), fxm * yn, -ds_j * fx_iz, ds_j * fx_iz * xn,
            fym * (1 + yn * yn), -fym * xy, -fym * xn, -ds_j * fy_iz, ds_j * fy_iz * yn)


@kernel
def extrinsic_row(a0, a1, a2, q0, q1, q2, r00, r01, r02, r10, r11, r12, r20, r21, r22, l0, l1, l2, d, ds_j):
    """One row of ``J_Tj`` through a fixed extrinsic ``R_tj`` (``r..``) whose metric translation in the
    units of frame ``j`` is ``b_lam`` (``l..``), for the row ``a`` of ``A`` and ``q = Q - d b_lam``:
    ``[(a x q) R_tj, -d s_j a R_tj, a . (d b_lam)]``."""
    c0 = a1 * q2 - a2 * q1
    c1 = a2 * q0 - a0 * q2
    c2 = a0 * q1 - a1 * q0
    aR0 = a0 * r00 + a1 * r10 + a2 * r20
    aR1 = a0 * r01 + a1 * r11 + a2 * r21
    aR2 = a0 * r02 + a1 * r12 + a2 * r22
    return (c0 * r00 + c1 * r10 + c2 * r20, c0 * r01 + c1 * r11 + c2 * r21, c0 * r02 + c1 * r12 + c2 * r22,
            -ds_j * aR0, -ds_j * aR1, -ds_j * aR2, a0 * (d * l0) + a1 * (d * l1) + a2 * (d * l2))


@kernel
def transfer_rows(uv_i, inv_depth, rows_ok, K_i, k_src, K_t, k_tgt, M, b, s_j, pose, R_tj, b_lam, extrinsic,
                  min_depth, jacobians):
    """The reprojection of ``n`` rows: source pixels ``uv_i (n, 2)``, inverse depths ``(n,)``, extra
    validity ``rows_ok (n,)``; intrinsics ``K_i``, ``K_t`` ``(k, 4)`` of row ``r`` at ``k_src[r]``,
    ``k_tgt[r]``; the pose pair's ``M (P, 3, 3)``, ``b (P, 3)``, ``s_j (P,)`` and ``b_lam (P, 3)`` at
    ``pose[r]``; with ``extrinsic`` the fixed rotation ``R_tj (3, 3)``. Returns ``uv (n, 2)`` (not zeroed),
    ``valid (n,)`` and, with ``jacobians``, ``J_Ti``, ``J_Tj`` ``(n, 2, 7)`` and ``J_d (n, 2)``, zero on
    invalid rows (else ``(0, 2, 7)`` and ``(0, 2)``)."""
    n = uv_i.shape[0]
    uv = np.empty((n, PIXEL_DIM))
    valid = np.zeros(n, np.bool_)
    m = n if jacobians else 0
    J_Ti = np.zeros((m, PIXEL_DIM, SIM3_DOF))
    J_Tj = np.zeros((m, PIXEL_DIM, SIM3_DOF))
    J_d = np.zeros((m, PIXEL_DIM))
    n_pose, n_src, n_tgt = M.shape[0], K_i.shape[0], K_t.shape[0]
    r00, r01, r02 = R_tj[0, 0], R_tj[0, 1], R_tj[0, 2]
    r10, r11, r12 = R_tj[1, 0], R_tj[1, 1], R_tj[1, 2]
    r20, r21, r22 = R_tj[2, 0], R_tj[2, 1], R_tj[2, 2]
    for r in range(n):
        ks, kt, p = k_src[r], k_tgt[r], pose[r]
        if not (0 <= p < n_pose and 0 <= ks < n_src and 0 <= kt < n_tgt):
            raise IndexError("reprojection: a row's pose pair or intrinsics index is out of range")
        px = (uv_i[r, 0] - K_i[ks, 2]) / K_i[ks, 0]
        py = (uv_i[r, 1] - K_i[ks, 3]) / K_i[ks, 1]
        d = inv_depth[r]
        m00, m01, m02 = M[p, 0, 0], M[p, 0, 1], M[p, 0, 2]
        m10, m11, m12 = M[p, 1, 0], M[p, 1, 1], M[p, 1, 2]
        m20, m21, m22 = M[p, 2, 0], M[p, 2, 1], M[p, 2, 2]
        b0, b1, b2 = b[p, 0], b[p, 1], b[p, 2]
        sj = s_j[p]
        Qx, Qy, Qz = target_point(m00, m01, m02, m10, m11, m12, m20, m21, m22, b0, b1, b2, px, py, d)
        fx, fy, cx, cy = K_t[kt, 0], K_t[kt, 1], K_t[kt, 2], K_t[kt, 3]
        ok = (Qz > 0 and Qz > min_depth * d * sj and math.isfinite(d) and d >= 0 and math.isfinite(Qx)
              and math.isfinite(Qy))
        inv_z = 1.0 / (Qz if ok else 1.0)
        xn, yn, u, v = projection(Qx, Qy, inv_z, fx, fy, cx, cy)
        uv[r, 0] = u
        uv[r, 1] = v
        ok = (ok and math.isfinite(u) and math.isfinite(v) and math.isfinite(xn * inv_z)
              and math.isfinite(yn * inv_z) and rows_ok[r])
        valid[r] = ok
        if not jacobians:
            continue
        # the factors of every Jacobian entry, zero on an invalid row (as the element-wise path's masks)
        fx_iz = fx * inv_z if ok else 0.0
        fy_iz = fy * inv_z if ok else 0.0
        if not ok:
            xn = yn = px = py = d = 0.0
        B00, B01, B02, B10, B11, B12, J_d0, J_d1 = projection_rows(
            fx_iz, fy_iz, xn, yn, m00, m01, m02, m10, m11, m12, m20, m21, m22, b0, b1, b2)
        J_d[r, 0] = J_d0
        J_d[r, 1] = J_d1
        row = source_row(B00, B01, B02, px, py, d)
        for c in range(SIM3_DOF):
            J_Ti[r, 0, c] = row[c]
        row = source_row(B10, B11, B12, px, py, d)
        for c in range(SIM3_DOF):
            J_Ti[r, 1, c] = row[c]
        ds_j = d * sj
        if not extrinsic:
            fxm = fx if ok else 0.0
            fym = fy if ok else 0.0
            e = target_rows(fxm, fym, fx_iz, fy_iz, xn, yn, ds_j)
            for c in range(TARGET_ROW_ENTRIES):
                J_Tj[r, 0, TARGET_U_COLUMNS[c]] = e[c]
                J_Tj[r, 1, TARGET_V_COLUMNS[c]] = e[TARGET_ROW_ENTRIES + c]
            continue
        l0, l1, l2 = b_lam[p, 0], b_lam[p, 1], b_lam[p, 2]
        q0 = (Qx if ok else 0.0) - d * l0
        q1 = (Qy if ok else 0.0) - d * l1
        q2 = (Qz if ok else 0.0) - d * l2
        row = extrinsic_row(fx_iz, 0.0, -fx_iz * xn, q0, q1, q2, r00, r01, r02, r10, r11, r12, r20, r21, r22,
                            l0, l1, l2, d, ds_j)
        for c in range(SIM3_DOF):
            J_Tj[r, 0, c] = row[c]
        row = extrinsic_row(0.0, fy_iz, -fy_iz * yn, q0, q1, q2, r00, r01, r02, r10, r11, r12, r20, r21, r22,
                            l0, l1, l2, d, ds_j)
        for c in range(SIM3_DOF):
            J_Tj[r, 1, c] = row[c]
    return uv, valid, J_Ti, J_Tj, J_d
