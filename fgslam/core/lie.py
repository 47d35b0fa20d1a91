"""Batched Lie groups SE(3) and Sim(3) in torch (float32 / float64, any leading batch shape ``...``).

Conventions (the standard ones, mapped exactly onto gtsam's at every gtsam boundary):

* ``SE3(R, t)`` acts as ``X -> R X + t``; matrix ``[[R, t], [0, 1]]``; tangent ``[w(3), v(3)]``
  equal to ``gtsam.Pose3.Logmap``.
* ``Sim3(R, t, s)`` acts as ``X -> s R X + t``; matrix ``[[s R, t], [0, 1]]``. It corresponds to
  ``gtsam.Similarity3(Rot3(R), t / s, s)`` (gtsam stores ``[[R, t_g], [0, 1/s]]`` and
  ``transformFrom(p) = s (R p + t_g)``). Tangent ``xi = [w(3), u(3), lambda]`` equal to
  ``gtsam.Similarity3.Logmap``: ``Exp(xi) = expm([[skew(w) + lambda I, u], [0, 0]])``, i.e.
  ``R = exp(skew(w))``, ``s = e^lambda``, ``t = V(w, lambda) u`` with
  ``V = int_0^1 exp(tau (skew(w) + lambda I)) dtau``. (Multiplying gtsam's matrix by ``s`` is a group
  isomorphism onto the standard form; its algebra map adds the central ``lambda I``, so Logmap,
  AdjointMap and the Lie bracket are the same in both forms.)
* Perturbations are on the RIGHT: ``T.retract(xi) = T @ Exp(xi)``, ``T.local(U) = Log(T^-1 U)``.
* ``adjoint()`` follows gtsam's ``AdjointMap``: ``T Exp(xi) T^-1 = Exp(Ad_T xi)``.

All closed forms have series branches near zero angle / zero log-scale, and ``so3_log`` is stable
at angles near pi, so identity and near-identity elements give no NaN. The rotation part (``skew``,
``so3_exp``, ``so3_log``) is :mod:`fgslam.core.so3`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from .so3 import batch_eye, project_so3, skew, small_angle, so3_exp, so3_log

# |lambda| below which the moments m_k(lambda) = int_0^1 tau^k e^(lambda tau) dtau use their power
# series (30 terms: truncation < 1e-23); above it the upward recurrence amplifies rounding <= 6!/2^6.
_SERIES_LAMBDA = 2.0
_SERIES_TERMS = 30
# Scaling and squaring of phi1 (right Jacobians): the scaled matrix has 1-norm <= 0.5 and its Taylor
# series is truncated after degree 14 (remainder < 0.5^15/15! ~ 2e-17 relative).
_PHI_SCALED_NORM = 0.5
_PHI_TAYLOR_DEGREE = 14


def _moments(lam: torch.Tensor, kmax: int) -> list[torch.Tensor]:
    """``m_k(lam) = int_0^1 tau^k exp(lam tau) dtau`` for k = 0..kmax (power series or recurrence)."""
    series = lam.abs() < _SERIES_LAMBDA
    ls = torch.where(series, lam, torch.zeros_like(lam))
    n = torch.arange(_SERIES_TERMS, dtype=lam.dtype, device=lam.device)
    terms = torch.cat([torch.ones_like(lam)[..., None], torch.cumprod(ls[..., None] / n[1:], -1)], -1)  # lam^n / n!
    lr = torch.where(series, torch.ones_like(lam), lam)
    e = torch.exp(lr)
    m_rec = torch.expm1(lr) / lr
    out = []
    for k in range(kmax + 1):
        if k > 0:
            m_rec = (e - k * m_rec) / lr
        m_ser = (terms / (n + (k + 1))).sum(-1)  # sum_n lam^n / (n! (n + k + 1)), one reduction (few kernels)
        out.append(torch.where(series, m_ser, m_rec))
    return out


def _sim3_v_coeffs(theta: torch.Tensor, lam: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Coefficients of ``V = a I + b W + c W^2`` (W = [w]x, theta = |w|) for Sim(3), V's definition above.

    With f(z) = (e^z - 1)/z: a = f(lam), b = Im f(lam + i theta)/theta,
    c = (f(lam) - Re f(lam + i theta))/theta^2; for small theta the series
    b = m1 - theta^2 m3/6 + theta^4 m5/120, c = m2/2 - theta^2 m4/24 + theta^4 m6/720.
    """
    m = _moments(lam, 6)
    a = m[0]
    small = theta < small_angle(theta.dtype)
    t2 = theta * theta
    b_ser = m[1] - t2 * m[3] / 6 + t2 * t2 * m[5] / 120
    c_ser = m[2] / 2 - t2 * m[4] / 24 + t2 * t2 * m[6] / 720
    th = torch.where(small, torch.ones_like(theta), theta)
    e = torch.exp(lam)
    ec, es = e * torch.cos(th), e * torch.sin(th)
    den = lam * lam + th * th
    P = (lam * (ec - 1) + th * es) / den  # Re f(lam + i theta)
    Q = (lam * es - th * (ec - 1)) / den  # Im f(lam + i theta)
    b = torch.where(small, b_ser, Q / th)
    c = torch.where(small, c_ser, (a - P) / (th * th))
    return a, b, c


def _v_apply(w: torch.Tensor, coeffs: tuple[torch.Tensor, ...], x: torch.Tensor) -> torch.Tensor:
    """``(a I + b W + c W^2) x`` via cross products."""
    a, b, c = coeffs
    wx = torch.linalg.cross(w, x, dim=-1)
    wwx = torch.linalg.cross(w, wx, dim=-1)
    return a[..., None] * x + b[..., None] * wx + c[..., None] * wwx


def _v_inverse_coeffs(theta: torch.Tensor, coeffs: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
    """Coefficients of ``V^-1 = alpha I + beta W + gamma W^2`` (uses W^3 = -theta^2 W)."""
    a, b, c = coeffs
    t2 = theta * theta
    d = a - t2 * c
    det = d * d + t2 * b * b
    return 1 / a, -b / det, (b * b - c * d) / (a * det)


# Index suffixes that keep the trailing vector / matrix dimensions when indexing the batch.
_V = (slice(None),)
_M = (slice(None), slice(None))


def _batch_index(idx) -> tuple:
    """Batch index as a tuple (ints, slices, tensors, ``...``, ``None`` all index batch dims only)."""
    return idx if isinstance(idx, tuple) else (idx,)


def _batch_shape(*shapes: torch.Size) -> torch.Size:
    # Fast path for the common equal-shape case: torch.broadcast_shapes imports sympy on first use
    # (about 2 s of CPU), which would land inside a SLAM frame loop.
    if all(shape == shapes[0] for shape in shapes[1:]):
        return torch.Size(shapes[0])
    return torch.broadcast_shapes(*shapes)


class SE3:
    """Batch of rigid transforms ``X -> R X + t``; fields ``R`` (..., 3, 3), ``t`` (..., 3).

    Tangent ``[w, v]`` (gtsam Pose3 order), right perturbation.
    """

    dof = 6

    def __init__(self, R: torch.Tensor, t: torch.Tensor):
        if R.shape[-2:] != (3, 3) or t.shape[-1:] != (3,):
            raise ValueError(f"SE3 needs R (...,3,3) and t (...,3), got {tuple(R.shape)} and {tuple(t.shape)}")
        self.R = R
        self.t = t

    # ----- construction
    @staticmethod
    def identity(shape: Sequence[int] = (), dtype: torch.dtype = torch.float64, device=None) -> SE3:
        R = torch.eye(3, dtype=dtype, device=device).expand(*shape, 3, 3).clone()
        return SE3(R, torch.zeros(*shape, 3, dtype=dtype, device=device))

    @staticmethod
    def exp(xi: torch.Tensor) -> SE3:
        """``Exp([w, v])``: R = exp([w]x), t = V(w) v (equals gtsam Pose3.Expmap)."""
        w, v = xi[..., :3], xi[..., 3:6]
        theta = torch.linalg.vector_norm(w, dim=-1)
        coeffs = _sim3_v_coeffs(theta, torch.zeros_like(theta))
        return SE3(so3_exp(w), _v_apply(w, coeffs, v))

    @staticmethod
    def from_matrix(M: torch.Tensor) -> SE3:
        """From homogeneous (..., 4, 4) matrices; the rotation block is projected onto SO(3)."""
        return SE3(project_so3(M[..., :3, :3]), M[..., :3, 3].clone())

    # ----- group operations
    def log(self) -> torch.Tensor:
        """Tangent ``[w, v]`` (..., 6) with ``SE3.exp(xi) == self``."""
        shape = self.shape
        w = so3_log(self.R.expand(*shape, 3, 3))
        theta = torch.linalg.vector_norm(w, dim=-1)
        inv = _v_inverse_coeffs(theta, _sim3_v_coeffs(theta, torch.zeros_like(theta)))
        return torch.cat([w, _v_apply(w, inv, self.t.expand(*shape, 3))], -1)

    def compose(self, other: SE3) -> SE3:
        return SE3(self.R @ other.R, (self.R @ other.t[..., None])[..., 0] + self.t)

    def __matmul__(self, other: SE3) -> SE3:
        return self.compose(other)

    def inverse(self) -> SE3:
        Rt = self.R.transpose(-1, -2)
        return SE3(Rt, -(Rt @ self.t[..., None])[..., 0])

    def act(self, X: torch.Tensor) -> torch.Tensor:
        """``R X + t`` for points X (..., 3) (broadcast against the batch)."""
        return (self.R @ X[..., None])[..., 0] + self.t

    def act_jacobian(self, X: torch.Tensor) -> torch.Tensor:
        """``d(T Exp(xi) X)/dxi`` at xi = 0: ``R [-[X]x, I]`` (..., 3, 6)."""
        eye = batch_eye(X.shape[:-1], 3, X)
        return self.R @ torch.cat([-skew(X), eye], -1)

    def adjoint(self) -> torch.Tensor:
        """gtsam ``AdjointMap``: ``[[R, 0], [[t]x R, R]]`` (..., 6, 6)."""
        Z = torch.zeros_like(self.R)
        top = torch.cat([self.R, Z], -1)
        bottom = torch.cat([skew(self.t) @ self.R, self.R], -1)
        return torch.cat([top, bottom], -2)

    def matrix(self) -> torch.Tensor:
        M = torch.zeros(*self.shape, 4, 4, dtype=self.dtype, device=self.R.device)
        M[..., :3, :3] = self.R
        M[..., :3, 3] = self.t
        M[..., 3, 3] = 1
        return M

    def retract(self, xi: torch.Tensor) -> SE3:
        return self @ SE3.exp(xi)

    def local(self, other: SE3) -> torch.Tensor:
        return (self.inverse() @ other).log()

    @staticmethod
    def ad(xi: torch.Tensor) -> torch.Tensor:
        """Lie-bracket matrix ``ad_xi`` (..., 6, 6) = ``[[W, 0], [[v]x, W]]`` (gtsam ``adjointMap``)."""
        W, V = skew(xi[..., :3]), skew(xi[..., 3:6])
        Z = torch.zeros_like(W)
        return torch.cat([torch.cat([W, Z], -1), torch.cat([V, W], -1)], -2)

    @staticmethod
    def right_jacobian(xi: torch.Tensor) -> torch.Tensor:
        """``J_r(xi)`` with ``Exp(xi + d) = Exp(xi) Exp(J_r d + O(d^2))`` (..., 6, 6)."""
        return _right_jacobian(SE3.ad(xi))

    @staticmethod
    def right_jacobian_inv(xi: torch.Tensor) -> torch.Tensor:
        """``J_r(xi)^-1 = d Log(Exp(xi) Exp(d)) / dd`` at d = 0 (..., 6, 6)."""
        return torch.linalg.inv(SE3.right_jacobian(xi))

    # ----- gtsam
    def to_gtsam(self):
        """``gtsam.Pose3`` for an unbatched element, else a flat list (row-major over the batch).

        Always float64; rotations of lower precision are projected onto SO(3) first."""
        import gtsam  # deferred: gtsam

        shape = self.shape
        R = _rotations_for_gtsam(self.R.detach().expand(*shape, 3, 3)).reshape(-1, 3, 3).numpy()
        t = self.t.detach().expand(*shape, 3).to(torch.float64).cpu().reshape(-1, 3).numpy()
        out = [gtsam.Pose3(gtsam.Rot3(R[i]), t[i]) for i in range(R.shape[0])]
        return out[0] if shape == () else out

    @staticmethod
    def from_gtsam(obj, dtype: torch.dtype = torch.float64) -> SE3:
        """From one ``gtsam.Pose3`` (shape ()) or a list of them (shape (N,))."""
        items = obj if isinstance(obj, (list, tuple)) else [obj]
        R = torch.as_tensor(np.stack([p.rotation().matrix() for p in items]), dtype=dtype)
        t = torch.as_tensor(np.stack([np.asarray(p.translation()) for p in items]), dtype=dtype)
        T = SE3(R, t)
        return T if isinstance(obj, (list, tuple)) else T[0]

    # ----- container
    @property
    def shape(self) -> torch.Size:
        return _batch_shape(self.R.shape[:-2], self.t.shape[:-1])

    @property
    def dtype(self) -> torch.dtype:
        return self.R.dtype

    def __getitem__(self, idx) -> SE3:
        shape, idx = self.shape, _batch_index(idx)
        return SE3(self.R.expand(*shape, 3, 3)[idx + _M], self.t.expand(*shape, 3)[idx + _V])

    def to(self, *args, **kwargs) -> SE3:
        return SE3(self.R.to(*args, **kwargs), self.t.to(*args, **kwargs))

    def __repr__(self) -> str:
        return f"SE3(shape={tuple(self.shape)}, dtype={self.dtype})"


class Sim3:
    """Batch of similarities ``X -> s R X + t``; fields ``R`` (..., 3, 3), ``t`` (..., 3), ``s`` (...).

    Tangent ``[w, u, lambda]`` (gtsam Similarity3 order, s = e^lambda), right perturbation.
    """

    dof = 7

    def __init__(self, R: torch.Tensor, t: torch.Tensor, s: torch.Tensor):
        if R.shape[-2:] != (3, 3) or t.shape[-1:] != (3,):
            raise ValueError(f"Sim3 needs R (...,3,3) and t (...,3), got {tuple(R.shape)} and {tuple(t.shape)}")
        self.R = R
        self.t = t
        self.s = torch.as_tensor(s, dtype=R.dtype, device=R.device)

    # ----- construction
    @staticmethod
    def identity(shape: Sequence[int] = (), dtype: torch.dtype = torch.float64, device=None) -> Sim3:
        R = torch.eye(3, dtype=dtype, device=device).expand(*shape, 3, 3).clone()
        t = torch.zeros(*shape, 3, dtype=dtype, device=device)
        return Sim3(R, t, torch.ones(*shape, dtype=dtype, device=device))

    @staticmethod
    def from_se3(T: SE3, s: float | torch.Tensor = 1.0) -> Sim3:
        s = torch.as_tensor(s, dtype=T.dtype, device=T.R.device).expand(T.shape).clone()
        return Sim3(T.R, T.t, s)

    @staticmethod
    def exp(xi: torch.Tensor) -> Sim3:
        """``Exp([w, u, lambda])``: R = exp([w]x), s = e^lambda, t = V(w, lambda) u (= gtsam Expmap)."""
        w, u, lam = xi[..., :3], xi[..., 3:6], xi[..., 6]
        theta = torch.linalg.vector_norm(w, dim=-1)
        coeffs = _sim3_v_coeffs(theta, lam)
        return Sim3(so3_exp(w), _v_apply(w, coeffs, u), torch.exp(lam))

    @staticmethod
    def from_matrix(M: torch.Tensor) -> Sim3:
        """From (..., 4, 4) matrices ``[[s R, t], [0, 1]]``: s = cbrt(det), R projected onto SO(3)."""
        A = M[..., :3, :3]
        s = torch.linalg.det(A).abs() ** (1.0 / 3.0)
        return Sim3(project_so3(A / s[..., None, None]), M[..., :3, 3].clone(), s)

    # ----- group operations
    def log(self) -> torch.Tensor:
        """Tangent ``[w, u, lambda]`` (..., 7) with ``Sim3.exp(xi) == self``."""
        shape = self.shape
        w = so3_log(self.R.expand(*shape, 3, 3))
        lam = torch.log(self.s).expand(shape)
        theta = torch.linalg.vector_norm(w, dim=-1)
        inv = _v_inverse_coeffs(theta, _sim3_v_coeffs(theta, lam))
        return torch.cat([w, _v_apply(w, inv, self.t.expand(*shape, 3)), lam[..., None]], -1)

    def compose(self, other: Sim3) -> Sim3:
        t = self.s[..., None] * (self.R @ other.t[..., None])[..., 0] + self.t
        return Sim3(self.R @ other.R, t, self.s * other.s)

    def __matmul__(self, other: Sim3) -> Sim3:
        return self.compose(other)

    def inverse(self) -> Sim3:
        Rt = self.R.transpose(-1, -2)
        return Sim3(Rt, -(Rt @ self.t[..., None])[..., 0] / self.s[..., None], 1 / self.s)

    def act(self, X: torch.Tensor) -> torch.Tensor:
        """``s R X + t`` for points X (..., 3) (broadcast against the batch)."""
        return self.s[..., None] * (self.R @ X[..., None])[..., 0] + self.t

    def act_jacobian(self, X: torch.Tensor) -> torch.Tensor:
        """``d(T Exp(xi) X)/dxi`` at xi = 0: ``s R [-[X]x, I, X]`` (..., 3, 7)."""
        eye = batch_eye(X.shape[:-1], 3, X)
        return self.s[..., None, None] * (self.R @ torch.cat([-skew(X), eye, X[..., None]], -1))

    def adjoint(self) -> torch.Tensor:
        """gtsam ``AdjointMap``: ``[[R, 0, 0], [[t]x R, s R, -t], [0, 0, 1]]`` (..., 7, 7)."""
        shape = self.shape
        R = self.R.expand(*shape, 3, 3)
        t = self.t.expand(*shape, 3)
        s = self.s.expand(shape)
        Ad = torch.zeros(*shape, 7, 7, dtype=self.dtype, device=R.device)
        Ad[..., :3, :3] = R
        Ad[..., 3:6, :3] = skew(t) @ R
        Ad[..., 3:6, 3:6] = s[..., None, None] * R
        Ad[..., 3:6, 6] = -t
        Ad[..., 6, 6] = 1
        return Ad

    def matrix(self) -> torch.Tensor:
        M = torch.zeros(*self.shape, 4, 4, dtype=self.dtype, device=self.R.device)
        M[..., :3, :3] = self.s[..., None, None] * self.R
        M[..., :3, 3] = self.t
        M[..., 3, 3] = 1
        return M

    def retract(self, xi: torch.Tensor) -> Sim3:
        return self @ Sim3.exp(xi)

    def local(self, other: Sim3) -> torch.Tensor:
        return (self.inverse() @ other).log()

    @staticmethod
    def ad(xi: torch.Tensor) -> torch.Tensor:
        """Lie-bracket matrix ``ad_xi`` (..., 7, 7) = ``[[W, 0, 0], [[u]x, W + lambda I, -u], [0, 0, 0]]``."""
        w, u, lam = xi[..., :3], xi[..., 3:6], xi[..., 6]
        out = torch.zeros(*xi.shape[:-1], 7, 7, dtype=xi.dtype, device=xi.device)
        W = skew(w)
        out[..., :3, :3] = W
        out[..., 3:6, :3] = skew(u)
        out[..., 3:6, 3:6] = W + lam[..., None, None] * batch_eye(xi.shape[:-1], 3, xi)
        out[..., 3:6, 6] = -u
        return out

    @staticmethod
    def right_jacobian(xi: torch.Tensor) -> torch.Tensor:
        """``J_r(xi)`` with ``Exp(xi + d) = Exp(xi) Exp(J_r d + O(d^2))`` (..., 7, 7)."""
        return _right_jacobian(Sim3.ad(xi))

    @staticmethod
    def right_jacobian_inv(xi: torch.Tensor) -> torch.Tensor:
        """``J_r(xi)^-1 = d Log(Exp(xi) Exp(d)) / dd`` at d = 0 (..., 7, 7)."""
        return torch.linalg.inv(Sim3.right_jacobian(xi))

    # ----- gtsam
    def to_gtsam(self):
        """``gtsam.Similarity3(Rot3(R), t/s, s)`` for an unbatched element, else a flat list
        (row-major over the batch); float64, lower-precision rotations projected onto SO(3)."""
        shape = self.shape
        R = _rotations_for_gtsam(self.R.detach().expand(*shape, 3, 3)).reshape(-1, 3, 3).numpy()
        t = self.t.detach().expand(*shape, 3).to(torch.float64).cpu().reshape(-1, 3).numpy()
        s = self.s.detach().expand(shape).to(torch.float64).cpu().reshape(-1).numpy()
        out = [similarity3(R[i], t[i], float(s[i])) for i in range(R.shape[0])]
        return out[0] if shape == () else out

    @staticmethod
    def from_gtsam(obj, dtype: torch.dtype = torch.float64) -> Sim3:
        """From one ``gtsam.Similarity3`` (shape ()) or a list of them (shape (N,))."""
        items = obj if isinstance(obj, (list, tuple)) else [obj]
        R = torch.as_tensor(np.stack([p.rotation().matrix() for p in items]), dtype=dtype)
        s = torch.as_tensor(np.array([p.scale() for p in items]), dtype=dtype)
        t_g = torch.as_tensor(np.stack([np.asarray(p.translation()) for p in items]), dtype=dtype)
        T = Sim3(R, s[:, None] * t_g, s)
        return T if isinstance(obj, (list, tuple)) else T[0]

    # ----- container
    @property
    def shape(self) -> torch.Size:
        return _batch_shape(self.R.shape[:-2], self.t.shape[:-1], self.s.shape)

    @property
    def dtype(self) -> torch.dtype:
        return self.R.dtype

    def __getitem__(self, idx) -> Sim3:
        shape, idx = self.shape, _batch_index(idx)
        R, t, s = self.R.expand(*shape, 3, 3), self.t.expand(*shape, 3), self.s.expand(shape)
        return Sim3(R[idx + _M], t[idx + _V], s[idx])

    def to(self, *args, **kwargs) -> Sim3:
        return Sim3(self.R.to(*args, **kwargs), self.t.to(*args, **kwargs), self.s.to(*args, **kwargs))

    def __repr__(self) -> str:
        return f"Sim3(shape={tuple(self.shape)}, dtype={self.dtype})"


def _right_jacobian(ad: torch.Tensor) -> torch.Tensor:
    """``J_r = phi1(-ad) = sum_k (-ad)^k / (k+1)! = int_0^1 exp(-tau ad) dtau`` (..., n, n).

    Scaling and squaring on the pair (E, Phi) = (exp(A), phi1(A)): with A = -ad / 2^m small, both
    come from a Taylor series; then m doublings phi1(2A) = (I + exp(A)) phi1(A) / 2, exp(2A) = exp(A)^2.
    """
    n = ad.shape[-1]
    A = -ad
    norm = torch.linalg.matrix_norm(A, ord=1).max().item() if A.numel() else 0.0
    m = max(0, math.ceil(math.log2(norm / _PHI_SCALED_NORM))) if norm > _PHI_SCALED_NORM else 0
    A = A / (2.0**m)
    eye = batch_eye(ad.shape[:-2], n, ad)
    term, E, Phi = eye, eye.clone(), eye.clone()
    for k in range(1, _PHI_TAYLOR_DEGREE + 1):
        term = term @ A / k
        E = E + term
        Phi = Phi + term / (k + 1)
    for _ in range(m):
        Phi = 0.5 * (Phi + E @ Phi)
        E = E @ E
    return Phi


def _rotations_for_gtsam(R: torch.Tensor) -> torch.Tensor:
    """float64 CPU rotations; lower-precision ones are re-projected onto SO(3) (gtsam.Rot3 keeps the
    matrix as given, and a float32-rounded rotation is orthonormal only to ~1e-7)."""
    if R.dtype == torch.float64:
        return R.cpu()
    return project_so3(R.to(torch.float64)).cpu()



def stack(elements: Sequence[SE3] | Sequence[Sim3], dim: int = 0) -> SE3 | Sim3:
    """Stack same-type group elements of equal batch shape along a new batch dimension ``dim``."""
    if not elements:
        raise ValueError("stack needs at least one element")
    first = elements[0]
    if any(type(e) is not type(first) for e in elements):
        raise TypeError("stack: all elements must be of the same group type")
    if dim < 0:
        dim += len(first.shape) + 1
    R = torch.stack([e.R.expand(*e.shape, 3, 3) for e in elements], dim)
    t = torch.stack([e.t.expand(*e.shape, 3) for e in elements], dim)
    if isinstance(first, Sim3):
        return Sim3(R, t, torch.stack([e.s.expand(e.shape) for e in elements], dim))
    return SE3(R, t)


def sim3_matrix_parts(M: np.ndarray, project: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R, t, s)`` of one Sim(3) matrix ``[[s R, t], [0, 1]]`` in numpy (for per-frame code that
    stays out of torch). ``s = cbrt(|det(s R)|)``; with ``project`` the rotation is replaced by the
    nearest one in SO(3) (SVD), so that repeated compositions do not accumulate rounding errors."""
    M = np.asarray(M, dtype=np.float64)
    s = float(np.cbrt(abs(np.linalg.det(M[:3, :3]))))
    R = M[:3, :3] / s
    if project:
        U, _, Vt = np.linalg.svd(R)
        U[:, 2] *= np.sign(np.linalg.det(U @ Vt))
        R = U @ Vt
    return R, M[:3, 3].copy(), s


def sim3_rigid(M: np.ndarray) -> np.ndarray:
    """Rigid part ``[R | t]`` of a Sim(3) matrix ``[[s R, t], [0, 1]]`` (a copy; R as :func:`sim3_matrix_parts`
    gives it, not projected)."""
    out = np.array(M, dtype=np.float64, copy=True)
    out[:3, :3] = sim3_matrix_parts(out)[0]
    return out


def similarity3(R: np.ndarray, t: np.ndarray, s: float):
    """``gtsam.Similarity3`` of rotation ``R``, translation ``t`` and scale ``s`` of the matrix
    ``[[s R, t], [0, 1]]`` (gtsam acts as ``s (R p + t_g)``, so ``t_g = t / s``): the one conversion
    into gtsam, used by :meth:`Sim3.to_gtsam` and :func:`gtsam_sim3`."""
    import gtsam  # deferred: gtsam

    return gtsam.Similarity3(gtsam.Rot3(R), t / s, s)


def gtsam_sim3(M: np.ndarray):
    """``gtsam.Similarity3`` of a Sim(3) matrix ``[[s R, t], [0, 1]]`` (R projected onto SO(3));
    numpy twin of ``Sim3.from_matrix(M).to_gtsam()`` without the torch round trip (hot path)."""
    R, t, s = sim3_matrix_parts(M, project=True)
    return similarity3(R, t, s)


def gtsam_matrix(S) -> np.ndarray:
    """Sim(3) matrix ``[[s R, t], [0, 1]]`` of a ``gtsam.Similarity3`` (``t = s t_g``); numpy twin of
    ``Sim3.from_gtsam(S).matrix()``."""
    s = float(S.scale())
    M = np.eye(4)
    M[:3, :3] = s * S.rotation().matrix()
    M[:3, 3] = s * np.asarray(S.translation(), dtype=np.float64)
    return M


def sim3_matrix_components(M) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(R (n, 3, 3), t (n, 3), s (n,))`` float64 tensors of a batch of Sim(3) matrices (n, 4, 4)
    ``[[s R, t], [0, 1]]`` (numpy or torch), ``s = cbrt(|det(s R)|)``, R not re-projected: the cheap
    batched twin of :func:`sim3_matrix_parts` for matrices kept on the manifold by their producers."""
    M = torch.as_tensor(M, dtype=torch.float64)
    sR = M[..., :3, :3]
    s = torch.linalg.det(sR).abs().pow(1.0 / 3.0)
    return sR / s[..., None, None], M[..., :3, 3], s
