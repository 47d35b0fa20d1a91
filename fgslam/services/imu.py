"""Visual-inertial SLAM on the run's backend: the IMU service (docs/architecture.md section 13).

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
- inertial-only optimisation (issue 26; ``init.refine_method: inertial_only``): right after a
  monocular initialisation and at each ``init.refine_at_s``, the scale, gravity direction, velocities
  and one bias over every keyframe since the initialisation with the visual poses held
  (:func:`~fgslam.services.imu_init.solve_inertial_only`), applied (rescale, gravity, velocities,
  biases, links rebuilt) and followed by a short visual-inertial window optimisation; its result and
  the standard deviation of the log-scale are logged and reported (:class:`InertialState`);
- map corrections (loops, global BA, plugins, its own rescale): :meth:`ImuService.adapt_correction`
  (SE(3) once the IMU fixed a monocular map's scale) before the contributor applies one and
  :meth:`ImuService.on_correction` after: velocities turn (and scale) with the poses, biases are kept,
  marginal priors are re-anchored (rigid) or dropped (:class:`~fgslam.services.corrections.ObservedContributor`;
  :meth:`fgslam.services.imu_chain.ImuChain.follow_correction`);
- IMU prediction (:meth:`ImuService.predict`): the pose at a time from the newest linked keyframe's
  state (pose, velocity, bias) and the buffered samples; the patch frontend uses it as motion prior
  and to pose frames whose visual tracking fails (bridging up to ``max_bridge_s``).

Modules: the configuration, counters and sample buffer are in :mod:`fgslam.services.imu_samples`, the
keyframe chain (keys, links, chain-start and marginal priors, how they follow a correction) in
:mod:`fgslam.services.imu_chain`, the initialisation's solves in :mod:`fgslam.services.imu_init`.

Gravity lives in the map's world frame (the first keyframe's camera frame for the patch frontend):
``g_W`` from the initialisation is the preintegration's gravity vector; the map is not rotated.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Optional, Union

import numpy as np

from ..backend.graph import Backend, CorrectionTarget
from ..backend.keys import bias_key, velocity_key
from ..core.errors import DataError
from ..factors.imu import body_pose, combined_params, sim3_from_body_pose
from ..io.calibration import Calibration
from ..io.frame import ImuSamples
from ..core.lie import gtsam_matrix, sim3_matrix_parts
from ..loop.records import PoseCorrection
from .corrections import route_correction, takes_corrections, uniform_correction
from .imu_chain import ImuChain
from .imu_init import InertialOnlyResult, detect_static, solve_inertial_only, solve_visual_inertial, spaced
from .imu_samples import ImuBuffer, ImuServiceConfig, ImuStats, StaticInit

if TYPE_CHECKING:
    import gtsam

logger = logging.getLogger(__name__)

#: one inertial-only optimisation's log entry (:attr:`ImuService.inertial_only`)
InertialOnlyEntry = dict[str, Union[float, int, bool, list[float]]]


@dataclass(frozen=True)
class InertialState:
    """The IMU state of a run as the summary reports it (:attr:`ImuService.inertial_state`):
    initialised or not, when (s, the first linked keyframe's time), the metric scale applied to a
    monocular map (map units at the start -> m; 1 for metric maps) with the standard deviation of the
    last inertial-only optimisation (``scale * sigma(log scale)``; None before one), gravity in the map
    frame (m/s^2), the newest linked keyframe's bias norms (m/s^2, rad/s) and the number of
    inertial-only optimisations applied."""

    initialised: bool
    time_init: Optional[float]
    scale: Optional[float]
    scale_sigma: Optional[float]
    gravity_W: Optional[list[float]]
    accel_bias_norm: Optional[float]
    gyro_bias_norm: Optional[float]
    inertial_only_runs: int = 0

    def to_dict(self) -> dict[str, object]:
        """Plain JSON-ready values."""
        return asdict(self)


class ImuService:
    """IMU factors, velocity and bias keys, initialisation and prediction on a backend (module
    docstring); the keyframe chain's keys and factors are its :class:`~fgslam.services.imu_chain.ImuChain`
    (``chain``).

    Args:
        config: the ``imu`` section.
        backend: the run's :class:`~fgslam.backend.Backend`.
        T_BC: (4, 4) camera-to-body (IMU) transform from the calibration.
        metric: whether the map is metric from the start (stereo, RGB-D); a monocular map is rescaled.
        contributor: who moves the map (``apply_correction``; the frontend) at the metric rescale.
        dataset_noise: the dataset's noise densities (EuRoC ``sensor.yaml`` keys) or None.
    """

    def __init__(self, config: ImuServiceConfig, backend: Backend, T_BC: np.ndarray, metric: bool,
                 contributor: Optional[CorrectionTarget] = None, dataset_noise: Optional[dict[str, float]] = None):
        import gtsam  # deferred: gtsam

        self.config = config
        self.backend = backend
        self.metric = bool(metric)
        self.contributor = contributor
        self.noise = config.noise(dataset_noise)
        self.T_BC = gtsam.Pose3(np.asarray(T_BC, dtype=np.float64))
        self.T_CB = self.T_BC.inverse()
        self.stats = ImuStats()
        self.buffer = ImuBuffer(config.max_gap_s, self.stats)  # bounded by the linked keyframes' span
        self.chain = ImuChain(config, backend, self.T_CB, self.buffer, self.stats, on_relinked=self._prune)
        self.static: Optional[StaticInit] = None
        self._static_done = False
        self.initialized = False
        self.gravity_W: Optional[np.ndarray] = None
        self.scale_applied: Optional[float] = None  # monocular: the metric scale applied at initialisation
        self.init_time: Optional[float] = None
        self._refinements = 0
        self.scale_refinements: list[float] = []
        self.scale_sigma: Optional[float] = None  # of the last inertial-only optimisation
        self.inertial_only: list[InertialOnlyEntry] = []  # each inertial-only optimisation's result (log)
        backend.on_keyframe(self._on_keyframe)
        backend.on_keyframe_removed(self._on_removed)
        if config.free_window_states:
            backend.on_window(self.chain.window_keys)

    # ------------------------------------------------------------------ samples
    def feed(self, imu: Optional[ImuSamples], frame_t: float) -> None:
        """Take the samples a frame carries (``fgslam.io.frame.ImuSamples`` of ``t_prev < t <= frame_t``,
        or None) into the buffer (:meth:`ImuBuffer.feed`: checked; bad stretches logged and remembered)."""
        self.buffer.feed(imu, frame_t)

    def covered(self, t0: float, t1: float) -> bool:
        """Whether the buffer covers ``[t0, t1]`` with good samples (no bad interval overlaps it)."""
        return self.buffer.covered(t0, t1)

    def _prune(self) -> None:
        """Drop samples and bad intervals before the oldest time still needed (after every relink)."""
        keep_from = None
        kfs = self.chain.kfs
        if kfs:
            linked = [t for t, kf in kfs if kf in self.chain.linked]
            keep_from = linked[0] if linked else kfs[max(0, len(kfs) - self.config.init.keyframes - 1)][0]
            if not self.initialized:
                keep_from = min(keep_from, kfs[0][0])
            elif not self.metric and self._refinements < len(self.config.init.refine_at_s):
                keep_from = min(keep_from, self.init_time)  # the scale refinements read back to the initialisation
        if keep_from is None or not self._static_done:
            return
        self.buffer.prune(keep_from)

    # ------------------------------------------------------------------ keyframes
    def _on_keyframe(self, kf_id: int, timestamp: float, key: int) -> None:
        self.chain.insert(timestamp, kf_id)
        if self.initialized:
            start = time.perf_counter()
            self.chain.relink()
            self.stats.update_s += time.perf_counter() - start

    def _on_removed(self, kf_id: int) -> None:
        self.chain.remove(kf_id)
        if self.initialized:
            self.chain.relink()

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
        import gtsam  # deferred: gtsam

        if not self.chain.kfs or not self._static_done:
            return
        ic = self.config.init
        if self.metric and self.static is not None and ic.static_metric_start:
            t_k, kf = self.chain.kfs[0]
            if self.covered(min(self.static.t, t_k), max(self.static.t, t_k)):
                R_BsBk = self.buffer.rotation_between(self.static.t, t_k, self.static.gyro_bias)
                T_WB = body_pose(self.backend.pose(kf), self.T_CB)
                g_W = np.asarray(T_WB.rotation().matrix()) @ R_BsBk.T @ self.static.gravity_B
                bias = gtsam.imuBias.ConstantBias(np.zeros(3), self.static.gyro_bias)
                self._start(g_W, {kf: np.zeros(3)}, bias, "static")
                return
        duration = ic.metric_min_duration_s if self.metric else ic.min_duration_s
        if len(self.chain.kfs) < ic.keyframes or self.chain.kfs[-1][0] - self.chain.kfs[0][0] < duration:
            return
        t_last = self.chain.kfs[-1][0]
        window = [(t, k) for t, k in self.chain.kfs if t >= t_last - duration]
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
        if not self.metric and ic.refine_method == "inertial_only" and ic.inertial_only_at_init:
            self._refine_inertial_only()

    def _try_refine_scale(self) -> None:
        """Monocular: at ``init.refine_at_s`` after the initialisation, the scale again over every
        keyframe since the initialisation: ``init.refine_method`` inertial_only
        (:meth:`_refine_inertial_only`) or linear (gravity known; the map and velocities rescaled when
        the scale changed by more than ``init.refine_min_change``)."""
        ic = self.config.init
        t_last = self.chain.kfs[-1][0]
        if t_last - self.init_time < ic.refine_at_s[self._refinements]:
            return
        self._refinements += 1
        if ic.refine_method == "inertial_only":
            self._refine_inertial_only()
            return
        window = spaced([(t, k) for t, k in self.chain.kfs if t >= self.init_time], ic.spacing_s)
        if len(window) < 3 or not self.covered(window[0][0], window[-1][0]):
            return
        solution = self._visual_inertial(window, self.gravity_W)
        if solution is None:
            return
        _, s, _, _ = solution
        self.scale_refinements.append(float(s))
        if abs(np.log(s)) <= ic.refine_min_change:
            return
        self._rescale(s)  # velocities follow (on_correction); marginal priors dropped there
        logger.info("IMU: scale refined by %.4f (%.1f s after the initialisation)", s, t_last - self.init_time)

    def _refine_inertial_only(self) -> Optional[InertialOnlyResult]:
        """ORB-SLAM3's inertial-only optimisation over every keyframe since the initialisation with
        their visual poses held
        (:func:`solve_inertial_only`), applied: the map rescaled (monocular, when the change exceeds
        ``init.refine_min_change`` and sigma(log scale) is below ``init.inertial_only_max_log_scale_sigma``), gravity, the linked keyframes' velocities and
        biases set, the IMU links rebuilt at the new gravity and bias, then
        ``init.inertial_only_ba_iterations`` of the visual-inertial window optimisation. Logged with
        the scale's standard deviation."""
        ic = self.config.init
        start = time.perf_counter()
        window = [(t, k) for t, k in self.chain.kfs if t >= self.init_time]
        if len(window) < 3 or not self.covered(window[0][0], window[-1][0]):
            return None
        poses = [self.backend.pose(k) for _, k in window]
        newest = next(k for _, k in reversed(self.chain.kfs) if k in self.chain.linked)
        bias0 = self.chain.state(newest)[2]
        v0 = self.chain.start_velocities(window, poses)
        settings = self.backend.optimizer.settings(ic.inertial_only_iterations)
        result = solve_inertial_only(window, poses, self.T_CB, self.buffer, self.config, self.noise, self.metric,
                                     self.gravity_W, v0, bias0, settings)
        if result is None:
            return None
        s = result.scale if not self.metric else 1.0
        rescaled = abs(np.log(s)) > ic.refine_min_change and result.log_scale_sigma < ic.inertial_only_max_log_scale_sigma
        if rescaled:
            self._rescale(s)
        self.gravity_W = np.asarray(result.gravity_W, dtype=np.float64)
        self.chain.params = combined_params(self.gravity_W, self.noise)
        # velocities in the map's units: the unapplied scale change divides them (metric: 1)
        v_factor = 1.0 if rescaled or self.metric else 1.0 / result.scale
        velocity = {k: v_factor * v for (_, k), v in zip(window, result.velocities)}
        for kf in self.chain.linked:
            if kf in velocity:
                self.backend.set_value(velocity_key(kf), np.asarray(velocity[kf], dtype=np.float64))
            self.backend.set_value(bias_key(kf), result.bias)
        self.chain.rebuild_links()
        if ic.inertial_only_ba_iterations > 0:
            self.backend.optimize_window([newest], iterations=ic.inertial_only_ba_iterations)
        total = (self.scale_applied or 1.0) * (s if not rescaled else 1.0)
        self.scale_sigma = float(total * result.log_scale_sigma)
        b = result.bias
        entry = {"t": float(self.chain.kfs[-1][0] - self.init_time), "keyframes": len(window), "scale_change": float(result.scale),
                 "applied": bool(rescaled), "log_scale_sigma": float(result.log_scale_sigma),
                 "gravity_W": [float(x) for x in self.gravity_W],
                 "accel_bias_norm": float(np.linalg.norm(b.accelerometer())), "gyro_bias_norm": float(np.linalg.norm(b.gyroscope())),
                 "cost": [result.initial_cost, result.final_cost], "seconds": time.perf_counter() - start}
        self.inertial_only.append(entry)
        self.scale_refinements.append(float(result.scale))
        self.stats.update_s += entry["seconds"]
        logger.info("IMU: inertial-only optimisation over %d keyframes (%.1f s after the initialisation): scale x%.4f "
                    "(sigma of log-scale %.4f; %s), gravity %s m/s^2, bias |a| %.4f m/s^2 |w| %.5f rad/s, cost %.4g -> %.4g",
                    len(window), entry["t"], result.scale, result.log_scale_sigma, "applied" if rescaled else "kept",
                    np.round(self.gravity_W, 4), entry["accel_bias_norm"], entry["gyro_bias_norm"], *entry["cost"])
        return result

    def _visual_inertial(self, window: list[tuple[float, int]], gravity_W: Optional[np.ndarray] = None,
                         ) -> Optional[tuple[np.ndarray, float, np.ndarray, np.ndarray]]:
        """:func:`solve_visual_inertial` over ``window`` (list of (t, kf)) at the keyframes' current poses."""
        return solve_visual_inertial(window, [self.backend.pose(kf) for _, kf in window], self.T_CB, self.buffer,
                                     self.config, self.noise, self.metric, self.static, gravity_W)

    def _rescale(self, scale: float) -> None:
        """Monocular: the map to metric, through the contributor (scale folded into its structure; without
        one the keyframe poses scale); the linked velocities follow (:meth:`on_correction`)."""
        U = np.eye(4)
        U[:3, :3] *= scale
        targets = () if self.contributor is None else (self.contributor,)
        correction = uniform_correction(self.backend, U, fold_scale=bool(targets))
        route_correction(self.backend, correction, targets)
        self.on_correction(correction)
        self.scale_applied = scale * (self.scale_applied if self.scale_applied is not None else 1.0)

    def _start(self, g_W: np.ndarray, velocities: dict[int, np.ndarray], bias: gtsam.imuBias.ConstantBias,
               how: str) -> None:
        """Gravity fixed, keys and links from the oldest given keyframe on."""
        start = time.perf_counter()
        self.gravity_W = np.asarray(g_W, dtype=np.float64)
        self.chain.params = combined_params(self.gravity_W, self.noise)
        t0, kf0 = self.chain.seed(velocities, bias, self.config.init.velocity_sigma)
        self.initialized = True
        self.init_time = float(t0)
        self.chain.relink()
        self.stats.update_s += time.perf_counter() - start
        logger.info("IMU: initialised (%s) at keyframe %d, gravity %s m/s^2 in the map frame", how, kf0,
                    np.round(self.gravity_W, 4))

    # ------------------------------------------------------------------ map corrections
    @property
    def scale_fixed(self) -> bool:
        """Whether the map's scale is held by the IMU (initialised; a metric map always is)."""
        return self.metric or self.initialized

    def adapt_correction(self, correction: PoseCorrection) -> PoseCorrection:
        """A correction before the contributor applies it (:class:`~fgslam.services.corrections.ObservedContributor`):
        once a monocular map's scale is fixed by the IMU, a Sim(3) correction whose scale would be
        folded into the structure is taken as SE(3): each listed keyframe keeps its corrected centre
        and rotation, the scale change is dropped (nothing folded). Otherwise unchanged."""
        if self.metric or not self.initialized or not correction.fold_scale:
            return correction

        def rigid(M: np.ndarray) -> np.ndarray:
            R, t, _ = sim3_matrix_parts(M, project=True)
            out = np.eye(4)
            out[:3, :3], out[:3, 3] = R, t
            return out

        old = {k: rigid(np.linalg.inv(U) @ correction.T_WC_new[k]) for k, U in correction.T_update.items()}
        new = {k: rigid(correction.T_WC_new[k]) for k in correction.T_update}
        scales = [s for s in correction.scale.values()]
        logger.info("IMU: loop correction taken as SE(3) (the IMU fixes the scale; its scale changes %.4f..%.4f dropped)",
                    min(scales, default=1.0), max(scales, default=1.0))
        return PoseCorrection.between(old, new, correction.solve_time_s, fold_scale=False, loops=correction.loops,
                                      n_accepted=correction.n_accepted, hold_older=correction.hold_older)

    def on_correction(self, correction: PoseCorrection) -> None:
        """After a map correction (loop, global BA, rescale; the keyframe poses already moved): the
        linked velocities, chain-start and marginal priors follow it
        (:meth:`~fgslam.services.imu_chain.ImuChain.follow_correction`); biases are kept."""
        self.chain.follow_correction(correction)

    # ------------------------------------------------------------------ prediction and reports
    def predict(self, timestamp: float) -> Optional[np.ndarray]:
        """T_WC (4x4 Sim(3) at the keyframe's scale) at ``timestamp`` predicted from the newest linked
        keyframe's state, or None (not initialised, samples do not cover, longer than ``max_bridge_s``)."""
        import gtsam  # deferred: gtsam

        if not self.initialized or not self.chain.linked:
            return None
        t_k, kf = next((t, k) for t, k in reversed(self.chain.kfs) if k in self.chain.linked)
        if not 0 <= timestamp - t_k <= self.config.max_bridge_s or not self.covered(t_k, timestamp):
            return None
        T_WB, v, bias = self.chain.state(kf)
        pim = self.buffer.preintegrate(self.chain.params, t_k, timestamp, bias)
        nav = pim.predict(gtsam.NavState(T_WB, v), bias)
        S = sim3_from_body_pose(nav.pose(), self.T_CB, float(self.backend.pose(kf).scale()))
        self.stats.predictions += 1
        return gtsam_matrix(S)

    def velocity(self, kf_id: int) -> Optional[np.ndarray]:
        """Keyframe ``kf_id``'s velocity (m/s, map frame) when it is linked, else None."""
        return self.chain.velocity(kf_id)

    def bias(self, kf_id: int) -> Optional[gtsam.imuBias.ConstantBias]:
        """Keyframe ``kf_id``'s IMU bias when it is linked, else None."""
        return self.chain.bias(kf_id)

    @property
    def inertial_state(self) -> InertialState:
        """The run's :class:`InertialState` (for the summary and the console report)."""
        acc = gyr = None
        linked = self.chain.linked_in_order()
        if self.initialized and linked:
            b = self.bias(linked[-1])
            acc, gyr = float(np.linalg.norm(b.accelerometer())), float(np.linalg.norm(b.gyroscope()))
        scale = None if not self.initialized else (1.0 if self.metric else self.scale_applied)
        return InertialState(initialised=self.initialized, time_init=self.init_time,
                             scale=None if scale is None else float(scale), scale_sigma=self.scale_sigma,
                             gravity_W=None if self.gravity_W is None else [float(x) for x in self.gravity_W],
                             accel_bias_norm=acc, gyro_bias_norm=gyr, inertial_only_runs=len(self.inertial_only))

    def summary(self) -> dict[str, object]:
        s = self.stats
        return {"initialized": self.initialized, "init_time": self.init_time, "scale": self.scale_applied,
                "gravity_W": None if self.gravity_W is None else [float(x) for x in self.gravity_W],
                "samples": s.samples, "dropped_samples": s.dropped_samples, "bad_intervals": s.bad_intervals,
                "links": s.links, "unlinked_intervals": s.unlinked, "marginalised": s.marginalised,
                "predictions": s.predictions, "update_s": s.update_s, "scale_sigma": self.scale_sigma,
                "inertial_only_runs": len(self.inertial_only)}


# ----------------------------------------------------------------------------------------- the run


def make_imu_service(config: ImuServiceConfig, backend: Backend, calibration: Optional[Calibration], has_imu: bool,
                     sensor: str, contributor: object = None, dataset_noise: Optional[dict[str, float]] = None,
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
    service = ImuService(config, backend, T_BC, metric=sensor in ("stereo", "rgbd"),
                         contributor=contributor if takes_corrections(contributor) else None,
                         dataset_noise=dataset_noise)
    return service
