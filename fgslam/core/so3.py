"""The rotation group SO(3) in torch (float32 / float64, any leading batch shape ``...``): skew
matrices, Rodrigues' exponential, a logarithm stable at angles near pi (equal to gtsam's
``Rot3.Logmap``), and the projection of near-rotations onto SO(3); the rotation part of
:mod:`fgslam.core.lie`'s SE(3) and Sim(3).

Near zero angle the coefficient functions switch to their Taylor series, so identity and
near-identity rotations give no NaN.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

# Below this rotation angle (radians) the trigonometric coefficient functions switch to their Taylor
# series (truncated after theta^4: truncation error < 1e-16 relative in float64, < 1e-9 in float32).
_SMALL_ANGLE = {torch.float64: 1e-2, torch.float32: 1e-1}
# sin(theta) below which (with cos(theta) < 0) so3_log takes the axis from the symmetric part of R.
_NEAR_PI_SIN = 0.5


def small_angle(dtype: torch.dtype) -> float:
    """Rotation angle (rad) below which the coefficient functions of ``dtype`` use their series."""
    return _SMALL_ANGLE.get(dtype, _SMALL_ANGLE[torch.float32])


def skew(v: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix ``[v]x`` (..., 3, 3) with ``[v]x y = v x y`` for v (..., 3)."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(v.shape[:-1] + (3, 3))


def _vee(M: torch.Tensor) -> torch.Tensor:
    """``vee(M - M^T) / 2`` for a (..., 3, 3) matrix (the axial vector of its skew part)."""
    return 0.5 * torch.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1
    )


def batch_eye(shape: Sequence[int], n: int, like: torch.Tensor) -> torch.Tensor:
    """``(*shape, n, n)`` identity matrices (an expanded view) of ``like``'s dtype and device."""
    return torch.eye(n, dtype=like.dtype, device=like.device).expand(*shape, n, n)


def _so3_coeffs(theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``A = sin(theta)/theta`` and ``B = (1 - cos theta)/theta^2`` with a series near 0."""
    small = theta < small_angle(theta.dtype)
    th = torch.where(small, torch.ones_like(theta), theta)
    t2 = theta * theta
    A = torch.where(small, 1 - t2 / 6 * (1 - t2 / 20), torch.sin(th) / th)
    half = torch.sin(0.5 * th) / th
    B = torch.where(small, 0.5 - t2 / 24 * (1 - t2 / 30), 2 * half * half)
    return A, B


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``exp([w]x)`` (..., 3, 3) of a rotation vector w (..., 3) (Rodrigues)."""
    theta = torch.linalg.vector_norm(w, dim=-1)
    A, B = _so3_coeffs(theta)
    W = skew(w)
    return batch_eye(w.shape[:-1], 3, w) + A[..., None, None] * W + B[..., None, None] * (W @ W)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector w (..., 3) with ``so3_exp(w) = R``, angle in [0, pi] (equal to gtsam Rot3.Logmap).

    The angle is ``atan2(sin, cos)`` (well conditioned everywhere); near pi the axis comes from the
    symmetric part ``(R + R^T)/2 - cos I = (1 - cos) n n^T`` with the sign of the skew part.
    """
    v = _vee(R)  # = sin(theta) n
    sin_t = torch.linalg.vector_norm(v, dim=-1)
    cos_t = 0.5 * (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1)
    theta = torch.atan2(sin_t, cos_t)
    # Generic / small angle: w = theta / sin(theta) * v.
    small = theta < small_angle(R.dtype)
    t2 = theta * theta
    safe_sin = torch.where(small, torch.ones_like(sin_t), sin_t)
    factor = torch.where(small, 1 + t2 / 6 * (1 + 7 * t2 / 60), theta / safe_sin)
    w_generic = factor[..., None] * v
    # Near pi: axis from the largest column of the symmetric part.
    near_pi = (cos_t < 0) & (sin_t < _NEAR_PI_SIN)
    S = 0.5 * (R + R.transpose(-1, -2)) - cos_t[..., None, None] * batch_eye(R.shape[:-2], 3, R)
    k = S.diagonal(dim1=-2, dim2=-1).argmax(-1)
    col = torch.gather(S, -1, k[..., None, None].expand(*S.shape[:-1], 1)).squeeze(-1)
    n = col / torch.linalg.vector_norm(col, dim=-1, keepdim=True).clamp_min(torch.finfo(R.dtype).tiny)
    sign = torch.where((n * v).sum(-1) < 0, -torch.ones_like(theta), torch.ones_like(theta))
    w_pi = (sign * theta)[..., None] * n
    return torch.where(near_pi[..., None], w_pi, w_generic)


def project_so3(A: torch.Tensor) -> torch.Tensor:
    """Nearest rotation matrix (Frobenius) to each (..., 3, 3) matrix, via SVD."""
    U, _, Vh = torch.linalg.svd(A)
    d = torch.sign(torch.linalg.det(U @ Vh))
    D = torch.ones(*A.shape[:-2], 3, dtype=A.dtype, device=A.device)
    D[..., 2] = d
    return (U * D[..., None, :]) @ Vh
