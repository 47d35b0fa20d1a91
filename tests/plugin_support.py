"""Support of the factor-plugin tests: synthetic ground-vehicle drives from the generator's analytic
trajectories, a toy odometry contributor that drifts like monocular visual odometry, and a
positions file writer."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np

from fgslam.io.synth.presets import build_trajectory, default_config
from fgslam.io.synth.sequence import camera_mount
from fgslam.loop.closure import LoopCorrection


def sim3_to_gtsam(T: np.ndarray) -> gtsam.Similarity3:
    """4x4 ``[[s R, t], [0, 1]]`` -> gtsam.Similarity3 (``X -> s (R X + t / s)``)."""
    s = float(np.cbrt(np.linalg.det(T[:3, :3])))
    return gtsam.Similarity3(gtsam.Rot3(T[:3, :3] / s), T[:3, 3] / s, s)


def gtsam_to_sim3(S: gtsam.Similarity3) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = S.scale() * S.rotation().matrix()
    T[:3, 3] = S.scale() * np.asarray(S.translation())
    return T


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


class DriftingOdometry:
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
                 first_pose: np.ndarray | None = None, initial_scale: float = 1.0, plugins=()) -> None:
        self.backend, self.t, self.T_WC, self.rng = backend, t, T_WC, rng
        self.rot_sigma, self.trans_sigma, self.scale_drift = rot_sigma, trans_sigma, scale_drift
        self.window, self.iterations = window, iterations
        self.plugins = [p for p in plugins if callable(getattr(p, "poll", None))]
        self.sigmas = (np.array([rot_sigma] * 3 + [trans_sigma] * 3 + [1e-3]) if factor_sigmas is None
                       else np.asarray(factor_sigmas, dtype=np.float64))
        self.Z: dict[tuple[int, int], np.ndarray] = {}
        self.handles: dict[tuple[int, int], int] = {}
        self.first_pose = T_WC[0] if first_pose is None else first_pose
        self.log_scale = float(np.log(initial_scale))
        if hasattr(backend, "add_contributor"):
            backend.add_contributor(self)

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
        for plugin in self.plugins:  # the safe point after a frame
            plugin.poll(b)

    def _add_factor(self, i: int, j: int) -> None:
        factor = gtsam.BetweenFactorSimilarity3(self.backend.pose_key(i) if hasattr(self.backend, "pose_key")
                                                else gtsam.symbol("x", i),
                                                gtsam.symbol("x", j), sim3_to_gtsam(self.Z[(i, j)]),
                                                gtsam.noiseModel.Diagonal.Sigmas(self.sigmas))
        self.handles[(i, j)] = self.backend.add_factor(factor, owner=self.name)

    def apply_correction(self, correction: LoopCorrection) -> None:
        if not correction.fold_scale:
            return
        # its measurements from now on come in the folded scale of the newest keyframe's structure
        self.log_scale += float(np.log(correction.update_for(max(self.backend.keyframe_ids))[1]))
        for (i, j), Z in self.Z.items():
            self.Z[(i, j)] = LoopCorrection.fold_relative(Z, correction.update_for(i)[1])
            if (i, j) in self.handles:
                self.backend.remove_factor(self.handles.pop((i, j)))
                self._add_factor(i, j)

    def run(self, n: int | None = None) -> np.ndarray:
        n = len(self.t) if n is None else n
        for k in range(n):
            self.step(k)
        return np.array([self.backend.pose_matrix(k) for k in range(n)])


def ate_se3(T_est: np.ndarray, T_true: np.ndarray) -> float:
    """RMS position error after the best rigid (no scale) alignment."""
    from fgslam.eval import umeyama

    a = umeyama(T_est[:, :3, 3], T_true[:, :3, 3], with_scale=False)
    aligned = T_est[:, :3, 3] @ a.R.T + a.t
    return float(np.sqrt(np.mean(np.sum((aligned - T_true[:, :3, 3]) ** 2, axis=1))))


class GraphBackend:
    """Stand-in for :class:`fgslam.backend.graph.Backend` (until it is merged) over plain gtsam graphs,
    with the part of BACKEND_SPEC.md's interface that the plugins use: keyframes with timestamps and
    callbacks, factors by handle and owner (unknown keys: OptimizationError naming the key), an anchor
    gauge prior, windowed / global optimisation with gtsam's LM (keys outside the window held by a
    tight prior), the Sim(3) pose-graph correction and corrections applied to contributors."""

    ANCHOR_SIGMA = 1e-3
    FIXED_SIGMA = 1e-7
    PGC_SIGMAS = np.array([1e-2] * 3 + [1e-1] * 3 + [1e-2])

    def __init__(self) -> None:
        self.values = gtsam.Values()
        self.times: dict[int, float] = {}
        self.factors: dict[int, tuple[object, str, tuple[int, ...]]] = {}
        self.callbacks: list = []
        self.contributors: list = []
        self.anchor: int | None = None
        self._anchor_pose = None
        self._next = 0

    def pose_key(self, kf_id: int) -> int:
        return gtsam.symbol("x", kf_id)

    @property
    def keyframe_ids(self) -> list[int]:
        return sorted(self.times)

    def has_keyframe(self, kf_id: int) -> bool:
        return kf_id in self.times

    def timestamp(self, kf_id: int) -> float:
        return self.times[kf_id]

    def add_keyframe(self, kf_id: int, T_WC: np.ndarray, timestamp: float) -> int:
        key = self.pose_key(kf_id)
        self.values.insert(key, sim3_to_gtsam(np.asarray(T_WC)))
        self.times[kf_id] = float(timestamp)
        if self.anchor is None and len(self.times) == 1:
            self.set_gauge(anchor=kf_id)
        for callback in list(self.callbacks):
            callback(kf_id, float(timestamp), key)
        return key

    def on_keyframe(self, callback) -> None:
        self.callbacks.append(callback)

    def set_gauge(self, anchor: int | None = None, scale_pair=None) -> None:
        self.anchor = anchor
        self._anchor_pose = None if anchor is None else self.pose(anchor)

    def pose(self, kf_id: int) -> gtsam.Similarity3:
        return self.values.atSimilarity3(self.pose_key(kf_id))

    def pose_matrix(self, kf_id: int) -> np.ndarray:
        return gtsam_to_sim3(self.pose(kf_id))

    def set_pose(self, kf_id: int, T_WC: np.ndarray) -> None:
        self.values.update(self.pose_key(kf_id), sim3_to_gtsam(np.asarray(T_WC)))
        if kf_id == self.anchor:
            self._anchor_pose = self.pose(kf_id)

    def add_factor(self, factor, owner: str = "user") -> int:
        from fgslam.errors import OptimizationError

        keys = tuple(int(k) for k in factor.keys())
        for key in keys:
            if not self.values.exists(key):
                raise OptimizationError(f"factor of '{owner}' on unknown key {gtsam.DefaultKeyFormatter(key)}")
        self._next += 1
        self.factors[self._next] = (factor, owner, keys)
        return self._next

    def remove_factor(self, handle: int) -> None:
        del self.factors[handle]

    def factor_handles(self, owner: str) -> list[int]:
        return [h for h, (_, o, _) in self.factors.items() if o == owner]

    def add_contributor(self, contributor) -> None:
        self.contributors.append(contributor)

    def apply_correction(self, correction) -> None:
        for kf_id in self.keyframe_ids:
            T_new, _ = correction.apply_pose(kf_id, self.pose_matrix(kf_id))
            self.set_pose(kf_id, T_new)
        for contributor in self.contributors:
            contributor.apply_correction(correction)

    def _solve(self, graph, keys: set[int], iterations: int) -> None:
        initial = gtsam.Values()
        for key in keys:
            initial.insert(key, self.values.atSimilarity3(key))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(iterations)
        result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
        for key in keys:
            self.values.update(key, result.atSimilarity3(key))

    def _gauge_graph(self, graph, keys: set[int]) -> None:
        if self.anchor is not None and self.pose_key(self.anchor) in keys:
            graph.add(gtsam.PriorFactorSimilarity3(self.pose_key(self.anchor), self._anchor_pose,
                                                   gtsam.noiseModel.Isotropic.Sigma(7, self.ANCHOR_SIGMA)))

    def optimize_window(self, free_kf_ids, iterations: int) -> None:
        free = {self.pose_key(k) for k in free_kf_ids}
        graph = gtsam.NonlinearFactorGraph()
        keys: set[int] = set()
        for factor, _, fkeys in self.factors.values():
            if free & set(fkeys):
                graph.add(factor)
                keys |= set(fkeys)
        for key in keys - free:
            graph.add(gtsam.PriorFactorSimilarity3(key, self.values.atSimilarity3(key),
                                                   gtsam.noiseModel.Isotropic.Sigma(7, self.FIXED_SIGMA)))
        self._gauge_graph(graph, keys)
        if graph.size():
            self._solve(graph, keys | free, iterations)

    def optimize_global(self, iterations: int = 30) -> None:
        graph = gtsam.NonlinearFactorGraph()
        for factor, _, _ in self.factors.values():
            graph.add(factor)
        keys = {self.pose_key(k) for k in self.times}
        self._gauge_graph(graph, keys)
        self._solve(graph, keys, iterations)

    def correct_pose_graph(self, kf_ids=None) -> dict[int, np.ndarray]:
        ids = self.keyframe_ids if kf_ids is None else sorted(kf_ids)
        keys = {self.pose_key(k) for k in ids}
        graph = gtsam.NonlinearFactorGraph()
        noise = gtsam.noiseModel.Diagonal.Sigmas(self.PGC_SIGMAS)
        for a, b in zip(ids[:-1], ids[1:]):
            Z = self.pose(a).inverse() * self.pose(b)
            graph.add(gtsam.BetweenFactorSimilarity3(self.pose_key(a), self.pose_key(b), Z, noise))
        for factor, owner, fkeys in self.factors.values():
            if set(fkeys) <= keys and owner != "odometry":
                graph.add(factor)
        self._gauge_graph(graph, keys)
        saved = gtsam.Values(self.values)
        self._solve(graph, keys, 100)
        out = {k: self.pose_matrix(k) for k in ids}
        self.values = saved
        return out
