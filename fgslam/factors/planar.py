"""Planar-motion constraint of a ground vehicle: camera height and roll/pitch relative to the ground.

A camera rigidly mounted on a vehicle that drives on a plane keeps a constant height above it and
a constant attitude across it; only the heading and the position in the plane change. The
constraint uses the *camera plane* ``n_W . x + d = 0``: the plane parallel to the ground (unit normal
``n_W``, world frame, pointing up) in which the camera centre moves. With the camera's up axis
``up_C`` (unit, camera coordinates: the ground normal as the mounted camera sees it; ``(0, -1, 0)``
for a level forward-looking camera with y down), the residual of keyframe ``T_WC``
(``gtsam.Similarity3``, ``X_W = s (R X_C + t)``, centre ``c = s t``) is::

    r = [ n_W . c + d,            height of the camera above the camera plane (world units)
          B^T R^T n_W ]           the plane's normal seen by the camera, across its up axis     (3,)

``B`` (3, 2) is an orthonormal basis of the plane orthogonal to ``up_C`` (:func:`tilt_basis`), so the
last two components are the sines of the camera's tilt (pitch- and roll-like) relative to the
plane, and ``|B^T v|^2 = 1 - (up_C . v)^2`` for the unit ``v = R^T n_W``.

Jacobian for right perturbations ``T <- T Exp([w, u, lambda])`` (gtsam's ``Similarity3.retract``),
exact at the linearisation point (``dc/du = s R``, ``d(R^T n)/dw = [R^T n]x``)::

    dr/d[w, u, lambda] = [[0,           s n_W^T R, 0],
                          [B^T [v]x,    0,         0]]      v = R^T n_W

:func:`fit_plane` gives the camera plane that best fits a set of keyframes under the same
residuals (closed form), :func:`plane_of_keyframe` the plane of a single keyframe. The factor
(:func:`planar_factor`) holds the plane in the coordinates of a reference keyframe
(:func:`planar_residual_relative`), so that a correction moving the whole map (a Sim(3) alignment,
a loop closure) moves the plane with it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .position import POSE_DOF, camera_centre

PLANAR_DIM = 3  # height, two tilt components


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def unit_up(up_C: Sequence[float]) -> np.ndarray:
    """``up_C`` as a unit (3,) vector; ValueError for a wrongly sized, non-finite or zero vector."""
    a = np.asarray(up_C, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(a)) if a.shape == (3,) else 0.0
    if a.shape != (3,) or not np.isfinite(norm) or norm == 0.0:
        raise ValueError(f"up axis must be a non-zero finite 3-vector, got {up_C!r}")
    return a / norm


def tilt_basis(up_C: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis ``[b1, b2]`` of the plane orthogonal to the unit ``up_C``, with
    ``b1 = up x e`` (``e`` the coordinate axis least aligned with ``up_C``, the first on ties) and
    ``b2 = up x b1``. For ``up_C = (0, -1, 0)``: ``b1 = z``, ``b2 = -x``, so the tilt is ``(v_z, -v_x)``
    of the normal ``v`` seen by the camera: pitch-like, then roll-like."""
    e = np.zeros(3)
    e[int(np.argmin(np.abs(up_C)))] = 1.0
    b1 = np.cross(up_C, e)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(up_C, b1)], axis=1)


def planar_residual(T_WC, n_W: np.ndarray, d: float, up_C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residual (3,) ``[height, tilt_1, tilt_2]`` of keyframe ``T_WC`` (``gtsam.Similarity3``) relative to
    the camera plane ``n_W . x + d = 0`` (``n_W``, ``up_C`` unit) and its Jacobian (3, 7) for right
    perturbations ``[w, u, lambda]``."""
    up = np.asarray(up_C, dtype=np.float64)
    n = np.asarray(n_W, dtype=np.float64)
    B = tilt_basis(up)
    R = T_WC.rotation().matrix()
    v = R.T @ n
    r = np.concatenate([[n @ camera_centre(T_WC) + d], B.T @ v])
    J = np.zeros((PLANAR_DIM, POSE_DOF))
    J[0, 3:6] = float(T_WC.scale()) * (n @ R)
    J[1:, 0:3] = B.T @ _skew(v)
    return r, J


def plane_in_world(T_ref, n_C: np.ndarray, d_C: float) -> tuple[np.ndarray, float]:
    """World camera plane ``(n_W, d_W)`` of the plane ``n_C . x + d_C = 0`` in the coordinates of the
    reference keyframe ``T_ref`` (``x_W = s R x + c``): ``n_W = R n_C``, ``d_W = s d_C - n_W . c``."""
    n_W = T_ref.rotation().matrix() @ np.asarray(n_C, dtype=np.float64)
    return n_W, float(T_ref.scale()) * float(d_C) - float(n_W @ camera_centre(T_ref))


def plane_in_keyframe(T_ref, n_W: np.ndarray, d_W: float) -> tuple[np.ndarray, float]:
    """The inverse of :func:`plane_in_world`: a world plane in the reference keyframe's coordinates."""
    n_W = np.asarray(n_W, dtype=np.float64)
    return T_ref.rotation().matrix().T @ n_W, (float(d_W) + float(n_W @ camera_centre(T_ref))) / float(T_ref.scale())


def planar_residual_relative(T_ref, T_k, n_C: np.ndarray, d_C: float, up_C: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`planar_residual` of keyframe ``T_k`` for the plane ``n_C . x + d_C = 0`` held in the
    coordinates of the reference keyframe ``T_ref`` (so that any motion of the whole map moves the
    plane with it), and its Jacobians (3, 7) w.r.t. the right perturbations of ``T_ref`` and ``T_k``.
    With ``n_W = R_r n_C``, ``r_h = n_W . (c_k - c_r) + s_r d_C`` and ``tilt = B^T R_k^T R_r n_C``::

        d r_h / d w_r = -(c_k - c_r)^T R_r [n_C]x     d r_h / d u_r = -s_r n_C^T     d r_h / d lambda_r = s_r d_C
        d tilt / d w_r = -B^T R_k^T R_r [n_C]x        (w.r.t. T_k: as :func:`planar_residual`)
    """
    n_C = np.asarray(n_C, dtype=np.float64)
    n_W, d_W = plane_in_world(T_ref, n_C, d_C)
    r, J_k = planar_residual(T_k, n_W, d_W, up_C)
    R_r, R_k = T_ref.rotation().matrix(), T_k.rotation().matrix()
    s_r = float(T_ref.scale())
    n_x = _skew(n_C)
    J_ref = np.zeros((PLANAR_DIM, POSE_DOF))
    J_ref[0, 0:3] = -(camera_centre(T_k) - camera_centre(T_ref)) @ R_r @ n_x
    J_ref[0, 3:6] = -s_r * n_C
    J_ref[0, 6] = s_r * float(d_C)
    J_ref[1:, 0:3] = -tilt_basis(np.asarray(up_C, dtype=np.float64)).T @ R_k.T @ R_r @ n_x
    return r, J_ref, J_k


def plane_of_keyframe(T_WC, up_C: np.ndarray) -> tuple[np.ndarray, float]:
    """The camera plane ``(n_W, d)`` of one keyframe: normal ``R up_C`` through its centre."""
    n = T_WC.rotation().matrix() @ np.asarray(up_C, dtype=np.float64)
    return n, float(-n @ camera_centre(T_WC))


def fit_plane(centres: np.ndarray, R_WC: np.ndarray, up_C: np.ndarray, height_sigma: float,
              tilt_sigma: float) -> tuple[np.ndarray, float]:
    """Camera plane ``(n_W, d)`` minimising the whitened planar residuals of N keyframes (centres
    (N, 3), rotations (N, 3, 3)) with the keyframes held fixed. Closed form: with ``a_k = R_k up_C``
    and ``d = -n . mean(c)``, the cost is ``n^T (C / sh^2 - A / st^2) n + const`` (``C`` the centres'
    scatter, ``A = sum a_k a_k^T``, using ``|B^T R^T n|^2 = 1 - (a . n)^2``), minimised by the
    eigenvector of the smallest eigenvalue, signed along ``sum a_k``."""
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    a = np.asarray(R_WC, dtype=np.float64).reshape(-1, 3, 3) @ np.asarray(up_C, dtype=np.float64)
    c_mean = c.mean(axis=0)
    dc = c - c_mean
    M = dc.T @ dc / height_sigma ** 2 - a.T @ a / tilt_sigma ** 2
    _, vectors = np.linalg.eigh(M)
    n = vectors[:, 0]
    if n @ a.sum(axis=0) < 0:
        n = -n
    return n, float(-n @ c_mean)


def planar_noise(height_sigma: float, tilt_sigma: float):
    """Diagonal gtsam noise model ``[height_sigma, tilt_sigma, tilt_sigma]`` (world units, sine of
    the tilt angle ~ radians); ValueError unless both are finite and positive."""
    import gtsam  # deferred: gtsam

    sig = np.array([height_sigma, tilt_sigma, tilt_sigma], dtype=np.float64)
    if not np.all(np.isfinite(sig)) or not np.all(sig > 0):
        raise ValueError(f"planar sigmas must be positive, got height {height_sigma!r}, tilt {tilt_sigma!r}")
    return gtsam.noiseModel.Diagonal.Sigmas(sig)


def planar_factor(key_ref: int, key: int, n_C: np.ndarray, d_C: float, up_C: Sequence[float],
                  height_sigma: float, tilt_sigma: float):
    """``gtsam.CustomFactor`` on two Similarity3 keys: keyframe ``key`` on the camera plane
    ``n_C . x + d_C = 0`` held in the coordinates of keyframe ``key_ref`` (it moves with the map), with
    its up axis ``up_C`` along the plane's normal (:func:`planar_residual_relative`)."""
    import gtsam  # deferred: gtsam

    up = unit_up(up_C)
    n = unit_up(n_C)
    if not np.isfinite(d_C):
        raise ValueError(f"planar factor on key {key}: non-finite plane offset {d_C!r}")
    if int(key_ref) == int(key):
        raise ValueError(f"planar factor: the reference and the keyframe are the same key {key}")

    def error(this, values, jacobians):
        keys = this.keys()
        r, J_ref, J_k = planar_residual_relative(values.atSimilarity3(keys[0]), values.atSimilarity3(keys[1]), n,
                                                 float(d_C), up)
        if jacobians is not None:
            jacobians[0] = J_ref
            jacobians[1] = J_k
        return r

    return gtsam.CustomFactor(planar_noise(height_sigma, tilt_sigma), [int(key_ref), int(key)], error)
