"""IMU preintegration on Sim(3) keyframe poses (docs/architecture.md section 13).

Keyframe poses are ``gtsam.Similarity3`` T_WC (camera to world, acting as ``X -> s R X + t`` with
``t = s t_g``; docs/architecture.md section 3), while gtsam's ``CombinedImuFactor`` acts on the metric body
(IMU) pose ``T_WB`` (``gtsam.Pose3``). The adapter

    T_WB(S) = P(S) T_CB,    P(S) = Pose3(R, s t_g)   (the camera's rigid pose: its centre and rotation)

ignores the keyframe's own scale (a gauge of the inverse-depth frontends, docs/architecture.md section 4):
only the camera centre and rotation are physical. With gtsam's right perturbation
``S Exp([w, u, lambda])`` the first-order change is ``R -> R Exp(w)`` and ``t -> t + s R u`` (lambda
cancels: the centre ``s e^lambda (R u + e^-lambda t_g)`` does not move), so

    d T_WB = Ad(T_CB^-1) [[I, 0, 0], [0, s I, 0]] [w, u, lambda]      (6 x 7, Pose3 tangent [w, v])

(:func:`body_pose_jacobian`, tested against finite differences). :func:`imu_factor_on_sim3` wraps a
``CombinedImuFactor`` into a factor on (x_i, v_i, x_j, v_j, b_i, b_j) with Sim(3) pose keys: its
linearisation is gtsam's own (whitened), the pose columns chained through the adapter's Jacobian.

Everything here is pure math: preintegration of a sample block between two times
(:func:`preintegrate`), the parameters from noise densities (:func:`combined_params`), the adapter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

POSE3_DIM = 6
SIM3_DIM = 7
IMU_FACTOR_DIM = 15  # CombinedImuFactor: rotation, velocity, position, accel bias, gyro bias


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise (EuRoC ``imu0/sensor.yaml`` keys) and gravity magnitude."""

    gyroscope_noise_density: float  # rad / s / sqrt(Hz)
    accelerometer_noise_density: float  # m / s^2 / sqrt(Hz)
    gyroscope_random_walk: float  # rad / s^2 / sqrt(Hz)
    accelerometer_random_walk: float  # m / s^3 / sqrt(Hz)
    integration_sigma: float = 1e-4  # m/s^2-like sigma of the position integration (gtsam integrationCovariance)


def combined_params(gravity_W: np.ndarray, noise: ImuNoise):
    """``gtsam.PreintegrationCombinedParams`` with gravity vector ``gravity_W`` (world frame, m/s^2,
    pointing down) and the noise densities squared as covariances."""
    import gtsam  # deferred: gtsam

    p = gtsam.PreintegrationCombinedParams(np.asarray(gravity_W, dtype=np.float64).reshape(3))
    eye = np.eye(3)
    p.setGyroscopeCovariance(noise.gyroscope_noise_density ** 2 * eye)
    p.setAccelerometerCovariance(noise.accelerometer_noise_density ** 2 * eye)
    p.setIntegrationCovariance(noise.integration_sigma ** 2 * eye)
    p.setBiasOmegaCovariance(noise.gyroscope_random_walk ** 2 * eye)
    p.setBiasAccCovariance(noise.accelerometer_random_walk ** 2 * eye)
    return p


def integration_steps(t: np.ndarray, t_start: float, t_end: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order-hold pieces of the interval ``[t_start, t_end]`` over samples at times ``t``
    (increasing): sample k holds over ``[t_k, t_k+1)`` (the last one until ``t_end``); the part before
    the first sample is held by that first sample. Returns ``(sample index, dt)`` of the pieces with
    ``dt > 0`` (their dts sum to ``t_end - t_start``)."""
    t = np.asarray(t, dtype=np.float64)
    if t.size == 0 or not t_end > t_start:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    starts = t.copy()
    starts[0] = min(starts[0], t_start)
    ends = np.append(t[1:], max(t[-1], t_end))
    lo = np.maximum(starts, t_start)
    hi = np.minimum(ends, t_end)
    dt = hi - lo
    keep = dt > 0
    return np.nonzero(keep)[0], dt[keep]


def preintegrate(params, bias, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, t_start: float, t_end: float):
    """``gtsam.PreintegratedCombinedMeasurements`` of the samples between ``t_start`` and ``t_end``
    (:func:`integration_steps`) at the bias linearisation point ``bias`` (``gtsam.imuBias.ConstantBias``)."""
    import gtsam  # deferred: gtsam

    pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
    idx, dt = integration_steps(t, t_start, t_end)
    integrate = pim.integrateMeasurement
    for k, d in zip(idx.tolist(), dt.tolist()):
        integrate(accel[k], gyro[k], d)
    return pim


def camera_pose(S_WC):
    """The rigid camera pose ``Pose3(R, s t_g)`` (rotation and centre) of a ``Similarity3`` T_WC."""
    import gtsam  # deferred: gtsam

    return gtsam.Pose3(S_WC.rotation(), float(S_WC.scale()) * np.asarray(S_WC.translation(), dtype=np.float64))


def body_pose(S_WC, T_CB):
    """Metric body pose ``T_WB = P(S_WC) T_CB`` (``gtsam.Pose3``) of a Sim(3) camera pose."""
    return camera_pose(S_WC).compose(T_CB)


def body_pose_jacobian(S_WC, T_CB) -> np.ndarray:
    """(6, 7) Jacobian of :func:`body_pose` (Pose3 right tangent ``[w, v]``) with respect to the
    Similarity3 right tangent ``[w, u, lambda]`` (module docstring)."""
    D = np.zeros((POSE3_DIM, SIM3_DIM))
    D[:3, :3] = np.eye(3)
    D[3:, 3:6] = float(S_WC.scale()) * np.eye(3)
    return np.asarray(T_CB.inverse().AdjointMap()) @ D


def sim3_from_body_pose(T_WB, T_CB, scale: float = 1.0):
    """The ``Similarity3`` T_WC with keyframe scale ``scale`` whose :func:`body_pose` is ``T_WB``."""
    import gtsam  # deferred: gtsam

    P = T_WB.compose(T_CB.inverse())
    return gtsam.Similarity3(P.rotation(), np.asarray(P.translation(), dtype=np.float64) / scale, scale)


#: the inner CombinedImuFactor's keys (its own small Values, independent of the backend's keys)
_INNER_KEYS = (0, 1, 2, 3, 4, 5)


def imu_factor_on_sim3(keys: tuple[int, int, int, int, int, int], pim, T_CB):
    """A factor on ``(x_i, v_i, x_j, v_j, b_i, b_j)`` (Sim(3) poses, ``Point3`` velocities,
    ``imuBias.ConstantBias``) whose whitened error and Jacobians are those of
    ``gtsam.CombinedImuFactor(pim)`` at the body poses :func:`body_pose` (module docstring). A
    ``gtsam.CustomFactor`` with a unit noise model (the whitening happens in the inner factor)."""
    import gtsam  # deferred: gtsam

    inner = gtsam.CombinedImuFactor(*_INNER_KEYS, pim)
    unit = gtsam.noiseModel.Unit.Create(IMU_FACTOR_DIM)
    xi, vi, xj, vj, bi, bj = (int(k) for k in keys)

    def error(this, values, H):
        Si, Sj = values.atSimilarity3(xi), values.atSimilarity3(xj)
        local = gtsam.Values()
        local.insert(0, body_pose(Si, T_CB))
        local.insert(1, values.atPoint3(vi))
        local.insert(2, body_pose(Sj, T_CB))
        local.insert(3, values.atPoint3(vj))
        local.insert(4, values.atConstantBias(bi))
        local.insert(5, values.atConstantBias(bj))
        if H is None:
            return np.asarray(inner.whitenedError(local), dtype=np.float64)
        A, b = inner.linearize(local).jacobian()  # A dx = b - (whitened error): b = -whitened error
        A = np.asarray(A)
        H[0] = A[:, 0:6] @ body_pose_jacobian(Si, T_CB)
        H[1] = A[:, 6:9]
        H[2] = A[:, 9:15] @ body_pose_jacobian(Sj, T_CB)
        H[3] = A[:, 15:18]
        H[4] = A[:, 18:24]
        H[5] = A[:, 24:30]
        return -np.asarray(b, dtype=np.float64)

    return gtsam.CustomFactor(unit, [xi, vi, xj, vj, bi, bj], error)
