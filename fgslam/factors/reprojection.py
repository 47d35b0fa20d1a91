"""Inverse-depth reprojection between two Sim(3) keyframes, with analytic Jacobians (batched torch in, torch
out; the rows run compiled, :mod:`fgslam.factors.reprojection_jit`).

The residual of DROID-SLAM eq. 4 (Jacobians: appendix C, eqs. 6-14) and of DPV-SLAM eqs. 2-3
(patches), in the conventions of fgslam:

- Poses ``T_WCi``, ``T_WCj`` are camera-to-world Sim(3): ``X_W = s R X_C + t`` (``fgslam.core.lie.Sim3``).
  Anything with attributes ``.R (..., 3, 3)``, ``.t (..., 3)`` and optionally ``.s (...)`` (an SE3
  object has scale 1), or a tuple ``(R, t, s)``, is accepted (:data:`PoseLike`).
- Jacobians are w.r.t. RIGHT perturbations ``T <- T Exp(xi)`` with the gtsam ``Similarity3``
  tangent order ``xi = [w (3), u (3), lambda]`` (rotation, translation, log-scale); columns 0-5
  are also the ``Pose3`` ``[w, v]`` Jacobian of an SE(3) pose held at scale 1.
- A measurement ``n`` is a source pixel ``uv_i`` of keyframe ``i`` with inverse depth ``d`` (the
  source camera-frame point ``X_i = p / d``, ``p = [(u - cx) / fx, (v - cy) / fy, 1]``) observed at
  ``uv_target`` in keyframe ``j``. Residual ``r = pi(T_WCj^-1 T_WCi X_i) - uv_target``.

Homogeneous form (no division by ``d``, so ``d = 0``, a point at infinity, is fine)::

    Q = R_j^T (s_i R_i p + d (t_i - t_j))  =  d s_j (T_WCj^-1 T_WCi X_i)
    uv = pi(Q)

Scale gauge: ``Q`` does not contain ``s_j`` and ``pi`` is scale-invariant, so the target scale drops
out (the ``lambda_j`` column of ``J_Tj`` is exactly zero), and ``s_i`` enters only through
``d / s_i``, so the ``lambda_i`` column of ``J_Ti`` equals ``-d * J_d``. The monocular frontends
therefore hold each keyframe's scale fixed and fold Sim(3) corrections into depths (``d <- d / s``).

An optional fixed extrinsic ``T_CtCj`` (e.g. ``T_CRCL`` of a stereo rig, in metres) moves the
target to a camera rigidly attached to keyframe ``j``. Its translation is metric, so it is applied
in the metric camera frame of ``j`` (camera-frame coordinates are world coordinates divided by
``s_j``, i.e. ``s_j`` is "world units per metre")::

    Q_t = R_CtCj Q + d s_j t_CtCj  =  d s_j (T_CtCj T_WCj^-1 T_WCi X_i)

Now ``s_j`` matters (a metric baseline fixes the scale); with ``s_j = 1`` (stereo and RGB-D
frontends) camera frames and world share metric units.

Patches (DPV-SLAM eq. 3): a patch of ``p x p`` pixels shares one inverse depth. The functions work
on rows; :func:`flatten_patches` turns patch ``k`` into rows ``k p^2 + a p + b`` (pixel row ``a``,
column ``b``), each carrying the patch's depth, and the patch's depth Jacobian is the sum of its
rows' contributions (e.g. ``J_d.reshape(..., P, p * p, 2)``).

Validity: a row is valid when ``d`` is finite and ``>= 0`` (``d < 0`` is behind the source camera),
the inputs are finite, and the point lies in front of the target camera with depth above
``config.min_depth`` (``Q_z > min_depth * d * s_j`` and ``Q_z > 0``). Invalid rows hold zeros in the
residual and every Jacobian (never NaN or inf); ``n_invalid`` counts them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, Union

import numpy as np
import torch

from ..core.config import MAX_SCALAR, ranged
from ..core.errors import DataError
from .configs import INTRINSICS, PIXEL_DIM, SIM3_DOF

#: a camera-frame point (x, y, z)
POINT_DIM = 3

__all__ = [
    "PoseLike",
    "ReprojectionConfig",
    "ReprojectionResult",
    "flatten_patches",
    "pose_components",
    "reproject",
    "reproject_edges",
    "reproject_inv_depth",
]


class RotationTranslation(Protocol):
    """A batched pose with rotation ``R (..., 3, 3)`` and translation ``t (..., 3)``, and a scale
    ``s (...)`` when it is a similarity (:class:`fgslam.core.lie.Sim3`; an :class:`fgslam.core.lie.SE3` has
    none: scale 1)."""

    @property
    def R(self) -> torch.Tensor: ...

    @property
    def t(self) -> torch.Tensor: ...


#: a pose argument: a Sim3/SE3-like object or an ``(R, t, s)`` tuple (``s`` a tensor or a number)
PoseLike = Union[RotationTranslation, tuple[torch.Tensor, torch.Tensor, Union[torch.Tensor, float]]]
#: a fixed 4x4 transform (an extrinsic such as ``T_CRCL``), numpy or torch
Transform = Union[np.ndarray, torch.Tensor]


@dataclass
class ReprojectionConfig:
    """Tunables of the inverse-depth reprojection residual."""

    min_depth: float = ranged(0.2, gt=0, le=MAX_SCALAR)  # smallest valid depth in the target camera, camera-frame units (DROID-SLAM's MIN_DEPTH)


@dataclass
class ReprojectionResult:
    """Residuals and Jacobians of ``N`` (any batch shape ``...``) reprojection measurements.

    Attributes:
        residual: ``(..., 2)`` predicted minus observed pixel coordinates.
        J_Ti: ``(..., 2, 7)`` d(residual)/d(xi_i), right perturbation of ``T_WCi``, order [w, u, lambda].
        J_Tj: ``(..., 2, 7)`` same for ``T_WCj``.
        J_d: ``(..., 2)`` d(residual)/d(inverse depth of the source pixel).
        valid: ``(...)`` bool; invalid rows are zero in all of the above.
    """

    residual: torch.Tensor
    J_Ti: torch.Tensor
    J_Tj: torch.Tensor
    J_d: torch.Tensor
    valid: torch.Tensor

    @property
    def n_invalid(self) -> int:
        """Number of invalid (zeroed) rows."""
        return int(self.valid.numel() - int(self.valid.sum()))


def pose_components(T: PoseLike) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(R (..., 3, 3), t (..., 3), s (...))`` of a Sim3/SE3-like object or an ``(R, t, s)`` tuple.

    Objects without an ``s`` attribute (SE3) get scale 1.
    """
    if isinstance(T, tuple):
        R, t, s = T
        return R, t, torch.as_tensor(s, dtype=t.dtype, device=t.device)
    s = getattr(T, "s", None)
    if s is None:
        s = torch.ones(T.t.shape[:-1], dtype=T.t.dtype, device=T.t.device)
    return T.R, T.t, s


def _as_rigid(T: Transform, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation and translation of a fixed 4x4 transform (numpy or torch), cast like ``like``."""
    M = torch.as_tensor(np.asarray(T) if not isinstance(T, torch.Tensor) else T, dtype=like.dtype, device=like.device)
    return M[..., :3, :3], M[..., :3, 3]


def _transfer(
    uv_i: torch.Tensor,
    inv_depth: torch.Tensor,
    T_WCi: PoseLike,
    T_WCj: PoseLike,
    K_i: torch.Tensor,
    K_t: torch.Tensor,
    T_CtCj: Transform | None,
    min_depth: float,
    jacobians: bool,
    rows_ok: torch.Tensor | None = None,
    pair_index: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None]:
    """Shared kernel: predicted target pixels, validity, and (optionally) Jacobians.

    ``rows_ok`` (optional bool mask) marks further invalid rows (e.g. a non-finite target).
    ``pair_index`` (optional, ``(n,)`` integers): the rows are ``(n,)`` and row ``r`` uses the pose pair
    ``pair_index[r]`` of poses with one batch dimension (``(G,)``: a block's edges, each pose pair formed
    once) instead of broadcasting poses against the rows.
    Returns ``uv (..., 2)`` (not zeroed), ``valid (...)`` and ``(J_Ti, J_Tj, J_d)`` or None. The
    Jacobians are already zero on invalid rows: every entry carries a factor ``fx / Q_z`` or
    ``fy / Q_z``, which is set to 0 there (and every other factor is made finite).

    The pose pair's ``M`` and ``b`` are formed here (once per pose pair when poses are shared); the rows
    go through the row arithmetic of :mod:`fgslam.factors.reprojection_jit`: its compiled loop for
    float64 CPU tensors without gradients, else the same functions element-wise on the tensors.
    """
    from . import reprojection_jit as rows  # deferred: numba (compiled kernel, core/jit.py)

    R_i, t_i, s_i = pose_components(T_WCi)
    R_j, t_j, s_j = pose_components(T_WCj)
    d = inv_depth

    # Pose-level quantities (once per pose pair when poses are shared, else once per row).
    R_jT = R_j.transpose(-1, -2)
    M = s_i[..., None, None] * (R_jT @ R_i)  # source unit-depth ray -> target direction
    b = (R_jT @ (t_i - t_j)[..., None])[..., 0]  # d(Q)/dd: source centre seen from the target
    R_tj = b_lam = None
    if T_CtCj is not None:
        R_tj, t_tj = _as_rigid(T_CtCj, t_i)
        M = R_tj @ M
        b_lam = s_j[..., None] * t_tj  # metric extrinsic translation in units of frame j
        b = (R_tj @ b[..., None])[..., 0] + b_lam
    if pair_index is not None:
        _check_pairs(pair_index, uv_i, M, b, s_j)
    if _compiled(uv_i, d, M, b, s_j, K_i, K_t, rows_ok, b_lam, R_tj=R_tj):
        return _transfer_compiled(rows.transfer_rows, uv_i, d, K_i, K_t, M, b, s_j, R_tj, b_lam, min_depth,
                                  jacobians, rows_ok, pair_index)
    if pair_index is not None:  # each pair's quantities gathered to its rows: the same values as the loop's
        pairs = (int(M.shape[0]),)
        if len(pair_index) and not (0 <= int(pair_index.min()) and int(pair_index.max()) < pairs[0]):
            raise IndexError("reprojection: a row's pose pair or intrinsics index is out of range")
        M, b, s_j = (x.expand(pairs + x.shape[len(x.shape) - tail:])[pair_index]
                     for x, tail in ((M, 2), (b, 1), (s_j, 0)))
        b_lam = None if b_lam is None else b_lam.expand(pairs + (POINT_DIM,))[pair_index]

    # Row-level, element-wise: Q = M p + d b with p = [px, py, 1] (homogeneous target-camera point).
    px, py = _rays(uv_i, K_i)
    m0, m1, m2 = M.unbind(-2)  # rows of M
    Qx, Qy, Qz = rows.target_point.py_func(*m0.unbind(-1), *m1.unbind(-1), *m2.unbind(-1), *b.unbind(-1), px, py, d)
    fx, fy, cx, cy = K_t.unbind(-1)
    in_front = (Qz > 0) & (Qz > min_depth * d * s_j)  # target depth Q_z / (d s_j) above min_depth
    valid = torch.isfinite(d) & (d >= 0) & in_front & torch.isfinite(Qx) & torch.isfinite(Qy)
    one = torch.ones((), dtype=Qz.dtype, device=Qz.device)
    zero = torch.zeros((), dtype=Qz.dtype, device=Qz.device)
    inv_z = 1.0 / torch.where(valid, Qz, one)
    xn, yn, u, v = rows.projection.py_func(Qx, Qy, inv_z, fx, fy, cx, cy)
    uv = torch.stack((u, v), dim=-1)
    valid = valid & torch.isfinite(uv).all(-1) & torch.isfinite(xn * inv_z) & torch.isfinite(yn * inv_z)
    if rows_ok is not None:
        valid = valid & rows_ok
    if not jacobians:
        return uv, valid, None

    # Make every factor finite and the projection Jacobian A = d(uv)/dQ zero on invalid rows:
    # rows of A are a0 = fx/Qz [1, 0, -xn], a1 = fy/Qz [0, 1, -yn].
    fx_iz = torch.where(valid, fx * inv_z, zero)
    fy_iz = torch.where(valid, fy * inv_z, zero)
    xn = torch.where(valid, xn, zero)
    yn = torch.where(valid, yn, zero)
    px = torch.where(valid, px, zero)
    py = torch.where(valid, py, zero)
    d = torch.where(valid, d, zero)

    # B = A M = d uv / d(source ray); J_d = A b.
    *B, J_d0, J_d1 = rows.projection_rows.py_func(fx_iz, fy_iz, xn, yn, *m0.unbind(-1), *m1.unbind(-1),
                                                  *m2.unbind(-1), *b.unbind(-1))
    J_d = torch.stack((J_d0, J_d1), dim=-1)
    J_Ti = torch.stack(rows.source_row.py_func(*B[:POINT_DIM], px, py, d)
                       + rows.source_row.py_func(*B[POINT_DIM:], px, py, d), dim=-1).unflatten(-1, (PIXEL_DIM, SIM3_DOF))

    ds_j = d * s_j
    z = torch.zeros_like(fx_iz)
    if T_CtCj is None:
        e = rows.target_rows.py_func(torch.where(valid, fx, zero), torch.where(valid, fy, zero), fx_iz, fy_iz, xn, yn,
                                     ds_j)
        entries = [z] * (PIXEL_DIM * SIM3_DOF)
        n = rows.TARGET_ROW_ENTRIES
        for c in range(n):
            entries[rows.TARGET_U_COLUMNS[c]] = e[c]
            entries[SIM3_DOF + rows.TARGET_V_COLUMNS[c]] = e[n + c]
    else:
        # q = Q - d b_lam (Q zero on invalid rows); the extrinsic's rotation and translation per row
        assert R_tj is not None and b_lam is not None  # set above with T_CtCj
        q = [torch.where(valid, Qc, zero) - d * b_lam[..., c] for c, Qc in enumerate((Qx, Qy, Qz))]
        ext = (*R_tj.reshape(R_tj.shape[:-2] + (POINT_DIM * POINT_DIM,)).unbind(-1), *b_lam.unbind(-1), d, ds_j)
        entries = list(rows.extrinsic_row.py_func(fx_iz, z, -fx_iz * xn, *q, *ext)
                       + rows.extrinsic_row.py_func(z, fy_iz, -fy_iz * yn, *q, *ext))
    J_Tj = torch.stack(torch.broadcast_tensors(*entries), dim=-1).unflatten(-1, (PIXEL_DIM, SIM3_DOF))
    return uv, valid, (J_Ti, J_Tj, J_d)


def _check_pairs(pair_index: torch.Tensor, uv_i: torch.Tensor, M: torch.Tensor, b: torch.Tensor,
                 s_j: torch.Tensor) -> None:
    """``pair_index``'s contract: one integer per row of ``(n, 2)`` source pixels, into ``G`` pose pairs
    (``M (G, 3, 3)``, ``b (G, 3)``, ``s_j`` ``(G,)`` or one scale); the range is checked where it is read."""
    if pair_index.dim() != 1 or pair_index.dtype == torch.bool or pair_index.is_floating_point():
        raise DataError(f"reproject: pair_index must be a 1-D integer tensor, got {pair_index.dtype} "
                        f"{tuple(pair_index.shape)}")
    if uv_i.dim() != 2 or uv_i.shape[0] != pair_index.shape[0]:
        raise DataError(f"reproject: pair_index has {pair_index.shape[0]} entries for source pixels of shape "
                        f"{tuple(uv_i.shape)} (one per row of (n, 2) pixels)")
    if M.dim() != 3 or b.shape[:-1] != M.shape[:1] or s_j.dim() > 1 or (s_j.dim() == 1 and s_j.shape != M.shape[:1]):
        raise DataError(f"reproject: pair_index needs one batch dimension of pose pairs, got {tuple(M.shape[:-2])}")


def _compiled(*tensors: torch.Tensor | None, R_tj: torch.Tensor | None) -> bool:
    """Whether the rows take the compiled loop: every tensor float64 (bool for masks) on the CPU, and no
    gradient to follow; one fixed extrinsic rotation ``R_tj`` at most."""
    present = [x for x in (*tensors, R_tj) if x is not None]
    if any(x.device.type != "cpu" or (x.dtype != torch.float64 and x.dtype != torch.bool) for x in present):
        return False
    if torch.is_grad_enabled() and any(x.requires_grad for x in present):
        return False
    return R_tj is None or R_tj.dim() == 2


def _broadcast(*shapes: tuple[int, ...]) -> tuple[int, ...]:
    """The broadcast of batch shapes; the common cases (equal shapes, or scalars) without numpy's
    general rule, which costs more than a small edge's rows."""
    out: tuple[int, ...] = ()
    for shape in shapes:
        shape = tuple(shape)
        if shape == out or not shape:
            continue
        out = shape if not out else tuple(np.broadcast_shapes(out, shape))
    return out


def _transfer_compiled(
    transfer_rows: Callable[..., tuple], uv_i: torch.Tensor, d: torch.Tensor, K_i: torch.Tensor, K_t: torch.Tensor,
    M: torch.Tensor, b: torch.Tensor, s_j: torch.Tensor, R_tj: torch.Tensor | None, b_lam: torch.Tensor | None,
    min_depth: float, jacobians: bool, rows_ok: torch.Tensor | None, pair_index: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None]:
    """:func:`_transfer` through the compiled loop: every operand broadcast to the rows' batch shape (pose
    and intrinsics operands by an index per row, not copied per row) and the outputs shaped back."""
    pose_batch = _broadcast(M.shape[:-2], b.shape[:-1], s_j.shape, () if b_lam is None else b_lam.shape[:-1])
    k_batch = _broadcast(K_i.shape[:-1], K_t.shape[:-1])
    batch = _broadcast(uv_i.shape[:-1], d.shape, () if pair_index is not None else pose_batch, k_batch,
                       () if rows_ok is None else rows_ok.shape)
    n = math.prod(batch)

    def rows_of(x: torch.Tensor, tail: tuple[int, ...], shape: tuple[int, ...]) -> np.ndarray:
        if x.shape != shape + tail:
            x = x.expand(shape + tail)
        return x.reshape((math.prod(shape),) + tail).contiguous().numpy()

    def index_of(shape: tuple[int, ...]) -> np.ndarray:
        if not shape:
            return np.zeros(n, np.intp)
        if shape == batch:
            return np.arange(n)
        # a writeable copy: numba compiles a read-only array (a broadcast view) as another type
        return np.broadcast_to(np.arange(math.prod(shape)).reshape(shape), batch).reshape(n).copy()

    k_index = index_of(k_batch)
    pose_index = index_of(pose_batch) if pair_index is None else pair_index.to(torch.int64).contiguous().numpy()
    ok = np.ones(n, np.bool_) if rows_ok is None else rows_of(rows_ok, (), batch)
    intrinsics = (rows_of(K_i, (INTRINSICS,), k_batch), k_index, rows_of(K_t, (INTRINSICS,), k_batch), k_index)
    pose_pairs = (rows_of(M, (POINT_DIM, POINT_DIM), pose_batch), rows_of(b, (POINT_DIM,), pose_batch),
                  rows_of(s_j, (), pose_batch), pose_index)
    extrinsic = (_EYE3 if R_tj is None else R_tj.contiguous().numpy(),
                 _NO_B_LAM if b_lam is None else rows_of(b_lam, (POINT_DIM,), pose_batch), R_tj is not None)
    uv, valid, J_Ti, J_Tj, J_d = transfer_rows(rows_of(uv_i, (PIXEL_DIM,), batch), rows_of(d, (), batch), ok,
                                               *intrinsics, *pose_pairs, *extrinsic, float(min_depth), bool(jacobians))
    uv_t, valid_t = torch.from_numpy(uv).reshape(batch + (PIXEL_DIM,)), torch.from_numpy(valid).reshape(batch)
    if not jacobians:
        return uv_t, valid_t, None
    return uv_t, valid_t, (torch.from_numpy(J_Ti).reshape(batch + (PIXEL_DIM, SIM3_DOF)),
                           torch.from_numpy(J_Tj).reshape(batch + (PIXEL_DIM, SIM3_DOF)), torch.from_numpy(J_d).reshape(batch + (PIXEL_DIM,)))


#: the compiled loop's extrinsic operands when there is none (it reads them only with an extrinsic)
_EYE3 = np.eye(POINT_DIM)
_NO_B_LAM = np.zeros((1, POINT_DIM))


def _rays(uv: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``x, y`` of the unit-depth ray ``p = [x, y, 1]`` of pixels ``uv`` (see ``camera.pixel_rays``)."""
    u, v = uv.unbind(-1)
    fx, fy, cx, cy = K.unbind(-1)
    return (u - cx) / fx, (v - cy) / fy


def _zero(x: torch.Tensor, valid: torch.Tensor, n_trailing: int) -> torch.Tensor:
    mask = valid.reshape(valid.shape + (1,) * n_trailing)
    return torch.where(mask, x, torch.zeros((), dtype=x.dtype, device=x.device))


def reproject(
    uv_i: torch.Tensor,
    inv_depth: torch.Tensor,
    T_WCi: PoseLike,
    T_WCj: PoseLike,
    K_i: torch.Tensor,
    K_j: torch.Tensor | None = None,
    *,
    T_CtCj: Transform | None = None,
    config: ReprojectionConfig | None = None,
    pair_index: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Predicted pixel coordinates of source pixels in keyframe ``j`` (what a frontend tracks from).

    Args:
        uv_i: ``(..., 2)`` source pixels of keyframe ``i``.
        inv_depth: ``(...)`` their inverse depths.
        T_WCi, T_WCj: camera-to-world Sim(3) poses (batch shapes broadcast against the rows).
        K_i: ``(..., 4)`` source intrinsics ``[fx, fy, cx, cy]``; ``K_j`` target intrinsics (default ``K_i``).
        T_CtCj: optional fixed metric 4x4 transform from keyframe ``j``'s camera to the observing
            camera (stereo: ``StereoRig.T_CRCL``).
        pair_index: optional ``(n,)``: rows ``(n, ...)`` where row ``r`` uses the pose pair ``pair_index[r]``
            of ``(G,)`` poses (a block's edges in one call), instead of broadcasting.

    Returns:
        ``uv_j (..., 2)`` (zero where invalid) and ``valid (...)``.
    """
    config = config or ReprojectionConfig()
    K_t = K_i if K_j is None else K_j
    uv, valid, _ = _transfer(uv_i, inv_depth, T_WCi, T_WCj, K_i, K_t, T_CtCj, config.min_depth, jacobians=False,
                             pair_index=pair_index)
    return _zero(uv, valid, 1), valid


def reproject_inv_depth(
    uv_i: torch.Tensor,
    inv_depth: torch.Tensor,
    T_WCi: PoseLike,
    T_WCj: PoseLike,
    K_i: torch.Tensor,
    uv_target: torch.Tensor,
    K_j: torch.Tensor | None = None,
    *,
    T_CtCj: Transform | None = None,
    config: ReprojectionConfig | None = None,
    pair_index: torch.Tensor | None = None,
) -> ReprojectionResult:
    """Inverse-depth reprojection residuals and Jacobians (DROID-SLAM eq. 4, DPV-SLAM eq. 3).

    Args: as :func:`reproject`, plus ``uv_target (..., 2)``, the observed pixels in keyframe ``j``
    (e.g. the source pixel's current reprojection plus the network's flow revision).

    Returns:
        :class:`ReprojectionResult`; ``residual = pi(T_CtCj T_WCj^-1 T_WCi X_i) - uv_target``.
        Weights are not applied: the caller whitens rows with its confidences.
    """
    config = config or ReprojectionConfig()
    K_t = K_i if K_j is None else K_j
    uv, valid, jac = _transfer(
        uv_i, inv_depth, T_WCi, T_WCj, K_i, K_t, T_CtCj, config.min_depth, jacobians=True,
        rows_ok=torch.isfinite(uv_target).all(-1), pair_index=pair_index,
    )
    J_Ti, J_Tj, J_d = jac
    residual = _zero(uv - uv_target, valid, 1)
    return ReprojectionResult(residual=residual, J_Ti=J_Ti, J_Tj=J_Tj, J_d=J_d, valid=valid)


def reproject_edges(
    uv_i: torch.Tensor,
    inv_depth: torch.Tensor,
    T_WCi: PoseLike,
    T_WCj: PoseLike,
    K: torch.Tensor,
    uv_target: torch.Tensor | None = None,
    *,
    right: torch.Tensor | None = None,
    K_right: torch.Tensor | None = None,
    T_CRCL: Transform | None = None,
    config: ReprojectionConfig | None = None,
) -> ReprojectionResult | tuple[torch.Tensor, torch.Tensor]:
    """Edges into the left image of keyframe ``j`` or, where ``right``, into its right image: the
    one place that splits a batch of edges by image side.

    A left edge is observed with the left intrinsics ``K``; a right edge with ``K_right`` through
    the rig's fixed metric left-to-right extrinsic ``T_CRCL`` (:func:`reproject_inv_depth`'s
    ``T_CtCj``). The source pixels are always in the left image (intrinsics ``K``).

    Args:
        uv_i, inv_depth, T_WCi, T_WCj: as :func:`reproject`, every one with the same leading batch
            dimension ``B`` (poses as ``(R, t, s)`` tuples or Sim3/SE3-like objects; trailing batch
            dimensions broadcast as usual).
        K: ``(4,)`` left intrinsics, shared by all edges.
        uv_target: ``(B, ..., 2)`` observed pixels; None: predictions only, no Jacobians.
        right: ``(B,)`` bool, the edge's target is the right image (None: all left).
        K_right: ``(4,)`` right intrinsics; ``T_CRCL`` ``(4, 4)`` left-to-right extrinsic (needed
            when any edge is a right edge).
        config: validity threshold.

    Returns:
        with ``uv_target``: :class:`ReprojectionResult` (as :func:`reproject_inv_depth`); without:
        ``(uv_j, valid)`` (as :func:`reproject`). Rows keep the input order; a batch with one
        image side only (or sorted left edges first) is evaluated without gathers.
    """
    B = int(uv_i.shape[0])
    right = None if right is None else torch.as_tensor(right, dtype=torch.bool, device=uv_i.device)
    n_right = 0 if right is None else int(right.sum())
    if n_right and (K_right is None or T_CRCL is None):
        raise DataError("reproject_edges: right-image edges need K_right and T_CRCL")

    def side(sel: slice | torch.Tensor, K_t: torch.Tensor, T_ext: Transform | None) -> tuple:
        Ti = tuple(x[sel] for x in pose_components(T_WCi))
        Tj = tuple(x[sel] for x in pose_components(T_WCj))
        if uv_target is None:
            return reproject(uv_i[sel], inv_depth[sel], Ti, Tj, K, K_t, T_CtCj=T_ext, config=config)
        res = reproject_inv_depth(uv_i[sel], inv_depth[sel], Ti, Tj, K, uv_target[sel], K_t, T_CtCj=T_ext,
                                  config=config)
        return res.residual, res.J_Ti, res.J_Tj, res.J_d, res.valid

    def packed(parts: tuple):
        if uv_target is None:
            return parts
        return ReprojectionResult(*parts)

    everything = slice(None)
    if n_right == 0:
        return packed(side(everything, K, None))
    if n_right == B:
        return packed(side(everything, K_right, T_CRCL))
    n_left = B - n_right
    if not bool(right[:n_left].any()):  # left edges first: contiguous slices, joined
        left_parts = side(slice(0, n_left), K, None)
        right_parts = side(slice(n_left, B), K_right, T_CRCL)
        return packed(tuple(torch.cat([a, b]) for a, b in zip(left_parts, right_parts)))
    out = None
    for mask, K_t, T_ext in ((~right, K, None), (right, K_right, T_CRCL)):
        parts = side(mask, K_t, T_ext)
        if out is None:
            out = [torch.zeros((B,) + tuple(p.shape[1:]), dtype=p.dtype, device=p.device) for p in parts]
        for full, p in zip(out, parts):
            full[mask] = p
    return packed(tuple(out))


def flatten_patches(uv_patches: torch.Tensor, inv_depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows of DPV-SLAM patches for :func:`reproject_inv_depth`.

    Args:
        uv_patches: ``(..., P, p, p, 2)`` pixel coordinates of the ``p x p`` pixels of ``P`` patches.
        inv_depth: ``(..., P)`` one inverse depth per patch.

    Returns:
        ``uv (..., P * p * p, 2)`` with patch ``k``'s pixel ``(a, b)`` at row ``k p^2 + a p + b``,
        and ``inv_depth (..., P * p * p)`` (each patch's depth repeated over its rows).
    """
    *batch, P, p, p2, two = uv_patches.shape
    if p != p2 or two != 2 or tuple(inv_depth.shape[-1:]) != (P,):
        raise DataError(f"flatten_patches: got uv {tuple(uv_patches.shape)} and depths {tuple(inv_depth.shape)}")
    uv = uv_patches.reshape(*batch, P * p * p, 2)
    d = inv_depth[..., :, None].expand(*inv_depth.shape, p * p).reshape(*inv_depth.shape[:-1], P * p * p)
    return uv, d
