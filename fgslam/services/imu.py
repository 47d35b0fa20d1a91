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
  scale :class:`~fgslam.loop.records.PoseCorrection` (the scale folded into the structure, as
  position priors do), and continues visual-inertial;
- IMU prediction (:meth:`ImuService.predict`): the pose at a time from the newest linked keyframe's
  state (pose, velocity, bias) and the buffered samples; the patch frontend uses it as motion prior
  and to pose frames whose visual tracking fails (bridging up to ``max_bridge_s``).

Modules: the configuration, counters and sample buffer are in :mod:`fgslam.services.imu_samples`, the
initialisation's solves in :mod:`fgslam.services.imu_init`.

Gravity lives in the map's world frame (the first keyframe's camera frame for the patch frontend):
``g_W`` from the initialisation is the preintegration's gravity vector; the map is not rotated.
"""

from __future__ import annotations

import bisect
import logging
import time
from typing import Any, Optional

import numpy as np

from ..errors import DataError
from ..factors.imu import body_pose, combined_params, imu_factor_on_sim3, sim3_from_body_pose
from ..backend.keys import bias_key, pose_key, velocity_key
from .imu_init import detect_static, solve_visual_inertial, spaced
from .imu_samples import ImuBuffer, ImuServiceConfig, ImuStats, StaticInit

logger = logging.getLogger(__name__)

OWNER = "imu"


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
        self.buffer = ImuBuffer(config.max_gap_s, self.stats)  # bounded by the linked keyframes' span
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
        or None) into the buffer (:meth:`ImuBuffer.feed`: checked; bad stretches logged and remembered)."""
        self.buffer.feed(imu, frame_t)

    def covered(self, t0: float, t1: float) -> bool:
        """Whether the buffer covers ``[t0, t1]`` with good samples (no bad interval overlaps it)."""
        return self.buffer.covered(t0, t1)

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
        self.buffer.prune(keep_from)

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
                pim = self.buffer.preintegrate(self.params, t_a, t_b, bias)
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
            pim = self.buffer.preintegrate(self.params, t_a, t_b, bias)
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
        """Once the buffer spans ``init.static_window_s``: whether the start is still (:func:`detect_static`)."""
        ic = self.config.init
        buf = self.buffer
        if buf.first_t is None or not buf.t.size or buf.t[-1] - buf.first_t < ic.static_window_s:
            return
        self._static_done = True
        self.static = detect_static(buf, self.config)

    def _try_initialise(self) -> None:
        import gtsam

        if not self._kfs or not self._static_done:
            return
        ic = self.config.init
        if self.metric and self.static is not None and ic.static_metric_start:
            t_k, kf = self._kfs[0]
            if self.covered(min(self.static.t, t_k), max(self.static.t, t_k)):
                R_BsBk = self.buffer.rotation_between(self.static.t, t_k, self.static.gyro_bias)
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
        window = spaced(window, ic.spacing_s)
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

    def _try_refine_scale(self) -> None:
        """Monocular: the scale again (gravity known) over every keyframe since the initialisation, at
        ``init.refine_at_s``; the map and the velocities rescaled when it changed (module docstring)."""
        ic = self.config.init
        t_last = self._kfs[-1][0]
        if t_last - self.init_time < ic.refine_at_s[self._refinements]:
            return
        self._refinements += 1
        window = spaced([(t, k) for t, k in self._kfs if t >= self.init_time], ic.spacing_s)
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
        """:func:`solve_visual_inertial` over ``window`` (list of (t, kf)) at the keyframes' current poses."""
        return solve_visual_inertial(window, [self.backend.pose(kf) for _, kf in window], self.T_CB, self.buffer,
                                     self.config, self.noise, self.metric, self.static, gravity_W)

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
        pim = self.buffer.preintegrate(self.params, t_k, timestamp, bias)
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
