"""The map: keyframe Sim(3) poses in one GTSAM graph, visual blocks, gauge and solvers.

Keyframe ``kf`` has the gtsam key :func:`pose_key` ``= gtsam.symbol('x', kf)`` holding a
``gtsam.Similarity3`` T_WC (camera-to-world; fgslam.lie's ``Sim3(R, t, s)`` maps to
``Similarity3(Rot3(R), t / s, s)``). Tangents are gtsam's ``[w, u, lambda]`` with right perturbation.

Contents of the optimisation problem:
- built-in gtsam factors (``BetweenFactorSimilarity3``, ``PriorFactorSimilarity3``, IMU...) added by
  handle with :meth:`SlamMap.add_factor`;
- visual blocks (:class:`fgslam.factors.schur.VisualBlock`), which own their structure and are
  Schur-reduced to dense pose systems at every linearisation (:meth:`SlamMap.add_block`);
- gauge factors the map maintains itself (docs/design.md section 4): a 7-dof prior on the anchor
  (oldest) keyframe, optionally a log-scale prior on every keyframe (inverse-depth frontends, where
  each keyframe's scale is a pure gauge) and a range constraint between the first two keyframes
  (monocular world scale).

Solvers (``MapConfig.solver``):
- ``python_lm``: Levenberg-Marquardt driven from Python: ``graph.linearize`` of the built-in
  factors plus the blocks' (H, g, c) as HessianFactor pieces, ``gfg.optimize()``, retract, joint
  trial structure by back-substitution, acceptance with the true cost, re-refined structure;
- ``gtsam_lm``: outer relinearisation loop around gtsam's LevenbergMarquardtOptimizer with each
  block wrapped as a ``LinearContainerFactor``;
- ``isam2``: a persistent iSAM2 (relinearise threshold 0, skip 1, wildfire 0 for exactness) whose
  block factors are swapped at every iteration.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from .config import ranged
from .errors import OptimizationError
from .factors.schur import POSE_DIM, VisualBlock, torch_threads
from .lie import Sim3

logger = logging.getLogger(__name__)


def pose_key(kf_id: int) -> int:
    """gtsam key of keyframe ``kf_id``'s pose (``gtsam.symbol('x', kf_id)``)."""
    import gtsam

    return gtsam.symbol("x", kf_id)


@dataclass
class GaugeConfig:
    """Gauge freedom handling (docs/design.md section 4)."""

    # A gauge factor only picks one point on a family of equal-cost solutions, so the optimum meets
    # it exactly whatever its sigma; moderate sigmas keep the system well conditioned and avoid the
    # stiffness of near-hard nonlinear penalties (the range) in LM. This holds while every other
    # factor is invariant along the gauge: with Sim(3) loop constraints that change keyframe scales,
    # turn hold_scale off (pointmap) or fold the correction into the depths and call set_pose().
    fix_anchor: bool = True  # 7-dof prior on the oldest keyframe at its value when it became anchor
    anchor_sigma: float = ranged(1e-3, gt=0)  # sigma of the anchor prior (tangent units)
    hold_scale: bool = True  # log-scale prior on every keyframe (dense/patch inverse-depth frontends)
    scale_sigma: float = ranged(1e-3, gt=0)  # sigma of the log-scale priors
    world_scale_range: bool = True  # fix the distance between the first two keyframes (monocular)
    range_sigma: float = ranged(1e-3, gt=0)  # sigma of that range constraint, relative to the initial distance


@dataclass
class MapConfig:
    """Solver choice and tolerances of :class:`SlamMap`."""

    solver: Literal["python_lm", "gtsam_lm", "isam2"] = "python_lm"  # see module docstring
    max_iterations: int = ranged(30, ge=1)  # LM iterations (python_lm) or outer relinearisations (gtsam_lm, isam2)
    relative_tolerance: float = ranged(1e-10, ge=0)  # stop when the relative cost decrease falls below this
    absolute_tolerance: float = ranged(1e-14, ge=0)  # stop when the cost falls below this
    step_tolerance: float = ranged(1e-12, ge=0)  # stop when the largest tangent step component falls below this
    lambda_initial: float = ranged(1e-6, gt=0)  # initial LM damping (identity, on the pose tangents)
    lambda_factor: float = ranged(10.0, gt=1)  # LM damping multiplier on rejection / divisor on acceptance
    lambda_min: float = ranged(1e-12, gt=0)  # smallest LM damping
    lambda_max: float = ranged(1e8, gt=0)  # python_lm gives up (converged) when rejected steps push lambda above this
    refine_steps: int = ranged(2, ge=0)  # structure Gauss-Newton steps at fixed poses before and after optimize()
    refine_each_iteration: bool = False  # also refine after every accepted step (else: joint updates only)
    inner_max_iterations: int = ranged(100, ge=1)  # gtsam LM iterations per outer relinearisation (gtsam_lm)
    max_backtracks: int = ranged(6, ge=0)  # step halvings when an outer gtsam_lm/isam2 step raises the true cost
    threads: int = ranged(1, ge=0)  # torch threads during optimisation (small dense solves: 1 is fastest)
    gauge: GaugeConfig = field(default_factory=GaugeConfig)


@dataclass
class OptimizeReport:
    """What :meth:`SlamMap.optimize` did."""

    solver: str
    initial_cost: float
    final_cost: float
    iterations: int
    converged: bool
    seconds: float


def _range_factor(key_a: int, key_b: int, distance: float, sigma: float):
    """Factor on ``| c_b - c_a | = distance`` for camera centres ``c = s * translation()`` of two
    Similarity3 (the world-frame origin of each camera). One Python factor per map: cheap."""
    import gtsam

    def error(this, values, jacobians):
        T_a = values.atSimilarity3(key_a)
        T_b = values.atSimilarity3(key_b)
        c_a = T_a.scale() * np.asarray(T_a.translation())
        c_b = T_b.scale() * np.asarray(T_b.translation())
        diff = c_b - c_a
        dist = float(np.linalg.norm(diff))
        if jacobians is not None:
            unit = diff / max(dist, np.finfo(float).tiny)
            # d c / d xi = s R [0, I, 0] (right perturbation: only the u block moves the centre)
            J_a = np.zeros((1, POSE_DIM))
            J_b = np.zeros((1, POSE_DIM))
            J_a[0, 3:6] = -unit @ (T_a.scale() * T_a.rotation().matrix())
            J_b[0, 3:6] = unit @ (T_b.scale() * T_b.rotation().matrix())
            jacobians[0] = J_a
            jacobians[1] = J_b
        return np.array([dist - distance])

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, sigma), [key_a, key_b], error)


class SlamMap:
    """Keyframe poses, factors, visual blocks and the solvers (see module docstring).

    Typical use by a frontend::

        smap = SlamMap(MapConfig())
        smap.add_keyframe(0, T_WC0); smap.add_keyframe(1, T_WC1)
        h = smap.add_block(InverseDepthBlock(...keys=(pose_key(0), pose_key(1)), ...))
        smap.add_factor(gtsam.BetweenFactorSimilarity3(...))
        report = smap.optimize()
        T_WC = smap.pose(1)                      # gtsam.Similarity3
    """

    def __init__(self, config: MapConfig | None = None):
        import gtsam

        self.config = config or MapConfig()
        self._values = gtsam.Values()
        self._keyframes: list[int] = []  # insertion order: the anchor is the first
        self._held_scale: dict[int, float] = {}
        self._factors: dict[int, object] = {}
        self._factor_keys: dict[int, tuple[int, ...]] = {}
        self._blocks: dict[int, VisualBlock] = {}
        self._gauge_handles: dict[str, int] = {}  # "anchor", "range", "scale:<kf>" -> factor handle
        self._next_handle = 0
        self._isam = None  # persistent gtsam.ISAM2 of the isam2 solver (None: rebuilt when next needed)
        self._isam_slots: dict[int, int] = {}  # factor handle -> iSAM2 factor index
        self._isam_block_slots: list[int] = []  # iSAM2 indices of the current block containers
        self._isam_pending_removals: list[int] = []  # iSAM2 indices of factors removed since the last update
        self._isam_keys: set[int] = set()  # variables already in iSAM2
        self._max_iterations = self.config.max_iterations  # iteration cap of the running optimize()

    # ------------------------------------------------------------------ keyframes
    @property
    def keyframe_ids(self) -> list[int]:
        return list(self._keyframes)

    def has_keyframe(self, kf_id: int) -> bool:
        return self._values.exists(pose_key(kf_id))

    def add_keyframe(self, kf_id: int, T_WC) -> int:
        """Add keyframe ``kf_id`` with initial pose ``T_WC`` (gtsam.Similarity3 or an unbatched
        fgslam.lie.Sim3); returns its gtsam key. Adds the gauge factors it needs."""
        key = pose_key(kf_id)
        if self._values.exists(key):
            raise OptimizationError(f"keyframe {kf_id} is already in the map")
        pose = T_WC.to_gtsam() if isinstance(T_WC, Sim3) else T_WC
        self._values.insert(key, pose)
        self._keyframes.append(kf_id)
        self._held_scale[kf_id] = float(pose.scale())
        self._update_gauge()
        return key

    def remove_keyframe(self, kf_id: int) -> None:
        """Remove keyframe ``kf_id`` and every factor and block that involves it (no marginalisation)."""
        key = pose_key(kf_id)
        if not self._values.exists(key):
            raise OptimizationError(f"keyframe {kf_id} is not in the map")
        for handle in [h for h, ks in self._factor_keys.items() if key in ks]:
            self._drop_factor(handle)
        self._gauge_handles = {n: h for n, h in self._gauge_handles.items() if h in self._factors}
        for handle in [h for h, b in self._blocks.items() if key in b.keys]:
            del self._blocks[handle]
        self._values.erase(key)
        self._keyframes.remove(kf_id)
        del self._held_scale[kf_id]
        self._isam = None  # iSAM2 cannot drop variables: rebuilt at the next optimisation
        self._update_gauge()

    def pose(self, kf_id: int):
        """Current T_WC of keyframe ``kf_id`` (gtsam.Similarity3)."""
        return self._values.atSimilarity3(pose_key(kf_id))

    def poses(self, kf_ids: list[int] | None = None) -> Sim3:
        """Current T_WC of ``kf_ids`` (default all, in insertion order) as a batched fgslam Sim3."""
        ids = self._keyframes if kf_ids is None else kf_ids
        return Sim3.from_gtsam([self.pose(k) for k in ids])

    def set_pose(self, kf_id: int, T_WC, hold_scale: bool = True) -> None:
        """Overwrite a pose (e.g. after a pose-graph correction). With ``hold_scale`` the keyframe's
        scale prior moves to the new scale (the caller folds the scale change into its depths)."""
        pose = T_WC.to_gtsam() if isinstance(T_WC, Sim3) else T_WC
        self._values.update(pose_key(kf_id), pose)
        if hold_scale and self._held_scale.get(kf_id) != float(pose.scale()):
            self._held_scale[kf_id] = float(pose.scale())
            self._rebuild_scale_prior(kf_id)
        self._isam = None  # iSAM2's linearisation point is stale: rebuilt at the next optimisation

    @property
    def values(self):
        """A copy of the current gtsam.Values."""
        import gtsam

        return gtsam.Values(self._values)

    # ------------------------------------------------------------------ factors and blocks
    def add_factor(self, factor) -> int:
        """Add a built-in (C++) gtsam nonlinear factor on existing keys; returns its handle."""
        keys = tuple(int(k) for k in factor.keys())
        for key in keys:
            if not self._values.exists(key):
                raise OptimizationError(f"factor on unknown key {key}: add the keyframe first")
        handle = self._next_handle
        self._next_handle += 1
        self._factors[handle] = factor
        self._factor_keys[handle] = keys
        return handle

    def remove_factor(self, handle: int) -> None:
        if handle not in self._factors:
            raise OptimizationError(f"no factor with handle {handle}")
        self._drop_factor(handle)

    def add_block(self, block: VisualBlock) -> int:
        """Add a visual block (its keys must exist); returns its handle."""
        for key in block.keys:
            if not self._values.exists(key):
                raise OptimizationError(f"visual block on unknown key {key}: add the keyframe first")
        handle = self._next_handle
        self._next_handle += 1
        self._blocks[handle] = block
        return handle

    def remove_block(self, handle: int) -> None:
        if handle not in self._blocks:
            raise OptimizationError(f"no visual block with handle {handle}")
        del self._blocks[handle]

    @property
    def blocks(self) -> dict[int, VisualBlock]:
        return dict(self._blocks)

    def _drop_factor(self, handle: int) -> None:
        del self._factors[handle]
        del self._factor_keys[handle]
        if self._isam is not None and handle in self._isam_slots:
            self._isam_pending_removals.append(self._isam_slots.pop(handle))

    # ------------------------------------------------------------------ gauge
    def _add_gauge_factor(self, name: str, factor) -> None:
        old = self._gauge_handles.pop(name, None)
        if old is not None and old in self._factors:
            self._drop_factor(old)
        self._gauge_handles[name] = self.add_factor(factor)

    def _rebuild_scale_prior(self, kf_id: int) -> None:
        import gtsam

        gauge = self.config.gauge
        if not gauge.hold_scale:
            return
        precisions = np.zeros(POSE_DIM)
        precisions[6] = 1.0 / gauge.scale_sigma**2
        prior = gtsam.Similarity3(gtsam.Rot3(), np.zeros(3), self._held_scale[kf_id])
        # The prior's rotation/translation rows have zero precision, so it constrains only
        # lambda = log(s / s_held) of Logmap(prior^-1 T) (scale composes independently).
        self._add_gauge_factor(
            f"scale:{kf_id}",
            gtsam.PriorFactorSimilarity3(pose_key(kf_id), prior, gtsam.noiseModel.Diagonal.Precisions(precisions)),
        )

    def _update_gauge(self) -> None:
        """(Re)create the anchor prior, the range constraint and missing scale priors."""
        import gtsam

        gauge = self.config.gauge
        kfs = self._keyframes
        if not kfs:
            return
        anchor = kfs[0]
        if gauge.fix_anchor and "anchor" not in self._gauge_handles:
            noise = gtsam.noiseModel.Isotropic.Sigma(POSE_DIM, gauge.anchor_sigma)
            self._add_gauge_factor("anchor", gtsam.PriorFactorSimilarity3(pose_key(anchor), self.pose(anchor), noise))
        for kf in kfs:
            if gauge.hold_scale and f"scale:{kf}" not in self._gauge_handles:
                self._rebuild_scale_prior(kf)
        if gauge.world_scale_range and len(kfs) >= 2 and "range" not in self._gauge_handles:
            T_a, T_b = self.pose(kfs[0]), self.pose(kfs[1])
            c_a = T_a.scale() * np.asarray(T_a.translation())
            c_b = T_b.scale() * np.asarray(T_b.translation())
            distance = float(np.linalg.norm(c_b - c_a))
            if distance <= 0.0:
                raise OptimizationError(
                    f"world-scale range gauge: keyframes {kfs[0]} and {kfs[1]} have the same centre"
                )
            self._add_gauge_factor(
                "range", _range_factor(pose_key(kfs[0]), pose_key(kfs[1]), distance, gauge.range_sigma * distance)
            )

    # ------------------------------------------------------------------ evaluation
    def nonlinear_graph(self):
        """All built-in and gauge factors as a gtsam.NonlinearFactorGraph (blocks excluded)."""
        import gtsam

        graph = gtsam.NonlinearFactorGraph()
        for factor in self._factors.values():
            graph.add(factor)
        return graph

    def cost(self, values=None) -> float:
        """GTSAM-convention total cost at ``values`` (default current) with the blocks' current structure."""
        values = self._values if values is None else values
        return self.nonlinear_graph().error(values) + sum(b.cost(values) for b in self._blocks.values())

    def _block_pieces(self, values, gfg) -> None:
        """Linearise every block at ``values`` and add their summed (H, g, c) to ``gfg`` as pieces."""
        diag: dict[int, np.ndarray] = {}
        grad: dict[int, np.ndarray] = {}
        off: dict[tuple[int, int], np.ndarray] = {}
        constant = 0.0
        d = POSE_DIM
        for block in self._blocks.values():
            keys, H, g, c = block.linearize(values)[0]
            constant += c
            for a, ka in enumerate(keys):
                sa = slice(d * a, d * a + d)
                diag[ka] = diag.get(ka, 0.0) + H[sa, sa]
                grad[ka] = grad.get(ka, 0.0) + g[sa]
                for b, kb in enumerate(keys):
                    if kb <= ka:
                        continue
                    off[(ka, kb)] = off.get((ka, kb), 0.0) + H[sa, slice(d * b, d * b + d)]
        import gtsam

        first = True
        for key, block in diag.items():
            gfg.add(gtsam.HessianFactor(key, block, -grad[key], constant if first else 0.0))
            first = False
        zero_block, zero_vec = np.zeros((d, d)), np.zeros(d)
        for (ka, kb), block in off.items():
            gfg.add(gtsam.HessianFactor(ka, kb, zero_block, block, zero_vec, zero_block, zero_vec, 0.0))

    def linearize(self, values=None):
        """gtsam.GaussianFactorGraph of the whole problem at ``values`` (default current): built-in and
        gauge factors linearised by gtsam plus the blocks' Schur-reduced systems."""
        values = self._values if values is None else values
        gfg = self.nonlinear_graph().linearize(values)
        self._block_pieces(values, gfg)
        return gfg

    def marginal_covariances(self, kf_ids: list[int] | None = None) -> dict[int, np.ndarray]:
        """Marginal covariances (7, 7) of keyframe poses in the tangent ``[w, u, lambda]`` at the
        current estimate (Laplace approximation of the linearised problem, blocks included)."""
        import gtsam

        with torch_threads(self.config.threads):
            marginals = gtsam.Marginals(self.linearize(), self._values)
        ids = self._keyframes if kf_ids is None else kf_ids
        return {kf: np.asarray(marginals.marginalCovariance(pose_key(kf))) for kf in ids}

    # ------------------------------------------------------------------ solvers
    def optimize(self, max_iterations: int | None = None) -> OptimizeReport:
        """Run the configured solver from the current estimate; updates poses and block structure.

        ``max_iterations`` overrides ``config.max_iterations`` for this call (e.g. the few
        iterations a frontend runs per update).
        """
        start = time.perf_counter()
        solver = self.config.solver
        self._max_iterations = self.config.max_iterations if max_iterations is None else max_iterations
        with torch_threads(self.config.threads):
            initial = self._refine_all()
            if solver == "python_lm":
                iterations, converged, final = self._python_lm(initial)
            elif solver == "gtsam_lm":
                iterations, converged, final = self._outer_loop(self._gtsam_lm_step, initial)
            elif solver == "isam2":
                iterations, converged, final = self._outer_loop(self._isam2_step, initial)
            else:
                raise OptimizationError(f"unknown solver {solver!r} (map.solver)")
            if self.config.refine_steps > 0:
                final = self._refine_all()
        report = OptimizeReport(solver, initial, final, iterations, converged, time.perf_counter() - start)
        logger.debug("optimize: %s", report)
        return report

    def _refine_all(self) -> float:
        """Refine every block's structure at the current poses (``refine_steps``); total cost."""
        steps = self.config.refine_steps
        graph_cost = self.nonlinear_graph().error(self._values)
        if steps <= 0:
            return graph_cost + sum(b.cost(self._values) for b in self._blocks.values())
        return graph_cost + sum(b.refine_structure(self._values, steps) for b in self._blocks.values())

    def _converged(self, old_cost: float, new_cost: float, max_step: float) -> bool:
        cfg = self.config
        return (
            new_cost <= cfg.absolute_tolerance
            or abs(old_cost - new_cost) <= cfg.relative_tolerance * max(old_cost, np.finfo(float).tiny)
            or max_step <= cfg.step_tolerance
        )

    @staticmethod
    def _max_abs(delta) -> float:
        vec = np.asarray(delta.vector())
        return float(np.abs(vec).max()) if vec.size else 0.0

    @staticmethod
    def _damping(values, lam: float):
        """Levenberg-Marquardt damping ``lam |dx|^2`` on every variable of ``values`` (identity)."""
        import gtsam

        gfg = gtsam.GaussianFactorGraph()
        zero = values.zeroVectors()
        for key in values.keys():
            dim = int(np.asarray(zero.at(key)).size)
            gfg.add(gtsam.JacobianFactor(key, np.sqrt(lam) * np.eye(dim), np.zeros(dim), gtsam.noiseModel.Unit.Create(dim)))
        return gfg

    def _python_lm(self, cost: float) -> tuple[int, bool, float]:
        cfg = self.config
        graph = self.nonlinear_graph()
        blocks = list(self._blocks.values())
        values = self._values
        lam = cfg.lambda_initial
        for it in range(1, self._max_iterations + 1):
            gfg = graph.linearize(values)
            self._block_pieces(values, gfg)
            accepted = False
            while not accepted:
                damped = gfg.clone()
                damped.push_back(self._damping(values, lam))
                delta = damped.optimize()
                trial_values = values.retract(delta)
                trial_structure = [b.clamp_structure(b.structure + b.back_substitute(delta)) for b in blocks]
                trial_cost = graph.error(trial_values) + sum(
                    b.cost(trial_values, s) for b, s in zip(blocks, trial_structure)
                )
                if np.isfinite(trial_cost) and trial_cost <= cost:
                    accepted = True
                    lam = max(lam / cfg.lambda_factor, cfg.lambda_min)
                else:
                    lam *= cfg.lambda_factor
                    if lam > cfg.lambda_max:
                        self._values = values
                        return it, True, cost  # no descent possible at this damping: at a minimum
            values = trial_values
            new_cost = self._commit_structure(blocks, trial_structure, values, trial_cost, graph)
            done = self._converged(cost, new_cost, self._max_abs(delta))
            cost = new_cost
            self._values = values
            if done:
                return it, True, cost
        return self._max_iterations, False, cost

    def _block_containers(self, values):
        """One LinearContainerFactor per block, linearised at ``values``."""
        import gtsam

        from .factors.schur import to_gaussian_factor

        out = gtsam.NonlinearFactorGraph()
        for block in self._blocks.values():
            keys, H, g, c = block.linearize(values)[0]
            lin_point = gtsam.Values()
            for key in keys:
                lin_point.insert(key, values.atSimilarity3(key))
            out.add(gtsam.LinearContainerFactor(to_gaussian_factor(keys, H, g, c), lin_point))
        return out

    def _commit_structure(self, blocks, structures, values, cost: float, graph) -> float:
        """Adopt accepted trial structures (optionally refined); returns the total cost."""
        for b, s in zip(blocks, structures):
            b.set_structure(s)
        if not (self.config.refine_each_iteration and self.config.refine_steps > 0):
            return cost
        return graph.error(values) + sum(b.refine_structure(values, self.config.refine_steps) for b in blocks)

    def _outer_loop(self, step, cost: float) -> tuple[int, bool, float]:
        """Relinearise blocks, let ``step`` move the variables, back-substitute, repeat.

        A step that raises the true cost is halved (in the tangent) up to ``max_backtracks`` times.
        """
        import gtsam

        cfg = self.config
        graph = self.nonlinear_graph()
        blocks = list(self._blocks.values())
        values = self._values
        for it in range(1, self._max_iterations + 1):
            containers = self._block_containers(values)
            new_values = step(graph, containers, values)
            delta = values.localCoordinates(new_values)
            for _ in range(cfg.max_backtracks + 1):
                trial_values = values.retract(delta)
                trial_structure = [b.clamp_structure(b.structure + b.back_substitute(delta)) for b in blocks]
                trial_cost = graph.error(trial_values) + sum(
                    b.cost(trial_values, s) for b, s in zip(blocks, trial_structure)
                )
                if np.isfinite(trial_cost) and trial_cost <= cost:
                    break
                delta = delta.scale(0.5)
            else:
                return it, True, cost  # no decrease along the step: at a minimum within tolerance
            values = trial_values
            new_cost = self._commit_structure(blocks, trial_structure, values, trial_cost, graph)
            done = self._converged(cost, new_cost, self._max_abs(delta))
            cost = new_cost
            self._values = values
            if done:
                return it, True, cost
        return self._max_iterations, False, cost

    def _gtsam_lm_step(self, graph, containers, values):
        import gtsam

        cfg = self.config
        full = gtsam.NonlinearFactorGraph(graph)
        full.push_back(containers)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(cfg.inner_max_iterations)
        params.setRelativeErrorTol(cfg.relative_tolerance)
        params.setAbsoluteErrorTol(cfg.absolute_tolerance)
        params.setlambdaInitial(cfg.lambda_initial)
        params.setlambdaFactor(cfg.lambda_factor)
        return gtsam.LevenbergMarquardtOptimizer(full, values, params).optimize()

    def _isam2_step(self, graph, containers, values):
        """One iSAM2 update that swaps in the new block containers (built-in factors are synced)."""
        import gtsam

        if self._isam is None:
            params = gtsam.ISAM2Params()
            params.setRelinearizeThreshold(0.0)
            params.relinearizeSkip = 1
            gn = gtsam.ISAM2GaussNewtonParams()
            gn.setWildfireThreshold(0.0)
            params.setOptimizationParams(gn)
            self._isam = gtsam.ISAM2(params)
            self._isam_slots, self._isam_block_slots, self._isam_pending_removals = {}, [], []
            self._isam_keys = set()
        new_factors = gtsam.NonlinearFactorGraph()
        new_handles = [h for h in self._factors if h not in self._isam_slots]
        for h in new_handles:
            new_factors.add(self._factors[h])
        new_factors.push_back(containers)
        new_theta = gtsam.Values()
        for kf in self._keyframes:
            key = pose_key(kf)
            if key not in self._isam_keys:
                new_theta.insert(key, values.atSimilarity3(key))
                self._isam_keys.add(key)
        removals = self._isam_pending_removals + self._isam_block_slots
        result = self._isam.update(new_factors, new_theta, removals)
        indices = list(result.getNewFactorsIndices())
        for h, index in zip(new_handles, indices[: len(new_handles)]):
            self._isam_slots[h] = index
        self._isam_block_slots = indices[len(new_handles):]
        self._isam_pending_removals = []
        return self._isam.calculateEstimate()
