"""Planar-motion constraint of a ground vehicle: camera height and roll/pitch relative to the ground.

A camera rigidly mounted on a vehicle that drives on a plane keeps a constant height above that
plane and a constant attitude across it; only the heading and the position in the plane change.
The plane is given by a reference keyframe ``T_ref`` (``gtsam.Similarity3``, ``X_W = s (R X_C + t)``):
its camera's up axis ``up_C`` (unit, camera coordinates; ``(0, -1, 0)`` for a forward-looking
camera with y pointing down) is the ground normal ``n_W = R_ref up_C``, and the plane passes at the
reference camera's height. For keyframe ``T_k`` (centre ``c = s t``) the residual is::

    r = [ n_W . (c_k - c_ref),        height of camera k above camera ref's, along the normal
          B^T R_k^T n_W ]             the normal seen by camera k, across its up axis     (3,)

``B`` (3, 2) is an orthonormal basis of the plane orthogonal to ``up_C`` (:func:`tilt_basis`), so the
last two components are the sines of camera k's tilt (pitch- and roll-like) relative to the
reference; all three are zero when k drives on the reference's plane with its attitude. The height
is in world units (metres once the map is metric); the residual is invariant to a common Sim(3)
motion of both keyframes except for the scale of the height.

Jacobians for right perturbations ``T <- T Exp([w, u, lambda])`` (gtsam's ``Similarity3.retract``),
exact at the linearisation point: ``dc/du = s R``, ``d(R a)/dw = -R [a]x``, ``d(R^T b)/dw = [R^T b]x``::

    d height / d w_ref = -(c_k - c_ref)^T R_ref [up_C]x     d height / d u_ref = -s_ref up_C^T
    d height / d u_k   =  s_k n_W^T R_k
    d tilt   / d w_ref = -B^T R_k^T R_ref [up_C]x           d tilt   / d w_k   =  B^T [v]x,  v = R_k^T n_W
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


def planar_residual(T_ref, T_k, up_C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residual (3,) ``[height, tilt_1, tilt_2]`` of keyframe ``T_k`` relative to the ground plane of
    ``T_ref`` (both ``gtsam.Similarity3``; ``up_C`` unit) and its Jacobians (3, 7) w.r.t. the right
    perturbations of ``T_ref`` and ``T_k``."""
    up = np.asarray(up_C, dtype=np.float64)
    B = tilt_basis(up)
    R_ref, R_k = T_ref.rotation().matrix(), T_k.rotation().matrix()
    s_ref, s_k = float(T_ref.scale()), float(T_k.scale())
    c_ref, c_k = camera_centre(T_ref), camera_centre(T_k)
    n_W = R_ref @ up
    v = R_k.T @ n_W
    r = np.concatenate([[n_W @ (c_k - c_ref)], B.T @ v])
    J_ref = np.zeros((PLANAR_DIM, POSE_DOF))
    J_k = np.zeros((PLANAR_DIM, POSE_DOF))
    up_x = _skew(up)
    J_ref[0, 0:3] = -(c_k - c_ref) @ R_ref @ up_x
    J_ref[0, 3:6] = -s_ref * up
    J_k[0, 3:6] = s_k * (n_W @ R_k)
    J_ref[1:, 0:3] = -B.T @ R_k.T @ R_ref @ up_x
    J_k[1:, 0:3] = B.T @ _skew(v)
    return r, J_ref, J_k


def planar_noise(height_sigma: float, tilt_sigma: float):
    """Diagonal gtsam noise model ``[height_sigma, tilt_sigma, tilt_sigma]`` (world units, sine of
    the tilt angle ~ radians); ValueError unless both are finite and positive."""
    import gtsam

    sig = np.array([height_sigma, tilt_sigma, tilt_sigma], dtype=np.float64)
    if not np.all(np.isfinite(sig)) or not np.all(sig > 0):
        raise ValueError(f"planar sigmas must be positive, got height {height_sigma!r}, tilt {tilt_sigma!r}")
    return gtsam.noiseModel.Diagonal.Sigmas(sig)


def planar_factor(key_ref: int, key_k: int, up_C: Sequence[float], height_sigma: float, tilt_sigma: float):
    """``gtsam.CustomFactor`` on two Similarity3 keys: keyframe ``key_k`` on the ground plane of
    ``key_ref`` with its attitude across the plane (see the module docstring)."""
    import gtsam

    up = unit_up(up_C)
    if int(key_ref) == int(key_k):
        raise ValueError(f"planar factor: reference and keyframe are the same key {key_k}")

    def error(this, values, jacobians):
        keys = this.keys()
        r, J_ref, J_k = planar_residual(values.atSimilarity3(keys[0]), values.atSimilarity3(keys[1]), up)
        if jacobians is not None:
            jacobians[0] = J_ref
            jacobians[1] = J_k
        return r

    return gtsam.CustomFactor(planar_noise(height_sigma, tilt_sigma), [int(key_ref), int(key_k)], error)
