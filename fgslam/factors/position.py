"""Position prior on a Sim(3) keyframe's camera centre (GPS-like measurements), with its Jacobian.

A keyframe pose ``T_WC`` is a ``gtsam.Similarity3`` acting as ``X_W = s (R X_C + t)``, so the
camera centre (the image of the camera origin) in the world frame is ``c_W = s t``. A measured
position ``p_W`` of that centre gives the residual::

    r = c_W - p_W = s t - p_W                                   (3,)

With gtsam's right perturbation ``T <- T Exp([w, u, lambda])`` (``Similarity3.retract``), the
composition gives ``t' = t / e^lambda + R V(w, lambda) u`` and ``s' = s e^lambda``, so
``c' = s t + s e^lambda R V u``: only ``u`` moves the centre, and at the linearisation point::

    dr/d[w, u, lambda] = [0, s R, 0]                            (3, 7), exact

The measurement is in the world frame of the map; a monocular map must first be brought into the
measurements' frame (see :class:`fgslam.services.plugins.PositionPrior`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

POSE_DOF = 7  # Sim(3) tangent [w, u, lambda]
POSITION_DIM = 3


def camera_centre(T_WC) -> np.ndarray:
    """World position ``s t`` of the camera centre of a ``gtsam.Similarity3`` ``T_WC`` (3,)."""
    return float(T_WC.scale()) * np.asarray(T_WC.translation(), dtype=np.float64)


def position_residual(T_WC, p_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residual ``s t - p_W`` (3,) and its Jacobian (3, 7) for right perturbations ``[w, u, lambda]``."""
    s = float(T_WC.scale())
    r = s * np.asarray(T_WC.translation(), dtype=np.float64) - np.asarray(p_W, dtype=np.float64)
    J = np.zeros((POSITION_DIM, POSE_DOF))
    J[:, 3:6] = s * T_WC.rotation().matrix()
    return r, J


def position_noise(sigma: float | Sequence[float], huber_k: float | None = None):
    """gtsam noise model of a position measurement: isotropic for one ``sigma``, diagonal for three
    (metres, world axes); wrapped in gtsam's Huber m-estimator when ``huber_k`` (whitened threshold)
    is given. ValueError for a non-positive, non-finite or wrongly sized sigma."""
    import gtsam  # deferred: gtsam

    sig = np.atleast_1d(np.asarray(sigma, dtype=np.float64))
    if sig.shape not in ((1,), (POSITION_DIM,)) or not np.all(np.isfinite(sig)) or not np.all(sig > 0):
        raise ValueError(f"position sigma must be one positive number or three, got {sigma!r}")
    if sig.shape == (1,):
        model = gtsam.noiseModel.Isotropic.Sigma(POSITION_DIM, float(sig[0]))
    else:
        model = gtsam.noiseModel.Diagonal.Sigmas(sig)
    if huber_k is not None:
        model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k), model)
    return model


def position_prior_factor(key: int, p_W: np.ndarray, sigma: float | Sequence[float], huber_k: float | None = None):
    """``gtsam.CustomFactor`` on the Similarity3 at ``key``: camera centre ``s t`` at ``p_W`` (3,) with
    an isotropic (one sigma) or diagonal (three sigmas) noise model, optionally Huber-robust."""
    import gtsam  # deferred: gtsam

    p = np.array(p_W, dtype=np.float64).reshape(POSITION_DIM)
    if not np.all(np.isfinite(p)):
        raise ValueError(f"position prior on key {key}: non-finite position {p}")

    def error(this, values, jacobians):
        r, J = position_residual(values.atSimilarity3(this.keys()[0]), p)
        if jacobians is not None:
            jacobians[0] = J
        return r

    return gtsam.CustomFactor(position_noise(sigma, huber_k), [int(key)], error)
