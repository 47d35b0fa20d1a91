"""The IMU service's configuration (YAML section ``imu``), its counters, and the sample buffer with the
rotation and preintegration helpers that read it (the service: :mod:`fgslam.services.imu`).

The buffer (:class:`ImuBuffer`) checks each frame's samples (missing, out of order, non-finite, gaps
longer than ``max_gap_s``, frame times not covered), keeps the good ones in time order and remembers
the bad intervals; the service bounds it to the span its keyframes still need (:meth:`ImuBuffer.prune`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal, Optional

import numpy as np

from ..core.config import MAX_ITERATIONS, MAX_KEYFRAMES, MAX_SCALAR, MAX_WINDOW, ranged
from ..factors.imu import ImuNoise, integration_steps, preintegrate
from .imu_checks import ImuCheckConfig

logger = logging.getLogger(__name__)

_SMALL_ANGLE_RAD = 1e-12  # rodrigues: below this rotation angle, the first-order expansion
_MERGE_TOLERANCE_S = 1e-9  # a bad interval starting within this of the previous one's end extends it

#: EuRoC's ADIS16448 (imu0/sensor.yaml): the defaults when neither the config nor the dataset give a value
EUROC_NOISE = {"gyroscope_noise_density": 1.6968e-4, "gyroscope_random_walk": 1.9393e-5,
               "accelerometer_noise_density": 2.0e-3, "accelerometer_random_walk": 3.0e-3}


@dataclass
class ImuInitConfig:
    """Initialisation of the IMU state (:mod:`fgslam.services.imu` docstring)."""

    static_window_s: float = ranged(0.5, gt=0, le=MAX_SCALAR)  # s of samples at the start tested for a still IMU
    # still = the means of static_chunks consecutive chunks of that window agree (vibration averages out:
    # EuRoC V1_01's MAV on the ground reads 0.8 m/s^2 of per-sample accel spread, 0.05 m/s^2 between chunk means)
    static_chunks: int = ranged(5, ge=2, le=MAX_KEYFRAMES)
    static_gyro_std: float = ranged(0.01, gt=0, le=MAX_SCALAR)  # rad/s: largest per-axis spread of the chunks' mean rates
    static_accel_std: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # m/s^2: largest per-axis spread of the chunks' mean specific forces
    static_metric_start: bool = True  # a metric map (stereo/RGB-D) with a still start initialises at once (velocity 0)
    keyframes: int = ranged(10, ge=3, le=MAX_KEYFRAMES)  # fewest keyframes of the visual-inertial initialisation
    min_duration_s: float = ranged(3.0, gt=0, le=MAX_SCALAR)  # monocular: s of the newest keyframes it uses (the scale needs accelerations)
    metric_min_duration_s: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # metric maps (stereo, RGB-D; no scale to estimate): the same
    spacing_s: float = ranged(0.3, ge=0, le=MAX_SCALAR)  # s between the keyframes it uses (longer baselines: less attenuation of the scale by visual noise)
    # monocular: the scale re-estimated (gravity known) over the keyframes since the initialisation
    # this many seconds after it; the map is rescaled when it changed by more than refine_min_change
    refine_at_s: list[float] = ranged(default_factory=lambda: [3.0, 6.0, 9.0, 12.0, 15.0], gt=0, le=MAX_SCALAR)
    refine_min_change: float = ranged(0.01, ge=0, le=MAX_SCALAR)  # relative scale change worth a rescale
    # how each refinement estimates: inertial_only (ORB-SLAM3: scale, gravity direction, velocities and
    # one bias by least squares on the preintegrated IMU factors, the visual poses held; then the IMU
    # links rebuilt and a short visual-inertial window optimisation) or linear (scale only, gravity known)
    refine_method: Literal["inertial_only", "linear"] = "inertial_only"
    # monocular: an inertial-only optimisation right after the linear initialisation as well. Off: its
    # window is the initialisation's own ~2 s (sigma(log scale) 0.2-0.4); measured on the room loop,
    # off 1.6 % scale error against 2.7 % on, and on a 6 s clip on applied x0.44 (log scale error 1.37)
    inertial_only_at_init: bool = False
    inertial_only_iterations: int = ranged(10, ge=1, le=MAX_ITERATIONS)  # LM iterations of the inertial-only optimisation
    inertial_only_gauge_sigma: float = ranged(1e-6, gt=0, le=MAX_SCALAR)  # rad (and log-scale on metric maps): holds the unobservable yaw about gravity
    inertial_only_gravity_prior: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # rad: weak prior on the gravity direction (keeps a short window determinate)
    inertial_only_log_scale_prior: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # weak prior on log(scale change) (monocular)
    inertial_only_max_log_scale_sigma: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # monocular: the scale is applied only when sigma(log scale) is below this
    # the one bias's prior (about the current estimate); measured on the room loop: 0.1 / 0.01 gave a
    # 2.7 % scale error, ORB-SLAM3's 0.003 / 0.1 (with the whole map's keyframes and a 0.1 gate) 54 % (docs/benchmarks/inertial.md)
    inertial_only_accel_bias_sigma: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # m/s^2
    inertial_only_gyro_bias_sigma: float = ranged(0.01, gt=0, le=MAX_SCALAR)  # rad/s
    inertial_only_ba_iterations: int = ranged(2, ge=0, le=MAX_ITERATIONS)  # LM iterations of the visual-inertial optimisation after it (0: none)
    max_scale_rel_sigma: float = ranged(0.05, gt=0, le=MAX_SCALAR)  # monocular: the scale's relative standard deviation (least squares) must be below this
    gyro_bias_iterations: int = ranged(5, ge=1, le=MAX_ITERATIONS)  # Gauss-Newton iterations of the gyroscope bias
    gravity_tolerance: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # relative |g| error beyond which the unconstrained solve is rejected
    min_scale: float = ranged(1e-3, gt=0, le=MAX_SCALAR)  # monocular: smallest plausible metric scale (map units -> m)
    max_scale: float = ranged(1e3, gt=0, le=MAX_SCALAR)  # monocular: largest plausible metric scale
    bias_gyro_sigma: float = ranged(1e-2, gt=0, le=MAX_SCALAR)  # rad/s: prior on the initial gyroscope bias
    bias_accel_sigma: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # m/s^2: prior on the initial accelerometer bias
    velocity_sigma: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # m/s: prior on the initial velocity
    restart_velocity_sigma: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # m/s: prior on the velocity of a keyframe starting a new chain


@dataclass
class ImuServiceConfig:
    """IMU fusion (YAML section ``imu`` of a run config; presets ``configs/*inertial*.yaml``)."""

    enabled: bool = False  # fuse the dataset's IMU (the inertial presets switch it on; a dataset without IMU is then an error)
    gravity: float = ranged(9.81, gt=0, le=MAX_SCALAR)  # m/s^2, magnitude of gravity
    # continuous-time noise (null: the dataset's imu0/sensor.yaml, else EuRoC's ADIS16448 values)
    gyroscope_noise_density: Optional[float] = ranged(None, gt=0, le=MAX_SCALAR)  # rad / s / sqrt(Hz)
    accelerometer_noise_density: Optional[float] = ranged(None, gt=0, le=MAX_SCALAR)  # m / s^2 / sqrt(Hz)
    gyroscope_random_walk: Optional[float] = ranged(None, gt=0, le=MAX_SCALAR)  # rad / s^2 / sqrt(Hz)
    accelerometer_random_walk: Optional[float] = ranged(None, gt=0, le=MAX_SCALAR)  # m / s^3 / sqrt(Hz)
    noise_inflation: float = ranged(1.0, ge=1, le=MAX_SCALAR)  # multiplies the white-noise densities (unmodelled vibration, timing)
    integration_sigma: float = ranged(1e-4, gt=0, le=MAX_SCALAR)  # gtsam integration covariance sigma
    history: Literal["window", "full"] = "window"  # window: marginalise old velocities/biases; full: keep (isam2)
    window_keyframes: int = ranged(20, ge=3, le=MAX_WINDOW)  # linked keyframes kept with history: window
    # velocities and biases of every linked keyframe (the IMU window) are free in each window optimisation,
    # also where the frontend holds the keyframe's pose fixed (else they are fixed with it: overconfident)
    free_window_states: bool = True
    max_gap_s: float = ranged(0.05, gt=0, le=MAX_SCALAR)  # s: a larger gap between samples (or to a frame time) is a bad interval
    max_interval_s: float = ranged(5.0, gt=0, le=MAX_SCALAR)  # s: longest keyframe interval given an IMU factor
    max_bridge_s: float = ranged(3.0, ge=0, le=MAX_SCALAR)  # s: IMU prediction from the newest linked keyframe up to this long
    init: ImuInitConfig = field(default_factory=ImuInitConfig)
    checks: ImuCheckConfig = field(default_factory=ImuCheckConfig)  # the stream's units, axes and clock checked before a run (imu_checks.py)

    def noise(self, dataset_noise: Optional[dict] = None) -> ImuNoise:
        """Noise densities: config, else the dataset's, else EuRoC's (white noise times ``noise_inflation``)."""
        values = {}
        for name, default in EUROC_NOISE.items():
            value = getattr(self, name)
            if value is None and dataset_noise:
                value = dataset_noise.get(name)
            inflation = self.noise_inflation if name.endswith("noise_density") else 1.0
            values[name] = float(default if value is None else value) * inflation
        return ImuNoise(integration_sigma=self.integration_sigma, **values)


@dataclass
class StaticInit:
    """A still start: when, the gyroscope bias and gravity in the body frame."""

    t: float
    gyro_bias: np.ndarray
    gravity_B: np.ndarray  # m/s^2 in the body frame at t


@dataclass
class ImuStats:
    """Counters of one run (``summary``)."""

    samples: int = 0
    dropped_samples: int = 0
    bad_intervals: int = 0
    links: int = 0
    unlinked: int = 0
    marginalised: int = 0
    predictions: int = 0
    update_s: float = 0.0  # time of the IMU bookkeeping per keyframe (factors, marginalisation)


def rodrigues(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (rad)."""
    theta = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if theta < _SMALL_ANGLE_RAD:
        return np.eye(3) + K
    return np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta ** 2 * K @ K


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of the rotation matrix ``R`` (gtsam's ``Rot3.Logmap``)."""
    import gtsam  # deferred: gtsam

    return np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(R)))


class ImuBuffer:
    """Time-indexed IMU samples (``t`` (N,) s, ``gyro`` and ``accel`` (N, 3) in the body frame) and the
    intervals ``bad`` without trustworthy samples; ``stats`` counts samples, drops and bad intervals."""

    def __init__(self, max_gap_s: float, stats: ImuStats):
        self.max_gap_s = max_gap_s
        self.stats = stats
        self.t = np.zeros(0)
        self.gyro = np.zeros((0, 3))
        self.accel = np.zeros((0, 3))
        self.bad: list[tuple[float, float]] = []  # intervals without trustworthy samples
        self.last_frame_t: Optional[float] = None
        self.first_t: Optional[float] = None

    def feed(self, imu, frame_t: float) -> None:
        """Take the samples a frame carries (``fgslam.io.frame.ImuSamples`` of ``t_prev < t <= frame_t``,
        or None), check them and buffer the good ones; bad stretches are logged and remembered."""
        frame_t = float(frame_t)
        prev_t = self.last_frame_t
        self.last_frame_t = frame_t if prev_t is None else max(prev_t, frame_t)
        if imu is None or len(imu) == 0:
            if prev_t is not None and frame_t - prev_t > self.max_gap_s:
                self._mark_bad(prev_t, frame_t, "no IMU samples")
            elif prev_t is not None and imu is None:
                self._mark_bad(prev_t, frame_t, "no IMU samples")
            return
        t = np.asarray(imu.timestamps, dtype=np.float64)
        gyro = np.asarray(imu.gyro, dtype=np.float64).reshape(-1, 3)
        accel = np.asarray(imu.accel, dtype=np.float64).reshape(-1, 3)
        ok = np.isfinite(t) & np.isfinite(gyro).all(axis=1) & np.isfinite(accel).all(axis=1)
        last = self.t[-1] if self.t.size else -np.inf
        # out of order: a sample not later than every sample before it (buffer and block) is dropped
        running = np.maximum.accumulate(np.concatenate([[last], np.where(ok, t, -np.inf)]))[:-1]
        in_order = t > running
        keep = ok & in_order
        dropped = int((~keep).sum())
        if dropped:
            self.stats.dropped_samples += dropped
            where = (float(np.nanmin(t)) if np.isfinite(t).any() else frame_t)
            self._mark_bad(min(where, prev_t if prev_t is not None else where), frame_t,
                           f"{int((~ok).sum())} non-finite and {int((ok & ~in_order).sum())} out-of-order IMU samples dropped")
        t, gyro, accel = t[keep], gyro[keep], accel[keep]
        if t.size:
            if self.first_t is None:
                self.first_t = float(t[0])
            gaps = np.diff(np.concatenate([[last], t])) if self.t.size else np.diff(t)
            starts = np.concatenate([[last], t[:-1]]) if self.t.size else t[:-1]
            for k in np.nonzero(gaps > self.max_gap_s)[0]:
                self._mark_bad(float(starts[k]), float(starts[k] + gaps[k]), f"IMU gap of {gaps[k]:.3f} s")
            self.t = np.concatenate([self.t, t])
            self.gyro = np.concatenate([self.gyro, gyro])
            self.accel = np.concatenate([self.accel, accel])
            self.stats.samples += int(t.size)
        end = self.t[-1] if self.t.size else -np.inf
        if prev_t is not None and frame_t - end > self.max_gap_s:
            self._mark_bad(max(end, prev_t), frame_t, "IMU samples do not cover the frame time")

    def _mark_bad(self, t0: float, t1: float, why: str) -> None:
        if self.bad and t0 <= self.bad[-1][1] + _MERGE_TOLERANCE_S:
            self.bad[-1] = (min(self.bad[-1][0], t0), max(self.bad[-1][1], t1))
        else:
            self.bad.append((t0, t1))
            self.stats.bad_intervals += 1
            logger.warning("IMU: %s in [%.3f, %.3f] s: keyframe intervals over it fall back to vision only", why, t0, t1)

    def covered(self, t0: float, t1: float) -> bool:
        """Whether the buffer covers ``[t0, t1]`` with good samples (no bad interval overlaps it)."""
        if not self.t.size or self.t[0] > t0 + self.max_gap_s or self.t[-1] < t1 - self.max_gap_s:
            return False
        return not any(a < t1 and b > t0 for a, b in self.bad)

    def samples(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t, gyro, accel)`` of the samples from the last one at or before ``t0`` to ``t1``."""
        lo = max(0, int(np.searchsorted(self.t, t0, side="right")) - 1)
        hi = int(np.searchsorted(self.t, t1, side="right"))
        return self.t[lo:hi], self.gyro[lo:hi], self.accel[lo:hi]

    def prune(self, keep_from: float) -> None:
        """Drop samples and bad intervals before ``keep_from`` (keeping the samples that bracket it)."""
        cut = max(0, int(np.searchsorted(self.t, keep_from, side="right")) - 2)
        if cut > 0:
            self.t, self.gyro, self.accel = self.t[cut:], self.gyro[cut:], self.accel[cut:]
        self.bad = [(a, b) for a, b in self.bad if b >= keep_from]

    def rotation_between(self, t0: float, t1: float, gyro_bias: np.ndarray) -> np.ndarray:
        """R_B(t0)B(t1) from the buffered gyroscope samples."""
        t, g, _ = self.samples(min(t0, t1), max(t0, t1))
        idx, dt = integration_steps(t, min(t0, t1), max(t0, t1))
        R = np.eye(3)
        for k, d in zip(idx.tolist(), dt.tolist()):
            R = R @ rodrigues((g[k] - gyro_bias) * d)
        return R if t1 >= t0 else R.T

    def preintegrate(self, params, t0: float, t1: float, bias):
        """The samples of ``[t0, t1]`` preintegrated with ``params`` from ``bias``."""
        t, g, a = self.samples(t0, t1)
        return preintegrate(params, bias, t, g, a, t0, t1)
