"""IMU measurements from an analytic body trajectory.

Model (EuRoC/Kalibr convention, body frame B = IMU frame)::

    gyro_k  = w_B(t_k) + b_g(t_k) + n_g,      n_g ~ N(0, (gyro_noise_density^2 / dt) I)
    accel_k = R_WB(t_k)^T (a_W(t_k) - g_W) + b_a(t_k) + n_a,   g_W = (0, 0, -gravity)
    b(t_{k+1}) = b(t_k) + random_walk * sqrt(dt) * N(0, I)

so a body at rest with z up reads accel = (0, 0, +gravity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...core.config import MAX_SCALAR, ranged
from .trajectory import BodyState

STANDARD_GRAVITY = 9.81  # m/s^2, the value the generator uses for |g_W| (TEAM.md contract)


@dataclass
class ImuConfig:
    """IMU rate and noise (continuous-time densities as in EuRoC's imu0/sensor.yaml)."""

    rate_hz: float = ranged(200.0, gt=0, le=MAX_SCALAR)  # IMU sample rate (Hz)
    gyroscope_noise_density: float = ranged(1.6968e-4, ge=0, le=MAX_SCALAR)  # rad / s / sqrt(Hz)
    gyroscope_random_walk: float = ranged(1.9393e-5, ge=0, le=MAX_SCALAR)  # rad / s^2 / sqrt(Hz)
    accelerometer_noise_density: float = ranged(2.0e-3, ge=0, le=MAX_SCALAR)  # m / s^2 / sqrt(Hz)
    accelerometer_random_walk: float = ranged(3.0e-3, ge=0, le=MAX_SCALAR)  # m / s^3 / sqrt(Hz)
    initial_gyro_bias: list[float] = ranged(default_factory=lambda: [0.001, -0.002, 0.0015], ge=-MAX_SCALAR, le=MAX_SCALAR)  # rad/s
    initial_accel_bias: list[float] = ranged(default_factory=lambda: [0.02, -0.01, 0.03], ge=-MAX_SCALAR, le=MAX_SCALAR)  # m/s^2
    gravity: float = ranged(STANDARD_GRAVITY, gt=0, le=MAX_SCALAR)  # |g_W| along -z of the world


@dataclass(frozen=True)
class ImuData:
    """N samples: ``t`` (N,) seconds, measured ``gyro``/``accel`` (N, 3), true biases
    ``bias_gyro``/``bias_accel`` (N, 3), noise-free ``gyro_true``/``accel_true`` (N, 3)."""

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    gyro_true: np.ndarray
    accel_true: np.ndarray


def specific_force(state: BodyState, gravity: float) -> np.ndarray:
    """(N, 3) noise-free accelerometer reading ``R_WB^T (a_W - g_W)``."""
    g_W = np.array([0.0, 0.0, -gravity])
    return np.einsum("nji,nj->ni", state.R_WB, state.a_WB - g_W)


def simulate_imu(state: BodyState, cfg: ImuConfig, rng: np.random.Generator) -> ImuData:
    """Noisy IMU samples at the (uniformly spaced) times of ``state``."""
    n = len(state.t)
    dt = 1.0 / cfg.rate_hz
    gyro_true = state.w_B.copy()
    accel_true = specific_force(state, cfg.gravity)
    steps_g = rng.standard_normal((n, 3)) * (cfg.gyroscope_random_walk * np.sqrt(dt))
    steps_a = rng.standard_normal((n, 3)) * (cfg.accelerometer_random_walk * np.sqrt(dt))
    steps_g[0] = 0.0
    steps_a[0] = 0.0
    bias_g = np.asarray(cfg.initial_gyro_bias, np.float64) + np.cumsum(steps_g, axis=0)
    bias_a = np.asarray(cfg.initial_accel_bias, np.float64) + np.cumsum(steps_a, axis=0)
    white_g = rng.standard_normal((n, 3)) * (cfg.gyroscope_noise_density / np.sqrt(dt))
    white_a = rng.standard_normal((n, 3)) * (cfg.accelerometer_noise_density / np.sqrt(dt))
    return ImuData(t=state.t, gyro=gyro_true + bias_g + white_g, accel=accel_true + bias_a + white_a,
                   bias_gyro=bias_g, bias_accel=bias_a, gyro_true=gyro_true, accel_true=accel_true)
