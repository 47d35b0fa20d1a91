"""Closed-form point-set alignment (numpy), below every user of it.

:func:`umeyama` is the one least-squares similarity used by trajectory evaluation
(:mod:`fgslam.eval.trajectory`), loop-closure Sim(3) estimation (:mod:`fgslam.loop.sim3_estimation`), the
COLMAP comparison and the runner's plugins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import EvaluationError


@dataclass(frozen=True)
class Alignment:
    """Similarity ``S_WW'`` mapping estimate-world points into the ground-truth world: ``X -> s R X + t``."""

    R: np.ndarray  # (3, 3) rotation R_WW'
    t: np.ndarray  # (3,) translation t_WW', metres of the ground truth
    s: float  # scale (1 for se3 / none / first-pose)

    @staticmethod
    def identity() -> Alignment:
        return Alignment(np.eye(3), np.zeros(3), 1.0)

    def matrix(self) -> np.ndarray:
        """``(4, 4)`` matrix ``[[s R, t], [0, 1]]``."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    def apply(self, T_WpC: np.ndarray) -> np.ndarray:
        """Aligned poses ``(N, 4, 4)``: ``R_WC = R R_W'C``, ``t_WC = s R t_W'C + t`` (rotations stay orthonormal)."""
        T_WC = np.array(T_WpC, dtype=np.float64, copy=True)
        T_WC[:, :3, :3] = self.R @ T_WpC[:, :3, :3]
        T_WC[:, :3, 3] = self.s * T_WpC[:, :3, 3] @ self.R.T + self.t
        return T_WC


def umeyama(X_src: np.ndarray, Y_dst: np.ndarray, with_scale: bool) -> Alignment:
    """Least-squares similarity (Umeyama 1991) minimising ``sum_i |Y_i - (s R X_i + t)|^2``.

    Args:
        X_src: ``(N, 3)`` source points (estimate positions).
        Y_dst: ``(N, 3)`` destination points (ground-truth positions).
        with_scale: estimate ``s`` (Sim(3)); otherwise ``s = 1`` (SE(3)).

    For collinear points the rotation about the common line is not unique (any choice has the same
    residual). Raises ``EvaluationError`` for fewer than 2 points or, with scale, a source with no
    spread.
    """
    X = np.asarray(X_src, dtype=np.float64)
    Y = np.asarray(Y_dst, dtype=np.float64)
    if X.shape != Y.shape or X.ndim != 2 or X.shape[1] != 3:
        raise EvaluationError(f"umeyama: point sets must both be (N, 3), got {X.shape} and {Y.shape}")
    n = X.shape[0]
    if n < 2:
        raise EvaluationError(f"umeyama: need at least 2 matched positions to align, got {n}")
    mu_X, mu_Y = X.mean(axis=0), Y.mean(axis=0)
    Xc, Yc = X - mu_X, Y - mu_Y
    cov_YX = Yc.T @ Xc / n
    U, D, Vt = np.linalg.svd(cov_YX)
    W = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        W[2, 2] = -1.0
    R = U @ W @ Vt
    s = 1.0
    if with_scale:
        var_X = float((Xc**2).sum() / n)
        if not var_X > 0:
            raise EvaluationError("umeyama: estimate positions have no spread, the scale is undetermined")
        s = float(np.sum(D * np.diag(W)) / var_X)
    t = mu_Y - s * R @ mu_X
    return Alignment(R, t, s)
