"""Visual-inertial SLAM on the run's backend: the IMU service (docs/design.md section 13).

:class:`ImuService` is attached to a :class:`~fgslam.backend.Backend` and works for any frontend that
feeds it keyframes (``on_keyframe``):

- the runner hands it every frame's IMU samples (:meth:`ImuService.feed`, before the frontend sees the
  frame); they are checked (missing, out of order, non-finite, gaps longer than ``max_gap_s``, frame
  times not covered) and kept in a time-indexed buffer bounded to the linked keyframes' span; a bad
  interval is logged and every keyframe interval that overlaps it gets no IMU factor (vision only);
- once initialised, each keyframe gets a velocity ``v<kf>`` (``Point3``, world frame, m/s) and a bias
  ``b<kf>`` (``imuBias.ConstantBias``) attached to it (free, fixed and removed with it:
  :meth:`Backend.attach_key`), and consecutive keyframes (in time) are linked by a
  ``CombinedImuFactor`` through the Sim(3) adapter (:func:`fgslam.factors.imu.imu_factor_on_sim3`). A
  keyframe the frontend removes (redundant, rejected) merges its two intervals: the links are
  recomputed from the buffer. A keyframe without a link to its predecessor starts a new chain with
  priors on its velocity and bias;
- bounded state (``history``): ``window`` keeps links over the newest ``window_keyframes`` linked
  keyframes and marginalises the oldest one's velocity and bias (conditioned on its pose, which stays
  in the map) into a linear prior on its successor (:meth:`Backend.marginalize_variables`): memory is
  flat apart from the keyframe poses; ``full`` keeps every link (use with ``map.solver: isam2``);
- initialisation (:meth:`ImuService.poll`, the runner's safe point after a frame): *static* when the
  first ``init.static_window_s`` of samples are still (gyro and accel spread below thresholds):
  gyroscope bias = mean rate, gravity direction = -mean specific force; a metric (stereo/RGB-D) map
  then starts visual-inertial at its first keyframe at rest. Otherwise *visual-inertial* from the
  first ``init.keyframes`` keyframes spanning ``init.min_duration_s``: gyroscope bias by Gauss-Newton
  on the rotation residuals, then gravity, velocities and (monocular) the metric scale by linear
  least squares on the preintegrated velocity and position deltas, then again with ``|g|`` fixed.
  A monocular map is rescaled to metric through the contributor's ``apply_correction`` with a uniform
  scale :class:`~fgslam.loop.closure.PoseCorrection` (the scale folded into the structure, as
  position priors do), and continues visual-inertial;
- IMU prediction (:meth:`ImuService.predict`): the pose at a time from the newest linked keyframe's
  state (pose, velocity, bias) and the buffered samples; the patch frontend uses it as motion prior
  and to pose frames whose visual tracking fails (bridging up to ``max_bridge_s``).

Gravity lives in the map's world frame (the first keyframe's camera frame for the patch frontend):
``g_W`` from the initialisation is the preintegration's gravity vector; the map is not rotated.
"""

from __future__ import annotations

import bisect
import logging
import time
from dataclasses import dataclass, field
from typing import Any, Literal, Optional

import numpy as np

from ..config import MAX_ITERATIONS, MAX_KEYFRAMES, MAX_SCALAR, MAX_WINDOW, ranged
from ..errors import DataError
from ..factors.imu import (ImuNoise, body_pose, combined_params, imu_factor_on_sim3, integration_steps,
                           preintegrate, sim3_from_body_pose)
from ..backend.keys import bias_key, pose_key, velocity_key

logger = logging.getLogger(__name__)

OWNER = "imu"
#: EuRoC's ADIS16448 (imu0/sensor.yaml): the defaults when neither the config nor the dataset give a value
EUROC_NOISE = {"gyroscope_noise_density": 1.6968e-4, "gyroscope_random_walk": 1.9393e-5,
               "accelerometer_noise_density": 2.0e-3, "accelerometer_random_walk": 3.0e-3}


@dataclass
class ImuInitConfig:
    """Initialisation of the IMU state (module docstring)."""

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


def _rodrigues(w: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if theta < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta ** 2 * K @ K


def _log_so3(R: np.ndarray) -> np.ndarray:
    import gtsam

    return np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(R)))


class ImuService:
    """IMU factors, velocity and bias keys, initialisation and prediction on a backend (module docstring).

    Args:
        config: the ``imu`` section.
        backend: the run's :class:`~fgslam.backend.Backend`.
        T_BC: (4, 4) camera-to-body (IMU) transform from the calibration.
        metric: whether the map is metric from the start (stereo, RGB-D); a monocular map is rescaled.
        contributor: who moves the map (``apply_correction``; the frontend) at the metric rescale.
        dataset_noise: the dataset's noise densities (EuRoC ``sensor.yaml`` keys) or None.
    """

    def __init__(self, config: ImuServiceConfig, backend, T_BC: np.ndarray, metric: bool, contributor=None,
                 dataset_noise: Optional[dict] = None):
        import gtsam

        self.config = config
        self.backend = backend
        self.metric = bool(metric)
        self.contributor = contributor
        self.noise = config.noise(dataset_noise)
        self.T_BC = gtsam.Pose3(np.asarray(T_BC, dtype=np.float64))
        self.T_CB = self.T_BC.inverse()
        self.stats = ImuStats()
        # sample buffer (time-indexed, bounded by the linked keyframes' span)
        self._t = np.zeros(0)
        self._gyro = np.zeros((0, 3))
        self._accel = np.zeros((0, 3))
        self._bad: list[tuple[float, float]] = []  # intervals without trustworthy samples
        self._last_frame_t: Optional[float] = None
        self._first_t: Optional[float] = None
        # keyframes in time order: (timestamp, kf_id)
        self._kfs: list[tuple[float, int]] = []
        self._linked: set[int] = set()  # keyframes with velocity and bias keys
        self._links: dict[tuple[int, int], int] = {}  # (kf_a, kf_b) -> factor handle
        self._starts: dict[int, list[int]] = {}  # chain-start prior handles per keyframe
        self.static: Optional[StaticInit] = None
        self._static_done = False
        self.initialized = False
        self.gravity_W: Optional[np.ndarray] = None
        self.params = None
        self.scale_applied: Optional[float] = None  # monocular: the metric scale applied at initialisation
        self.init_time: Optional[float] = None
        self._refinements = 0
        self.scale_refinements: list[float] = []
        backend.on_keyframe(self._on_keyframe)
        backend.on_keyframe_removed(self._on_removed)
        if config.free_window_states:
            backend.on_window(self._window_keys)

    # ------------------------------------------------------------------ samples
    def feed(self, imu, frame_t: float) -> None:
        """Take the samples a frame carries (``fgslam.io.frame.ImuSamples`` of ``t_prev < t <= frame_t``,
        or None), check them and buffer the good ones; bad stretches are logged and remembered."""
        frame_t = float(frame_t)
        prev_t = self._last_frame_t
        self._last_frame_t = frame_t if prev_t is None else max(prev_t, frame_t)
        if imu is None or len(imu) == 0:
            if prev_t is not None and frame_t - prev_t > self.config.max_gap_s:
                self._mark_bad(prev_t, frame_t, "no IMU samples")
            elif prev_t is not None and imu is None:
                self._mark_bad(prev_t, frame_t, "no IMU samples")
            return
        t = np.asarray(imu.timestamps, dtype=np.float64)
        gyro = np.asarray(imu.gyro, dtype=np.float64).reshape(-1, 3)
        accel = np.asarray(imu.accel, dtype=np.float64).reshape(-1, 3)
        ok = np.isfinite(t) & np.isfinite(gyro).all(axis=1) & np.isfinite(accel).all(axis=1)
        last = self._t[-1] if self._t.size else -np.inf
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
            if self._first_t is None:
                self._first_t = float(t[0])
            gaps = np.diff(np.concatenate([[last], t])) if self._t.size else np.diff(t)
            starts = np.concatenate([[last], t[:-1]]) if self._t.size else t[:-1]
            for k in np.nonzero(gaps > self.config.max_gap_s)[0]:
                self._mark_bad(float(starts[k]), float(starts[k] + gaps[k]), f"IMU gap of {gaps[k]:.3f} s")
            self._t = np.concatenate([self._t, t])
            self._gyro = np.concatenate([self._gyro, gyro])
            self._accel = np.concatenate([self._accel, accel])
            self.stats.samples += int(t.size)
        end = self._t[-1] if self._t.size else -np.inf
        if prev_t is not None and frame_t - end > self.config.max_gap_s:
            self._mark_bad(max(end, prev_t), frame_t, "IMU samples do not cover the frame time")

    def _mark_bad(self, t0: float, t1: float, why: str) -> None:
        if self._bad and t0 <= self._bad[-1][1] + 1e-9:
            self._bad[-1] = (min(self._bad[-1][0], t0), max(self._bad[-1][1], t1))
        else:
            self._bad.append((t0, t1))
            self.stats.bad_intervals += 1
            logger.warning("IMU: %s in [%.3f, %.3f] s: keyframe intervals over it fall back to vision only", why, t0, t1)

    def covered(self, t0: float, t1: float) -> bool:
        """Whether the buffer covers ``[t0, t1]`` with good samples (no bad interval overlaps it)."""
        if not self._t.size or self._t[0] > t0 + self.config.max_gap_s or self._t[-1] < t1 - self.config.max_gap_s:
            return False
        return not any(a < t1 and b > t0 for a, b in self._bad)

    def _samples(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lo = max(0, int(np.searchsorted(self._t, t0, side="right")) - 1)
        hi = int(np.searchsorted(self._t, t1, side="right"))
        return self._t[lo:hi], self._gyro[lo:hi], self._accel[lo:hi]

    def _prune(self) -> None:
        """Drop samples and bad intervals before the oldest time still needed."""
        keep_from = None
        if self._kfs:
            linked = [t for t, kf in self._kfs if kf in self._linked]
            keep_from = linked[0] if linked else self._kfs[max(0, len(self._kfs) - self.config.init.keyframes - 1)][0]
            if not self.initialized:
                keep_from = min(keep_from, self._kfs[0][0])
            elif not self.metric and self._refinements < len(self.config.init.refine_at_s):
                keep_from = min(keep_from, self.init_time)  # the scale refinements read back to the initialisation
        if keep_from is None or not self._static_done:
            return
        cut = max(0, int(np.searchsorted(self._t, keep_from, side="right")) - 2)
        if cut > 0:
            self._t, self._gyro, self._accel = self._t[cut:], self._gyro[cut:], self._accel[cut:]
        self._bad = [(a, b) for a, b in self._bad if b >= keep_from]

    def _preintegrate(self, t0: float, t1: float, bias):
        t, g, a = self._samples(t0, t1)
        return preintegrate(self.params, bias, t, g, a, t0, t1)

    # ------------------------------------------------------------------ keyframes
    def _on_keyframe(self, kf_id: int, timestamp: float, key: int) -> None:
        bisect.insort(self._kfs, (float(timestamp), int(kf_id)))
        if self.initialized:
            start = time.perf_counter()
            self._relink()
            self.stats.update_s += time.perf_counter() - start

    def _on_removed(self, kf_id: int) -> None:
        self._kfs = [(t, k) for t, k in self._kfs if k != kf_id]
        self._linked.discard(kf_id)
        self._starts.pop(kf_id, None)
        for pair in [p for p in self._links if kf_id in p]:
            del self._links[pair]  # the backend removed the factor with the keyframe
        if self.initialized:
            self._relink()

    def _window_keys(self, free_kf_ids: list[int]) -> list[int]:
        """Velocity and bias keys of the linked keyframes (``free_window_states``)."""
        return [key for kf in self._linked for key in (velocity_key(kf), bias_key(kf))]

    def _state(self, kf_id: int):
        """(T_WB Pose3, velocity, bias) of a linked keyframe."""
        b = self.backend
        values = b.values_of([pose_key(kf_id), velocity_key(kf_id), bias_key(kf_id)])
        return (body_pose(values.atSimilarity3(pose_key(kf_id)), self.T_CB), np.asarray(values.atPoint3(velocity_key(kf_id))),
                values.atConstantBias(bias_key(kf_id)))

    def _relink(self) -> None:
        """Velocity/bias keys for every keyframe from the first linked one on, links between consecutive
        ones (in time) where the IMU covers the interval, chain-start priors where not; then the window."""
        kfs = self._kfs
        if not self._linked:
            return
        first = next(i for i, (_, k) in enumerate(kfs) if k in self._linked)
        for i in range(first, len(kfs)):
            t_b, kf_b = kfs[i]
            if i == first:
                continue
            t_a, kf_a = kfs[i - 1]
            link_ok = (t_b - t_a <= self.config.max_interval_s and t_b > t_a and self.covered(t_a, t_b))
            if kf_b not in self._linked:
                self._add_state(kf_b, kf_a if link_ok else None, t_a, t_b)
            if (kf_a, kf_b) in self._links:
                continue
            # a link from another predecessor (the keyframe between was removed) is replaced
            for pair in [p for p in self._links if p[1] == kf_b]:
                self.backend.remove_factor(self._links.pop(pair))
            if link_ok:
                bias = self._state(kf_a)[2]
                pim = self._preintegrate(t_a, t_b, bias)
                keys = (pose_key(kf_a), velocity_key(kf_a), pose_key(kf_b), velocity_key(kf_b), bias_key(kf_a), bias_key(kf_b))
                self._links[(kf_a, kf_b)] = self.backend.add_factor(imu_factor_on_sim3(keys, pim, self.T_CB), OWNER)
                self.stats.links += 1
                for handle in self._starts.pop(kf_b, []):  # linked now: no chain-start priors
                    self.backend.remove_factor(handle)
            elif kf_b not in self._starts:
                self.stats.unlinked += 1
                T_WB, v, bias = self._state(kf_b)
                self._starts[kf_b] = self._start_priors(kf_b, v, bias, self.config.init.restart_velocity_sigma)
        if self.config.history == "window":
            self._marginalise_old()
        self._prune()

    def _add_state(self, kf_b: int, kf_a: Optional[int], t_a: float, t_b: float) -> None:
        """Velocity and bias keys of a new keyframe: predicted from its predecessor when the IMU covers
        the interval, else the predecessor's bias and its visual velocity."""
        import gtsam

        if kf_a is not None and kf_a in self._linked:
            T_WB_a, v_a, bias = self._state(kf_a)
            pim = self._preintegrate(t_a, t_b, bias)
            v_b = np.asarray(pim.predict(gtsam.NavState(T_WB_a, v_a), bias).velocity())
        else:
            prev = [k for _, k in self._kfs if k in self._linked]
            bias = self._state(prev[-1])[2] if prev else gtsam.imuBias.ConstantBias()
            v_b = np.zeros(3)
            if kf_a is not None and t_b > t_a:
                c_a = body_pose(self.backend.pose(kf_a), self.T_CB).translation()
                c_b = body_pose(self.backend.pose(kf_b), self.T_CB).translation()
                v_b = (np.asarray(c_b) - np.asarray(c_a)) / (t_b - t_a)
        self.backend.add_variable(velocity_key(kf_b), np.asarray(v_b, dtype=np.float64), attach_to=kf_b)
        self.backend.add_variable(bias_key(kf_b), bias, attach_to=kf_b)
        self._linked.add(kf_b)

    def _start_priors(self, kf_id: int, v: np.ndarray, bias, velocity_sigma: float) -> list[int]:
        import gtsam

        ic = self.config.init
        bias_sigmas = np.array([ic.bias_accel_sigma] * 3 + [ic.bias_gyro_sigma] * 3)
        return [
            self.backend.add_factor(gtsam.PriorFactorPoint3(velocity_key(kf_id), np.asarray(v, dtype=np.float64),
                                                            gtsam.noiseModel.Isotropic.Sigma(3, velocity_sigma)), OWNER),
            self.backend.add_factor(gtsam.PriorFactorConstantBias(bias_key(kf_id), bias,
                                                                  gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas)), OWNER),
        ]

    def _marginalise_old(self) -> None:
        """history: window: the oldest linked keyframes beyond ``window_keyframes`` lose their velocity
        and bias into a linear prior on what their factors reach (their pose held)."""
        linked = [k for _, k in self._kfs if k in self._linked]
        while len(linked) > self.config.window_keyframes:
            kf = linked.pop(0)
            self.backend.marginalize_variables([velocity_key(kf), bias_key(kf)], condition_on=[pose_key(kf)],
                                               owner=OWNER)
            self._linked.discard(kf)
            self._starts.pop(kf, None)
            for pair in [p for p in self._links if kf in p]:
                del self._links[pair]
            self.stats.marginalised += 1

    # ------------------------------------------------------------------ initialisation
    def poll(self) -> None:
        """Safe point (after a frame, no optimisation running): initialise when possible."""
        if not self._static_done:
            self._try_static()
        if not self.initialized:
            self._try_initialise()
        elif not self.metric and self._refinements < len(self.config.init.refine_at_s):
            self._try_refine_scale()

    def _try_static(self) -> None:
        ic = self.config.init
        if self._first_t is None or not self._t.size or self._t[-1] - self._first_t < ic.static_window_s:
            return
        self._static_done = True
        t0 = self._first_t
        sel = (self._t >= t0) & (self._t <= t0 + ic.static_window_s)
        if any(a < t0 + ic.static_window_s and b > t0 for a, b in self._bad) or sel.sum() < 3:
            return
        g, a = self._gyro[sel], self._accel[sel]
        chunks = np.array_split(np.arange(g.shape[0]), min(ic.static_chunks, g.shape[0]))
        g_spread = float(np.std([g[c].mean(axis=0) for c in chunks], axis=0).max())
        a_spread = float(np.std([a[c].mean(axis=0) for c in chunks], axis=0).max())
        if g_spread > ic.static_gyro_std or a_spread > ic.static_accel_std:
            logger.info("IMU: the start is not still (chunk means spread %.4f rad/s, %.3f m/s^2): no static initialisation",
                        g_spread, a_spread)
            return
        f = a.mean(axis=0)
        self.static = StaticInit(t=float(self._t[sel][-1]), gyro_bias=g.mean(axis=0),
                                 gravity_B=-self.config.gravity * f / np.linalg.norm(f))
        logger.info("IMU: static initialisation: gyroscope bias %s rad/s, |f| %.3f m/s^2",
                    np.round(self.static.gyro_bias, 5), float(np.linalg.norm(f)))

    def _rotation_between(self, t0: float, t1: float, gyro_bias: np.ndarray) -> np.ndarray:
        """R_B(t0)B(t1) from the buffered gyroscope samples."""
        t, g, _ = self._samples(min(t0, t1), max(t0, t1))
        idx, dt = integration_steps(t, min(t0, t1), max(t0, t1))
        R = np.eye(3)
        for k, d in zip(idx.tolist(), dt.tolist()):
            R = R @ _rodrigues((g[k] - gyro_bias) * d)
        return R if t1 >= t0 else R.T

    def _try_initialise(self) -> None:
        import gtsam

        if not self._kfs or not self._static_done:
            return
        ic = self.config.init
        if self.metric and self.static is not None and ic.static_metric_start:
            t_k, kf = self._kfs[0]
            if self.covered(min(self.static.t, t_k), max(self.static.t, t_k)):
                R_BsBk = self._rotation_between(self.static.t, t_k, self.static.gyro_bias)
                T_WB = body_pose(self.backend.pose(kf), self.T_CB)
                g_W = np.asarray(T_WB.rotation().matrix()) @ R_BsBk.T @ self.static.gravity_B
                bias = gtsam.imuBias.ConstantBias(np.zeros(3), self.static.gyro_bias)
                self._start(g_W, {kf: np.zeros(3)}, bias, "static")
                return
        duration = ic.metric_min_duration_s if self.metric else ic.min_duration_s
        if len(self._kfs) < ic.keyframes or self._kfs[-1][0] - self._kfs[0][0] < duration:
            return
        t_last = self._kfs[-1][0]
        window = [(t, k) for t, k in self._kfs if t >= t_last - duration]
        window = self._spaced(window)
        if len(window) < 3:
            return
        if not self.covered(window[0][0], window[-1][0]):
            return
        solution = self._visual_inertial(window)
        if solution is None:
            return
        g_W, scale, velocities, bg = solution
        if not self.metric:
            self._rescale(scale)  # the velocities were solved in metres already
        bias = gtsam.imuBias.ConstantBias(np.zeros(3), bg)
        self._start(g_W, {kf: v for (_, kf), v in zip(window, velocities)}, bias, "visual-inertial")

    def _spaced(self, window):
        spaced = [window[-1]]
        for item in reversed(window[:-1]):
            if spaced[-1][0] - item[0] >= self.config.init.spacing_s:
                spaced.append(item)
        return spaced[::-1]

    def _try_refine_scale(self) -> None:
        """Monocular: the scale again (gravity known) over every keyframe since the initialisation, at
        ``init.refine_at_s``; the map and the velocities rescaled when it changed (module docstring)."""
        ic = self.config.init
        t_last = self._kfs[-1][0]
        if t_last - self.init_time < ic.refine_at_s[self._refinements]:
            return
        self._refinements += 1
        window = self._spaced([(t, k) for t, k in self._kfs if t >= self.init_time])
        if len(window) < 3 or not self.covered(window[0][0], window[-1][0]):
            return
        solution = self._visual_inertial(window, self.gravity_W)
        if solution is None:
            return
        _, s, _, _ = solution
        self.scale_refinements.append(float(s))
        if abs(np.log(s)) <= ic.refine_min_change:
            return
        self._rescale(s)
        for kf in self._linked:
            v = np.asarray(self.backend.values_of([velocity_key(kf)]).atPoint3(velocity_key(kf)))
            self.backend.set_value(velocity_key(kf), s * v)
        import gtsam

        for handle in self.backend.factor_handles(OWNER):  # marginal priors linearised at the old scale
            if isinstance(self.backend.factor(handle), gtsam.LinearContainerFactor):
                self.backend.remove_factor(handle)
        self.scale_applied *= s
        logger.info("IMU: scale refined by %.4f (%.1f s after the initialisation)", s, t_last - self.init_time)

    def _visual_inertial(self, window, gravity_W: Optional[np.ndarray] = None):
        """Gyroscope bias, gravity, scale and velocities of ``window`` (list of (t, kf)); None when
        implausible (logged)."""
        import gtsam

        ic = self.config.init
        G = self.config.gravity
        R_WB = []
        c = []
        R_WC = []
        for _, kf in window:
            S = self.backend.pose(kf)
            R = np.asarray(S.rotation().matrix())
            R_WC.append(R)
            R_WB.append(R @ np.asarray(self.T_CB.rotation().matrix()))
            c.append(float(S.scale()) * np.asarray(S.translation()))
        ts = [t for t, _ in window]
        n = len(window)
        # gyroscope bias: Gauss-Newton on Log(dR(bg)^T R_i^T R_j) with numeric Jacobians
        bg = self.static.gyro_bias.copy() if self.static is not None else np.zeros(3)

        def residuals(bg):
            out = []
            for i in range(n - 1):
                dR = self._rotation_between(ts[i], ts[i + 1], bg)
                out.append(_log_so3(dR.T @ R_WB[i].T @ R_WB[i + 1]))
            return np.concatenate(out)

        for _ in range(ic.gyro_bias_iterations):
            r0 = residuals(bg)
            J = np.zeros((r0.size, 3))
            eps = 1e-6
            for k in range(3):
                d = np.zeros(3)
                d[k] = eps
                J[:, k] = (residuals(bg + d) - r0) / eps
            step = np.linalg.lstsq(J, -r0, rcond=None)[0]
            bg = bg + step
            if np.abs(step).max() < 1e-9:
                break
        bias = gtsam.imuBias.ConstantBias(np.zeros(3), bg)
        t_CB = np.asarray(self.T_CB.translation())
        params = combined_params(np.zeros(3), self.noise)  # gravity is an unknown: preintegrate without it
        saved = self.params
        self.params = params
        pims = [self._preintegrate(ts[i], ts[i + 1], bias) for i in range(n - 1)]
        self.params = saved

        def solve(g_known: Optional[np.ndarray]):
            nv = 3 * n
            cols = nv + (0 if g_known is not None else 3) + (0 if self.metric else 1)
            rows, rhs = [], []
            for i, pim in enumerate(pims):
                dt = pim.deltaTij()
                Ri = R_WB[i]
                dp = Ri @ np.asarray(pim.deltaPij())
                dv = Ri @ np.asarray(pim.deltaVij())
                lever = (R_WC[i + 1] - R_WC[i]) @ t_CB
                # s (c_j - c_i) - v_i dt - 0.5 g dt^2 = dp - lever ;  v_j - v_i - g dt = dv
                A1 = np.zeros((3, cols))
                A2 = np.zeros((3, cols))
                A1[:, 3 * i:3 * i + 3] = -dt * np.eye(3)
                A2[:, 3 * i:3 * i + 3] = -np.eye(3)
                A2[:, 3 * (i + 1):3 * (i + 1) + 3] = np.eye(3)
                b1 = dp - lever
                b2 = dv.copy()
                if g_known is None:
                    A1[:, nv:nv + 3] = -0.5 * dt * dt * np.eye(3)
                    A2[:, nv:nv + 3] = -dt * np.eye(3)
                else:
                    b1 = b1 + 0.5 * dt * dt * g_known
                    b2 = b2 + dt * g_known
                if self.metric:
                    b1 = b1 - (c[i + 1] - c[i])
                else:
                    A1[:, -1] = c[i + 1] - c[i]
                w = 1.0 / max(dt, 1e-3)  # position rows per unit time, like the velocity rows
                rows += [w * A1, A2]
                rhs += [w * b1, b2]
            A, b = np.vstack(rows), np.concatenate(rhs)
            x = np.linalg.lstsq(A, b, rcond=None)[0]
            v = x[:nv].reshape(n, 3)
            g = g_known if g_known is not None else x[nv:nv + 3]
            s = 1.0 if self.metric else float(x[-1])
            sigma_s = 0.0
            if not self.metric:  # least-squares standard deviation of the scale
                dof = max(A.shape[0] - A.shape[1], 1)
                var = float(np.sum((A @ x - b) ** 2)) / dof
                sigma_s = float(np.sqrt(var * np.linalg.pinv(A.T @ A)[-1, -1]))
            return v, g, s, sigma_s

        if gravity_W is not None:
            g_W = np.asarray(gravity_W, dtype=np.float64)
        elif self.static is not None:
            R_BsB0 = self._rotation_between(self.static.t, ts[0], bg)
            g_W = R_WB[0] @ R_BsB0.T @ self.static.gravity_B
        else:
            _, g_free, s_free, _ = solve(None)
            if abs(np.linalg.norm(g_free) - G) > ic.gravity_tolerance * G:
                logger.info("IMU: visual-inertial initialisation rejected: |g| = %.3f m/s^2 (scale %.4g); retrying",
                            float(np.linalg.norm(g_free)), s_free)
                return None
            g_W = G * g_free / np.linalg.norm(g_free)
        v, g_W, s, sigma_s = solve(g_W)
        if not self.metric and not (ic.min_scale <= s <= ic.max_scale and sigma_s < ic.max_scale_rel_sigma * s):
            logger.info("IMU: visual-inertial initialisation rejected: scale %.4g +- %.2g; retrying", s, sigma_s)
            return None
        logger.info("IMU: visual-inertial initialisation over %d keyframes (%.2f s): scale %.4f, gyroscope bias %s",
                    n, ts[-1] - ts[0], s, np.round(bg, 5))
        return g_W, s, v, bg

    def _rescale(self, scale: float) -> None:
        """Monocular: the map to metric, through the contributor (scale folded into its structure)."""
        from .plugins import CorrectedBackend, apply_correction, uniform_correction

        U = np.eye(4)
        U[:3, :3] *= scale
        target = CorrectedBackend(self.backend, [self.contributor]) if self.contributor is not None else self.backend
        apply_correction(target, uniform_correction(target, U))
        self.scale_applied = scale

    def _start(self, g_W: np.ndarray, velocities: dict[int, np.ndarray], bias, how: str) -> None:
        """Gravity fixed, keys and links from the oldest given keyframe on."""
        start = time.perf_counter()
        self.gravity_W = np.asarray(g_W, dtype=np.float64)
        self.params = combined_params(self.gravity_W, self.noise)
        ordered = [(t, k) for t, k in self._kfs if k in velocities]
        t0, kf0 = ordered[0]
        self.backend.add_variable(velocity_key(kf0), np.asarray(velocities[kf0], dtype=np.float64), attach_to=kf0)
        self.backend.add_variable(bias_key(kf0), bias, attach_to=kf0)
        self._linked.add(kf0)
        self._starts[kf0] = self._start_priors(kf0, velocities[kf0], bias, self.config.init.velocity_sigma)
        self.initialized = True
        self.init_time = float(t0)
        # the other keyframes of the initialisation take their solved velocities
        i0 = self._kfs.index((t0, kf0))
        for i in range(i0 + 1, len(self._kfs)):
            t_b, kf_b = self._kfs[i]
            if kf_b in velocities:
                self.backend.add_variable(velocity_key(kf_b), np.asarray(velocities[kf_b], dtype=np.float64), attach_to=kf_b)
                self.backend.add_variable(bias_key(kf_b), bias, attach_to=kf_b)
                self._linked.add(kf_b)
        self._relink()
        self.stats.update_s += time.perf_counter() - start
        logger.info("IMU: initialised (%s) at keyframe %d, gravity %s m/s^2 in the map frame", how, kf0,
                    np.round(self.gravity_W, 4))

    # ------------------------------------------------------------------ prediction
    def predict(self, timestamp: float) -> Optional[np.ndarray]:
        """T_WC (4x4 Sim(3) at the keyframe's scale) at ``timestamp`` predicted from the newest linked
        keyframe's state, or None (not initialised, samples do not cover, longer than ``max_bridge_s``)."""
        import gtsam

        if not self.initialized or not self._linked:
            return None
        t_k, kf = next((t, k) for t, k in reversed(self._kfs) if k in self._linked)
        if not 0 <= timestamp - t_k <= self.config.max_bridge_s or not self.covered(t_k, timestamp):
            return None
        T_WB, v, bias = self._state(kf)
        pim = self._preintegrate(t_k, timestamp, bias)
        nav = pim.predict(gtsam.NavState(T_WB, v), bias)
        S = sim3_from_body_pose(nav.pose(), self.T_CB, float(self.backend.pose(kf).scale()))
        self.stats.predictions += 1
        from ..lie import gtsam_matrix

        return gtsam_matrix(S)

    def velocity(self, kf_id: int) -> Optional[np.ndarray]:
        return np.asarray(self.backend.values_of([velocity_key(kf_id)]).atPoint3(velocity_key(kf_id))) \
            if kf_id in self._linked else None

    def bias(self, kf_id: int):
        return self.backend.values_of([bias_key(kf_id)]).atConstantBias(bias_key(kf_id)) if kf_id in self._linked else None

    def summary(self) -> dict[str, Any]:
        s = self.stats
        return {"initialized": self.initialized, "init_time": self.init_time, "scale": self.scale_applied,
                "gravity_W": None if self.gravity_W is None else [float(x) for x in self.gravity_W],
                "samples": s.samples, "dropped_samples": s.dropped_samples, "bad_intervals": s.bad_intervals,
                "links": s.links, "unlinked_intervals": s.unlinked, "marginalised": s.marginalised,
                "predictions": s.predictions, "update_s": s.update_s}


# ----------------------------------------------------------------------------------------- the run


def make_imu_service(config: ImuServiceConfig, backend: Any, calibration: Any, has_imu: bool, sensor: str,
                     contributor: Any = None, dataset_noise: Optional[dict] = None,
                     where: str = "the dataset") -> Optional[ImuService]:
    """The run's :class:`ImuService` on ``backend`` (``config.enabled``), else None. DataError when
    ``where`` has no IMU or its calibration no ``T_BC``. ``contributor`` (the frontend, when it has
    ``apply_correction``) gets the service's scale corrections."""
    if not config.enabled:
        return None
    if not has_imu:
        raise DataError(f"imu.enabled (an inertial preset) but {where} has no IMU samples; use a vision-only preset "
                        "or a dataset with an IMU stream (EuRoC layout mav0/imu0/data.csv)")
    T_BC = getattr(calibration, "T_BC", None)
    if T_BC is None:
        raise DataError(f"imu.enabled but the calibration of {where} has no camera-IMU transform T_BC")
    if not callable(getattr(contributor, "apply_correction", None)):
        contributor = None
    service = ImuService(config, backend, T_BC, metric=sensor in ("stereo", "rgbd"), contributor=contributor,
                         dataset_noise=dataset_noise)
    return service
