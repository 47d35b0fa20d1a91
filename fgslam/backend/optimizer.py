"""The backend's solves over its :class:`~fgslam.backend.store.GraphStore` (docs/architecture.md section 8),
all through the one LM loop (:func:`fgslam.backend.solver.levenberg_marquardt`):

- :meth:`Optimizer.optimize_window`: the given keyframes are free (LM settings of ``map.window``: a
  window runs the frontend's few iterations per frame). With ``map.window.leaving: fixed`` every
  other key keeps its value (:mod:`fgslam.backend.window`). With ``marginalize`` the persistent
  built-in factors over keys outside the window are linearised at the current estimate and the
  outside keys eliminated (GTSAM's partial elimination), which leaves a linear prior
  (``gtsam.LinearContainerFactor``) on the window keys they connect to. Not marginalised: the gauge
  and the contributors' blocks (a frontend rebuilds its blocks, with the frames it holds fixed, for
  every optimisation, so it decides what its measurements of old frames still say).
- :meth:`Optimizer.optimize_global`: every key.
- :meth:`Optimizer.correct_pose_graph`: Sim(3) between factors from the current estimate between
  consecutive keyframes plus the persistent factors over them; returns the new poses.
- :meth:`Optimizer.marginalize_variables`: non-keyframe variables out of the graph, as a linear prior.

Solvers (``map.solver``): ``lm`` (``python_lm`` is an alias): damped GTSAM elimination of the
linearised graph (built-in factors linearised by gtsam, block pieces as ``HessianFactor``s);
``isam2``: the step of each LM iteration comes from a ``gtsam.ISAM2``
(:class:`~fgslam.backend.window.Isam2Stepper`); a step that raises the true cost is halved.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Callable, Iterable

import numpy as np

from ..core.errors import OptimizationError
from ..factors.schur import torch_threads
from ..core.lie import gtsam_matrix
from .config import BackendConfig
from .gauge import Gauge
from .keys import key_name, pose_key
from .motion_only import optimize_pose
from .pose_graph import PoseGraphIsam2, anchor_prior, diagonal_model
from .solver import LMSettings, NonlinearProblem, levenberg_marquardt
from .store import GraphStore
from .window import Isam2Stepper, WindowProblem, eliminate_keys, restricted_factor

logger = logging.getLogger(__name__)

MIN_MARGINAL_REGULARIZATION = 1e-12  # marginalize_variables always regularises (unobserved directions)


@dataclass
class OptimizeReport:
    """What one optimisation of the backend did."""

    solver: str
    initial_cost: float
    final_cost: float
    iterations: int
    converged: bool
    seconds: float
    free_keys: int = 0


class Optimizer:
    """The solves of one backend: its store's factors and blocks plus the gauge's factors."""

    def __init__(self, config: BackendConfig, store: GraphStore, gauge: Gauge):
        self.config = config
        self.store = store
        self.gauge = gauge
        self._window_hooks: list[Callable] = []  # free keyframes -> extra keys freed with a window

    def on_window(self, hook: Callable[[list[int]], Iterable[int]]) -> None:
        """Register ``hook(free_kf_ids) -> keys``: non-keyframe variables that every
        :meth:`optimize_window` frees besides the window's own (e.g. the velocities and biases of the IMU's
        fixed-lag window, which no visual factor holds once their keyframe's pose is fixed)."""
        self._window_hooks.append(hook)

    # ------------------------------------------------------------------ problems
    def nonlinear_graph(self, include_gauge: bool = True):
        """Built-in factors (and the gauge factors of a global optimisation) as a NonlinearFactorGraph
        (blocks excluded)."""
        import gtsam  # deferred: gtsam

        graph = gtsam.NonlinearFactorGraph()
        for factor, _, _ in self.store.factors.entries.values():
            graph.add(factor)
        if include_gauge:
            for factor in self.gauge.factors(self.store.keyframe_ids):
                graph.add(factor)
        return graph

    def _problem(self, free_keys: list[int], refine_steps: int | None = None) -> WindowProblem:
        """The optimisation problem over ``free_keys`` (module docstring)."""
        import gtsam  # deferred: gtsam

        free = set(free_keys)
        keyframe_of = self.store.keyframe_of
        free_kfs = [keyframe_of[k] for k in free_keys if k in keyframe_of]
        factors = [(f, keys) for f, keys, _ in self.store.factors.entries.values()]
        factors += [(f, tuple(int(k) for k in f.keys())) for f in self.gauge.factors(free_kfs)]
        factors = [(f, keys) for f, keys in factors if any(k in free for k in keys)]
        if self.config.window.leaving == "marginalize" and any(any(k not in free for k in keys) for _, keys in factors):
            factors = [(f, keys) for f, keys in factors if all(k in free for k in keys)] + self._marginal_prior(free)
        inner = gtsam.NonlinearFactorGraph()
        cross = []
        for factor, keys in factors:
            if all(k in free for k in keys):
                inner.add(factor)
            elif any(k in free for k in keys):
                cross.append(factor)
        blocks = [b for b in self.store.factors.blocks() if any(int(k) in free for k in b.keys)]
        needed = set(free)
        for factor in cross:
            needed.update(int(k) for k in factor.keys())
        for block in blocks:
            needed.update(int(k) for k in block.keys)
        steps = self.config.refine_steps if refine_steps is None else refine_steps
        return WindowProblem(self.store.values_of(needed), sorted(free), inner, cross, blocks, steps,
                             self.config.refine_each_iteration,
                             self.config.damp_structure and self.config.solver_kind != "isam2")

    def _marginal_prior(self, free: set) -> list:
        """``window.leaving: marginalize``: the persistent built-in factors (and the anchor prior and
        range) that reach a key outside ``free``, linearised at the current estimate, the outside keys
        eliminated; the remaining linear factors on free keys as ``LinearContainerFactor``s (the
        prior they leave on the window)."""
        import gtsam  # deferred: gtsam

        estimate = self.store.estimate
        outside_factors = [(f, keys) for f, keys, _ in self.store.factors.entries.values()
                           if any(k not in free for k in keys)]
        outside_factors += [(f, tuple(int(k) for k in f.keys())) for f in self.gauge.factors(())
                            if any(int(k) not in free for k in f.keys())]  # the anchor and the range
        if not outside_factors:
            return []
        gfg = gtsam.GaussianFactorGraph()
        outside = []
        for factor, keys in outside_factors:
            gfg.push_back(factor.linearize(estimate))
            outside.extend(k for k in keys if k not in free and k not in outside)
        reg = self.config.window.marginal_regularization
        dims = {int(k): int(d) for k, d in estimate.dims().items()}
        remaining = eliminate_keys(gfg, outside, dims, reg, hint="; set map.window.marginal_regularization > 0")
        lin_point = gtsam.Values(estimate)
        for key in estimate.keys():
            if int(key) not in free:
                lin_point.erase(key)
        return [(factor, tuple(int(k) for k in factor.keys())) for factor in _linear_priors(remaining, lin_point)]

    def cost(self) -> float:
        """GTSAM-convention total cost at the current estimate (global gauge, blocks' current structure)."""
        return self._problem(self._every_key()).cost()

    def linearize(self):
        """gtsam.GaussianFactorGraph of the whole problem at the current estimate (global optimisation's)."""
        return self._problem(self._every_key()).linearize()

    def marginal_covariances(self, kf_ids: list[int] | None = None) -> dict[int, np.ndarray]:
        """Marginal covariances (7, 7) of keyframe poses in the tangent ``[w, u, lambda]`` at the
        current estimate (Laplace approximation of the linearised problem, blocks included)."""
        import gtsam  # deferred: gtsam

        with torch_threads(self.config.threads):
            marginals = gtsam.Marginals(self.linearize(), self.store.estimate)
        ids = self.store.keyframe_ids if kf_ids is None else kf_ids
        return {kf: np.asarray(marginals.marginalCovariance(pose_key(kf))) for kf in ids}

    def _every_key(self) -> list[int]:
        return [int(k) for k in self.store.estimate.keys()]

    # ------------------------------------------------------------------ optimisation
    def settings(self, iterations: int | None, window: bool = False) -> LMSettings:
        """The LM settings of ``map`` (``window``: with ``map.window``'s lambda factor)."""
        cfg = self.config
        return LMSettings(
            max_iterations=cfg.max_iterations if iterations is None else int(iterations),
            lambda_initial=cfg.lambda_initial,
            lambda_factor=cfg.window.lambda_factor if window else cfg.lambda_factor, lambda_max=cfg.lambda_max,
            lambda_min=cfg.lambda_min, relative_tolerance=cfg.relative_tolerance,
            absolute_tolerance=cfg.absolute_tolerance, step_tolerance=cfg.step_tolerance,
            max_backtracks=cfg.max_backtracks,
        )

    def optimize_pose(self, blocks, values, key: int, iterations: int | None = None, hold=None,
                      step_tolerance: float | None = None):
        """Motion-only optimisation of ``key`` against ``blocks`` whose other keys are held at ``values``
        (a frame tracked against its keyframe; :mod:`fgslam.backend.motion_only`), with the map's LM
        settings (``step_tolerance``: the caller's own instead of ``map.step_tolerance``). The backend's
        own graph is not touched; returns a ``MotionOnlyResult``."""
        settings = self.settings(iterations)
        if step_tolerance is not None:
            settings = replace(settings, step_tolerance=float(step_tolerance))
        return optimize_pose(blocks, values, key, settings, hold)

    def optimize_window(self, free_kf_ids: Iterable[int], iterations: int | None = None,
                        extra_free_keys: Iterable[int] = ()) -> OptimizeReport:
        """Optimise the poses of ``free_kf_ids`` (and ``extra_free_keys``, other variables) with every
        other key held fixed or marginalised (``map.window.leaving``; module docstring);
        ``iterations``: LM iterations (default ``map.max_iterations``). Updates the free poses and
        the blocks' structure."""
        free_kf_ids = list(free_kf_ids)
        free = []
        for kf in free_kf_ids:
            self.store.check_keyframe(kf)
            free.append(pose_key(kf))
            free.extend(self.store.attached.get(int(kf), ()))  # keys attached to a free keyframe are free
        kfs = [int(kf) for kf in free_kf_ids] if self._window_hooks else []
        extra_free_keys = list(extra_free_keys) + [k for hook in self._window_hooks for k in hook(kfs)]
        for key in extra_free_keys:
            if not self.store.has_key(key):
                raise OptimizationError(f"unknown key {key_name(int(key))}")
            free.append(int(key))
        return self._optimize(list(dict.fromkeys(free)), iterations, window=True)

    def optimize_global(self, iterations: int | None = None) -> OptimizeReport:
        """Optimise every key (``iterations``: default ``map.max_iterations``)."""
        return self._optimize(self._every_key(), iterations)

    def _optimize(self, free: list[int], iterations: int | None, window: bool = False) -> OptimizeReport:
        start = time.perf_counter()
        kind = self.config.solver_kind
        refine_steps = self.config.window.refine_steps if window else self.config.refine_steps
        with torch_threads(self.config.threads):
            problem = self._problem(free, refine_steps)
            initial = problem.refine(refine_steps)
            propose = Isam2Stepper(problem) if kind == "isam2" else None
            try:
                lm = levenberg_marquardt(problem, self.settings(iterations, window), propose=propose,
                                         initial_cost=initial)  # the cost refine() just evaluated
            finally:
                problem.end_damping()
            final = problem.refine(refine_steps) if refine_steps > 0 else lm.final_cost
        self.store.update(problem.free_values(), problem.free)
        report = OptimizeReport(kind, initial, final, lm.iterations, lm.converged, time.perf_counter() - start,
                                len(free))
        logger.debug("optimize: %s", report)
        return report

    # ------------------------------------------------------------------ marginalisation
    def marginalize_variables(self, keys: Iterable[int], condition_on: Iterable[int] = (), owner: str = "marginal") -> list[int]:
        """Remove the non-keyframe variables ``keys`` and every persistent factor on them, keeping what
        those factors said about the other keys they reach as a linear prior (their Gaussian marginal at
        the current estimate: the factors linearised, ``keys`` eliminated, the rest as
        ``gtsam.LinearContainerFactor``s owned by ``owner``). Keys in ``condition_on`` are held at their
        current value instead (their columns dropped: the prior then does not touch them; e.g. a
        keyframe pose that stays in the map, fixed outside the window). Returns the new factors' handles."""
        import gtsam  # deferred: gtsam

        store = self.store
        keys = [int(k) for k in keys]
        for key in keys:
            store.check_variable(key, "only existing non-keyframe variables can be marginalised, not {}")
        drop = set(keys)
        held = {int(k) for k in condition_on}
        touching = [(h, f, fkeys) for h, (f, fkeys, _) in store.factors.entries.items() if any(k in drop for k in fkeys)]
        dims = {int(k): int(d) for k, d in store.estimate.dims().items()}
        gfg = gtsam.GaussianFactorGraph()
        reached: set[int] = set()
        for _, factor, fkeys in touching:
            free = {k for k in fkeys if k not in held}
            restricted = restricted_factor(factor.linearize(store.estimate), fkeys, free, dims)
            if restricted is not None:
                gfg.push_back(restricted)
                reached.update(k for k in free if k not in drop)
        # directions no factor observes stay determinate: always a (tiny) regularisation here
        remaining = eliminate_keys(gfg, keys, dims, max(self.config.window.marginal_regularization,
                                                        MIN_MARGINAL_REGULARIZATION))
        for handle, _, _ in touching:
            store.factors.remove(handle)
        for key in keys:
            store.remove_variable(key)
        lin_point = store.values_of(reached) if reached else gtsam.Values()
        return [store.factors.add(factor, owner) for factor in _linear_priors(remaining, lin_point)]

    # ------------------------------------------------------------------ pose graph
    def correct_pose_graph(self, kf_ids: Iterable[int] | None = None, iterations: int | None = None) -> dict[int, np.ndarray]:
        """Sim(3) pose-graph correction over ``kf_ids`` (default every keyframe; in insertion order):
        the graph of :meth:`pose_graph_problem`, solved by the one LM loop (or iSAM2 steps). Returns
        the new T_WC (4x4) per keyframe; does not apply them (``set_pose`` does)."""
        graph, values, ids = self.pose_graph_problem(kf_ids)
        if not ids:
            return {}
        problem = NonlinearProblem(graph, values)
        propose = PoseGraphIsam2(graph, values).bind(problem) if self.config.solver_kind == "isam2" else None
        report = levenberg_marquardt(problem, self.settings(iterations), propose=propose)
        logger.debug("pose graph over %d keyframes: cost %.6g -> %.6g in %d iterations", len(ids),
                     report.initial_cost, report.final_cost, report.iterations)
        at = problem.values.atSimilarity3
        return {kf: gtsam_matrix(at(pose_key(kf))) for kf in ids}

    def pose_graph_problem(self, kf_ids: Iterable[int] | None = None):
        """``(graph, values, ids)`` of the pose-graph correction over ``kf_ids``:
        ``BetweenFactorSimilarity3`` between consecutive keyframes from the current estimate (sigmas
        ``map.pose_graph``), the persistent factors whose keys are all among them (loops, user
        factors), a 7-dof prior (``gauge.anchor_sigma``) on the first at its current pose; ``values``
        a copy of their current poses; ``ids`` the keyframes in insertion order."""
        import gtsam  # deferred: gtsam

        store = self.store
        all_ids = store.keyframe_ids
        ids = all_ids if kf_ids is None else [int(k) for k in kf_ids]
        for kf in ids:
            store.check_keyframe(kf)
        order = {kf: i for i, kf in enumerate(all_ids)}
        ids = sorted(set(ids), key=order.__getitem__)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        if not ids:
            return graph, values, ids
        pg = self.config.pose_graph
        sigmas = np.array([pg.rotation_sigma] * 3 + [pg.translation_sigma] * 3 + [pg.log_scale_sigma])
        odometry = diagonal_model(sigmas)
        keys = [pose_key(kf) for kf in ids]
        estimate = store.estimate
        poses = [estimate.atSimilarity3(key) for key in keys]
        if len(ids) == len(all_ids) and estimate.size() == len(ids):
            values = gtsam.Values(estimate)  # one C++ copy (4,541 poses: 2 ms against 0.1 s insert by insert)
        else:
            for key, pose in zip(keys, poses):
                values.insert(key, pose)
        add, between = graph.add, gtsam.BetweenFactorSimilarity3
        for a in range(len(keys) - 1):
            add(between(keys[a], keys[a + 1], poses[a].between(poses[a + 1]), odometry))
        key_set = set(keys)
        for factor, fkeys, _ in store.factors.entries.values():
            if all(k in key_set for k in fkeys):
                add(factor)
        add(anchor_prior(keys[0], poses[0], self.config.gauge.anchor_sigma))
        return graph, values, ids


def _linear_priors(remaining, lin_point) -> list:
    """The non-empty factors of the eliminated graph ``remaining`` as ``gtsam.LinearContainerFactor``s
    linearised at ``lin_point``."""
    import gtsam  # deferred: gtsam

    out = []
    for i in range(remaining.size()):
        factor = remaining.at(i)
        if factor is None or len(factor.keys()) == 0:
            continue
        out.append(gtsam.LinearContainerFactor(factor, lin_point))
    return out
