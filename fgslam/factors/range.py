"""Range residual between the camera centres of two Sim(3) keyframe poses, with its Jacobians.

Poses are ``gtsam.Similarity3`` camera-to-world ``T_WC``: ``X_W = s (R X_C + t)`` in gtsam's
convention, so the camera centre (the world position of the camera origin) is ``c = s t`` with
``t = T.translation()``. The residual of two poses ``a``, ``b`` and a measured distance ``D`` is::

    r = | c_b - c_a | - D                                                  (1,)

Jacobians are w.r.t. RIGHT perturbations ``T <- T Exp(xi)`` with gtsam's ``Similarity3`` tangent
order ``xi = [w (3), u (3), lambda]``. To first order ``c(T Exp(xi)) = c + s R u``: rotation and
log-scale of the camera's own frame leave its origin where it is, so only the ``u`` block is
non-zero::

    dr/dxi_b = [0, n^T s_b R_b, 0],    dr/dxi_a = [0, -n^T s_a R_a, 0],    n = (c_b - c_a) / |c_b - c_a|

(``n = 0`` when the centres coincide: the norm has no derivative there.) The monocular map uses it
as the world-scale gauge between its first two keyframes (:func:`range_factor`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["RANGE_DOF", "camera_centre", "range_factor", "range_residual"]

RANGE_DOF = 7  # tangent dimension of each pose ([w, u, lambda])


def camera_centre(T_WC) -> np.ndarray:
    """World position ``s t`` (3,) of the camera origin of a ``gtsam.Similarity3`` ``T_WC``."""
    return T_WC.scale() * np.asarray(T_WC.translation(), dtype=np.float64)


def range_residual(T_a, T_b, distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residual ``|c_b - c_a| - distance`` of two ``gtsam.Similarity3`` poses and its Jacobians.

    Returns ``r`` (1,), ``J_a`` = dr/dxi_a (1, 7), ``J_b`` = dr/dxi_b (1, 7) (module docstring).
    """
    diff = camera_centre(T_b) - camera_centre(T_a)
    dist = float(np.linalg.norm(diff))
    unit = diff / max(dist, np.finfo(float).tiny)
    J_a = np.zeros((1, RANGE_DOF))
    J_b = np.zeros((1, RANGE_DOF))
    J_a[0, 3:6] = -unit @ (T_a.scale() * T_a.rotation().matrix())
    J_b[0, 3:6] = unit @ (T_b.scale() * T_b.rotation().matrix())
    return np.array([dist - distance]), J_a, J_b


def range_factor(key_a: int, key_b: int, distance: float, sigma: float):
    """``gtsam.CustomFactor`` on :func:`range_residual` between the ``Similarity3`` values at
    ``key_a`` and ``key_b``, with an isotropic noise of ``sigma`` (same units as ``distance``).
    One Python factor per map: cheap."""
    import gtsam  # deferred: gtsam

    def error(this, values, jacobians):
        r, J_a, J_b = range_residual(values.atSimilarity3(key_a), values.atSimilarity3(key_b), distance)
        if jacobians is not None:
            jacobians[0] = J_a
            jacobians[1] = J_b
        return r

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, sigma), [key_a, key_b], error)
