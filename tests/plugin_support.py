"""Support of the factor-plugin tests: synthetic ground-vehicle drives from the generator's analytic
trajectories, a toy odometry contributor that drifts like monocular visual odometry, and a
positions file writer."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np

from fgslam.backend.graph import as_similarity3
from fgslam.frontends.base import FrameStatus, Frontend
from fgslam.backend.keys import pose_key
from fgslam.io.synth.motions import build_trajectory
from fgslam.io.synth.scenarios import camera_mount, default_config
from fgslam.loop.records import LoopCorrection


def drive(preset: str = "street-loop", seconds: float | None = None, keyframe_dt: float = 0.3,
          **overrides) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Keyframe times (N,), camera poses ``T_WC`` (N, 4, 4) and the camera's true ground normal in
    camera coordinates (3,) and height above the ground plane z = 0 (N,) along a synthetic preset's
    analytic trajectory (street-loop: 606 m around a block; highway: 27 m/s)."""
    cfg = default_config(preset)
    for section, values in overrides.items():
        for name, value in values.items():
            setattr(getattr(cfg, section), name, value)
    duration = cfg.loop_duration_s() if seconds is None else seconds
    t = np.arange(0.0, duration + 1e-9, keyframe_dt)
    T_WB = build_trajectory(cfg).sample(t).T_WB()
    T_BC = camera_mount(cfg.camera)
    T_WC = T_WB @ T_BC
    up_C = T_BC[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # world z (the ground normal) in a level body's camera
    return t, T_WC, up_C, T_WC[:, 2, 3]


def path_length(T_WC: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(T_WC[:, :3, 3], axis=0), axis=1).sum())


def write_positions(path: Path, t: np.ndarray, T_WC: np.ndarray, rate_hz: float, sigma: float,
                    rng: np.random.Generator) -> Path:
    """A positions file: the true camera centre at ``rate_hz`` (linear between keyframes) plus
    N(0, sigma^2) noise on each axis."""
    ts = np.arange(t[0], t[-1] + 1e-9, 1.0 / rate_hz)
    p = np.stack([np.interp(ts, t, T_WC[:, k, 3]) for k in range(3)], axis=1) + rng.normal(scale=sigma, size=(len(ts), 3))
    path.write_text("# t x y z\n" + "".join(f"{a:.6f} {x:.6f} {y:.6f} {z:.6f}\n" for a, (x, y, z) in zip(ts, p)))
    return path


class DriftingOdometry(Frontend):
    """A toy contributor that feeds keyframes and Sim(3) odometry factors into a backend, the way a
    visual-odometry frontend would: each new keyframe is dead-reckoned from the backend's current
    estimate of the previous one with a measured relative pose, the measurement being the true one
    with rotation and translation noise and (``scale_drift``) a translation scale that drifts as a
    random walk in log scale, like monocular visual odometry. A monocular map starts in a frame and
    scale of its own: ``first_pose`` (e.g. the identity) and ``initial_scale`` (map units per metre). Its measurements are its structure:
    :meth:`apply_correction` folds a correction's scale into them (``LoopCorrection.fold_relative``)."""

    name = "odometry"

    def __init__(self, backend, t: np.ndarray, T_WC: np.ndarray, rng: np.random.Generator, *,
                 rot_sigma: float = 0.002, trans_sigma: float = 0.01, scale_drift: float = 0.0,
                 window: int = 5, iterations: int = 3, factor_sigmas: np.ndarray | None = None,
                 first_pose: np.ndarray | None = None, initial_scale: float = 1.0) -> None:
        self.backend, self.t, self.T_WC, self.rng = backend, t, T_WC, rng
        self.rot_sigma, self.trans_sigma, self.scale_drift = rot_sigma, trans_sigma, scale_drift
        self.window, self.iterations = window, iterations
        self.sigmas = (np.array([rot_sigma] * 3 + [trans_sigma] * 3 + [1e-3]) if factor_sigmas is None
                       else np.asarray(factor_sigmas, dtype=np.float64))
        self.Z: dict[tuple[int, int], np.ndarray] = {}
        self.handles: dict[tuple[int, int], int] = {}
        self.first_pose = T_WC[0] if first_pose is None else first_pose
        self.log_scale = float(np.log(initial_scale))

    def measure(self, i: int, j: int) -> np.ndarray:
        T_ij = np.linalg.inv(self.T_WC[i]) @ self.T_WC[j]
        self.log_scale += self.rng.normal(scale=self.scale_drift)
        Z = np.eye(4)
        Z[:3, :3] = T_ij[:3, :3] @ gtsam.Rot3.Expmap(self.rng.normal(scale=self.rot_sigma, size=3)).matrix()
        step = float(np.linalg.norm(T_ij[:3, 3]))
        Z[:3, 3] = np.exp(self.log_scale) * T_ij[:3, 3] + self.rng.normal(scale=self.trans_sigma * max(step, 1e-3), size=3)
        return Z

    def step(self, k: int) -> None:
        """Add keyframe ``k`` (the first at ``first_pose``), its odometry factor, and optimise the window."""
        b = self.backend
        if k == 0:
            b.add_keyframe(0, self.first_pose, float(self.t[0]))
            return
        Z = self.measure(k - 1, k)
        self.Z[(k - 1, k)] = Z
        b.add_keyframe(k, b.pose_matrix(k - 1) @ Z, float(self.t[k]))
        self._add_factor(k - 1, k)
        free = [kf for kf in b.keyframe_ids[-self.window:]]
        b.optimize_window(free, self.iterations)

    def process(self, k: int) -> None:
        """The frontend interface of a run (the system steps it: see :func:`plugin_system`)."""
        self.step(k)

    def trajectory(self):
        ids = self.backend.keyframe_ids
        return self.t[ids], np.array([self.backend.pose_matrix(k) for k in ids]), ["tracked"] * len(ids)

    def num_keyframes(self) -> int:
        return len(self.backend.keyframe_ids)

    def _add_factor(self, i: int, j: int) -> None:
        factor = gtsam.BetweenFactorSimilarity3(pose_key(i), pose_key(j), as_similarity3(self.Z[(i, j)]),
                                                gtsam.noiseModel.Diagonal.Sigmas(self.sigmas))
        self.handles[(i, j)] = self.backend.add_factor(factor, owner=self.name)

    def apply_correction(self, correction: LoopCorrection) -> None:
        """As a frontend whose keyframe poses live in the backend: move them, fold the scale."""
        for kf_id in self.backend.keyframe_ids:
            T_new, _ = correction.apply_pose(kf_id, self.backend.pose_matrix(kf_id))
            self.backend.set_pose(kf_id, T_new)
        if not correction.fold_scale:
            return
        # its measurements from now on come in the folded scale of the newest keyframe's structure
        self.log_scale += float(np.log(correction.update_for(max(self.backend.keyframe_ids))[1]))
        for (i, j), Z in self.Z.items():
            self.Z[(i, j)] = LoopCorrection.fold_relative(Z, correction.update_for(i)[1])
            if (i, j) in self.handles:
                self.backend.remove_factor(self.handles.pop((i, j)))
                self._add_factor(i, j)


def plugin_system(odometry, entries, timestamps=None):
    """The run's system around ``odometry`` (a DriftingOdometry, or one without ``apply_correction``)
    with the factor plugins of ``entries`` (none: no plugin service); it steps keyframe numbers as frames."""
    from fgslam.services.plugins import FactorPlugins
    from fgslam.run.system import SlamSystem

    plugins = FactorPlugins(entries, odometry.backend, timestamps, contributor=odometry) if entries else None
    return SlamSystem(odometry, odometry.backend, plugins=plugins)


def run_drive(system, n: int) -> np.ndarray:
    """Feed ``n`` keyframes through ``system`` (:func:`plugin_system`), finish, and return the
    backend's final keyframe poses (n, 4, 4)."""
    for k in range(n):
        system.step(k)
    system.finish()
    return np.array([system.backend.pose_matrix(k) for k in range(n)])


def ate_se3(T_est: np.ndarray, T_true: np.ndarray) -> float:
    """RMS position error after the best rigid (no scale) alignment."""
    from fgslam.core.geometry import umeyama

    a = umeyama(T_est[:, :3, 3], T_true[:, :3, 3], with_scale=False)
    aligned = T_est[:, :3, 3] @ a.R.T + a.t
    return float(np.sqrt(np.mean(np.sum((aligned - T_true[:, :3, 3]) ** 2, axis=1))))


class OdometryFrontend(Frontend):
    """A frontend for ``run_slam`` that makes every frame a keyframe of its backend, posed by a
    :class:`DriftingOdometry` over the dataset's ground truth (no images used); its trajectory is the
    backend's keyframe poses. It is the contributor of the plugins' corrections (through its odometry)."""

    name = "odometry"

    def __init__(self, backend, t: np.ndarray, T_WC: np.ndarray, rng: np.random.Generator, **odometry) -> None:
        self.odometry = DriftingOdometry(backend, t, T_WC, rng, **odometry)
        self.backend = backend
        self.t = t

    def process(self, frame) -> FrameStatus:
        self.odometry.step(frame.index)
        return FrameStatus(frame.index, frame.timestamp, self.backend.pose_matrix(frame.index), "tracked",
                           is_keyframe=True, num_valid=1)

    def apply_correction(self, correction) -> None:
        self.odometry.apply_correction(correction)

    def trajectory(self):
        ids = self.backend.keyframe_ids
        return self.t[ids], np.array([self.backend.pose_matrix(k) for k in ids]), ["tracked"] * len(ids)

    def num_keyframes(self) -> int:
        return len(self.backend.keyframe_ids)


class NoContributor(Frontend):
    """The same odometry as a frontend without ``apply_correction``: plugins' corrections then move the
    backend's keyframes with their Sim(3) scales (nothing folds them), which a Sim(3) map absorbs: new
    keyframes are dead-reckoned from the corrected, scaled poses."""

    def __init__(self, odometry: DriftingOdometry) -> None:
        self.odometry = odometry
        self.backend = odometry.backend

    def process(self, k: int) -> None:
        self.odometry.step(k)

    def trajectory(self):
        return self.odometry.trajectory()

    def num_keyframes(self) -> int:
        return self.odometry.num_keyframes()
