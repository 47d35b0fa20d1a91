"""The one Levenberg-Marquardt loop of fgslam (docs/architecture.md section 6).

Every iterative least-squares solve in the project goes through :func:`levenberg_marquardt`: the
backend's windowed and global optimisation (visual blocks Schur-reduced to pose systems), the
patch frontend's global bundle adjustment (one compressed factor per source keyframe), the Sim(3)
pose graph of loop closure and ``fgslam pgo``. What differs between them lives in the
:class:`LMProblem` they hand in: how the problem is linearised at its current state (a
``gtsam.GaussianFactorGraph`` over its variable keys, structure already eliminated), how a trial
state follows from a step (retraction, back-substituted structure) and what it costs.

One iteration: linearise; solve the damped system with GTSAM's elimination (``ordering``:
COLAMD or METIS, computed once per problem and reused: the keys of a problem do not change);
try the step; accept it when the true cost does not rise, else raise the damping and re-solve
the same linearisation. Damping (``damping``):

- ``identity``: ``lambda |dx|^2`` on every variable (GTSAM's default LM, ``diagonalDamping`` off);
- ``marquardt``: Marquardt's scaled damping ``lambda diag(H)`` with a floor for zero entries
  (:func:`damping_diagonal`).

Both damp the variables of the linearisation, the poses. A problem whose structure was eliminated
can damp that too (``damps_structure``, the backend's ``map.damp_structure``): each damped solve
then re-eliminates the structure with ``lambda`` added to its information, so a rejected step shrinks
the back-substituted structure step as well, not the pose step alone.

With a ``propose`` step provider (iSAM2) the step comes from the provider once per iteration and a
step that raises the cost is halved up to ``max_backtracks`` times instead.

Stopping: the cost falls below ``absolute_tolerance``, the decrease below
``absolute_decrease_tolerance`` or, relative to the cost, below ``relative_tolerance``, the largest
step component below ``step_tolerance``, the damping above ``lambda_max`` without an accepted step
(a minimum within tolerance), a rejected step whose cost change is below the decrease tolerances
(as gtsam's LM: raising the damping cannot find a decrease that counts; on the KITTI 00 pose graph
this saved 4 of 10 damped solves), or ``max_iterations``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Literal, Protocol

import numpy as np


@dataclass(frozen=True)
class LMSettings:
    """Settings of one :func:`levenberg_marquardt` call (built by each caller from its typed config)."""

    max_iterations: int
    lambda_initial: float
    lambda_factor: float
    lambda_max: float
    lambda_min: float = 1e-12
    relative_tolerance: float = 0.0
    absolute_tolerance: float = 0.0
    absolute_decrease_tolerance: float = 0.0  # stop when the cost decrease falls below this (GTSAM's absoluteErrorTol)
    step_tolerance: float = 0.0
    damping: Literal["identity", "marquardt"] = "identity"
    ordering: Literal["colamd", "metis"] = "colamd"
    max_backtracks: int = 6  # step halvings of a proposed (iSAM2) step that raises the cost


class LMProblem(Protocol):
    """What :func:`levenberg_marquardt` needs from a problem."""

    def cost(self) -> float:
        """True cost (GTSAM convention, ``0.5 sum |r|^2_Sigma``) at the current state."""

    def linearize(self):
        """``gtsam.GaussianFactorGraph`` of the problem at the current state, over its variable keys."""

    def trial(self, delta) -> tuple[float, object]:
        """``(cost, state)`` of the state the step ``delta`` (``gtsam.VectorValues``) leads to; the cost
        is ``inf`` when the state is invalid."""

    def accept(self, state, cost: float) -> float:
        """Adopt a trial state (its cost given); returns the current cost afterwards (a problem may
        refine its structure on acceptance)."""

    # Marquardt damping only: ``hessian_diagonal() -> dict[key, np.ndarray]``, the diagonal of H at
    # the last linearisation (GTSAM's Python wrapper does not expose the graph's own).
    # Structure damping: with ``damps_structure`` true, ``structure_damped(lam)`` gives the last
    # linearisation with ``lam`` added to the eliminated structure's information (the damping of the
    # whole joint system, not only of the poses), and ``trial`` back-substitutes through it.


@dataclass
class LMReport:
    """What :func:`levenberg_marquardt` did."""

    initial_cost: float
    final_cost: float
    iterations: int  # linearisations
    solves: int  # damped solves (accepted and rejected steps)
    converged: bool
    final_lambda: float
    timings: dict = field(default_factory=lambda: {"linearize": 0.0, "solve": 0.0, "evaluate": 0.0})


def damping_diagonal(diag: np.ndarray, lam: float) -> np.ndarray:
    """Marquardt's scaled damping added to the diagonal of H: ``lam * scale + (scale - diag)^+`` with
    ``scale = max(diag, eps * max(max diag, 1))`` (a zero diagonal entry gets a tiny floor)."""
    scale = np.maximum(diag, np.finfo(float).eps * max(float(diag.max(initial=0.0)), 1.0))
    return lam * scale + (scale - diag).clip(min=0.0)


class _Damper:
    """Unary damping factors ``gtsam.HessianFactor(key, diag(damping), 0, 0)`` for the variables of
    one problem. Their keys and dimensions are taken once, at the first linearisation (a problem's
    keys do not change between linearisations); each damped solve then costs one constructor call
    per key, with the diagonal blocks of all keys of one dimension built as one array."""

    def __init__(self, mode: str, problem):
        if mode == "marquardt" and not hasattr(problem, "hessian_diagonal"):
            raise TypeError("Marquardt damping needs the problem's hessian_diagonal()")
        self.mode = mode
        self.problem = problem
        self.keys: list[int] | None = None
        self.flat = np.zeros(0)  # Marquardt: diag(H) of the last linearisation, keys in self.keys order

    def _layout(self, keys: list[int], dims: list[int]) -> None:
        self.keys = keys
        dims_arr = np.asarray(dims, dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(dims_arr)])[:-1]
        self.by_dim = {int(d): np.flatnonzero(dims_arr == d) for d in np.unique(dims_arr)}

    def linearized(self, gfg) -> None:
        """Take what the damping of a new linearisation ``gfg`` needs (the layout at the first)."""
        if self.mode == "marquardt":
            diag = self.problem.hessian_diagonal()
            if self.keys is None:
                keys = list(diag)
                self._layout(keys, [int(np.size(diag[k])) for k in keys])
            self.flat = (np.concatenate([np.asarray(diag[k], dtype=np.float64).ravel() for k in self.keys])
                         if self.keys else np.zeros(0))
        elif self.keys is None:
            zero = gfg.gradientAtZero()  # dimensions of the linearisation's variables
            keys = [int(k) for k in gfg.keyVector()]
            self._layout(keys, [int(zero.dim(k)) for k in keys])

    def damped(self, gfg, lam: float):
        import gtsam  # deferred: gtsam

        out = gtsam.GaussianFactorGraph()
        out.push_back(gfg)  # shares the linearised factors
        push, hessian, keys = out.push_back, gtsam.HessianFactor, self.keys
        if self.mode == "identity":
            for d, idx in self.by_dim.items():
                G, zero = lam * np.eye(d), np.zeros(d)  # copied by each factor
                for i in idx.tolist():
                    push(hessian(keys[i], G, zero, 0.0))
            return out
        flat = damping_diagonal(self.flat, lam)
        for d, idx in self.by_dim.items():
            blocks = np.zeros((idx.size, d, d))
            blocks[:, np.arange(d), np.arange(d)] = flat[self.offsets[idx][:, None] + np.arange(d)]
            zero = np.zeros(d)
            for i, G in zip(idx.tolist(), blocks):
                push(hessian(keys[i], G, zero, 0.0))
        return out


def _tiny_change(cost: float, new_cost: float, settings: LMSettings) -> bool:
    """Whether the cost change ``cost -> new_cost`` is below the decrease tolerances (the stopping rule
    of an accepted step; for a rejected one it means no damping will find a decrease that counts, so
    the loop stops as gtsam's LM does, instead of raising the damping up to ``lambda_max``)."""
    change = abs(cost - new_cost)
    return (change <= settings.absolute_decrease_tolerance
            or change <= settings.relative_tolerance * max(cost, np.finfo(float).tiny))


def _max_abs(vec: np.ndarray) -> float:
    return float(np.abs(vec).max()) if vec.size else 0.0


def _solve(graph, settings: LMSettings, ordering_cache: list):
    import gtsam  # deferred: gtsam

    if settings.ordering == "metis":
        if not ordering_cache:
            ordering_cache.append(gtsam.Ordering.MetisGaussianFactorGraph(graph))
    elif not ordering_cache:
        ordering_cache.append(gtsam.Ordering.ColamdGaussianFactorGraph(graph))
    return graph.optimize(ordering_cache[0])


def levenberg_marquardt(problem: LMProblem, settings: LMSettings, propose: Callable | None = None,
                        ordering_cache: list | None = None, initial_cost: float | None = None) -> LMReport:
    """Minimise ``problem`` from its current state (module docstring). ``ordering_cache``: a list that
    holds the elimination ordering across calls on problems with the same keys (filled on first use).
    ``propose``: a step provider ``propose(gfg) -> gtsam.VectorValues`` (iSAM2) instead of the damped
    elimination. ``initial_cost``: the problem's cost at its current state when the caller has just
    evaluated it (saves one evaluation per call: the window BA runs this many times per frame)."""
    ordering_cache = [] if ordering_cache is None else ordering_cache
    cost = float(problem.cost()) if initial_cost is None else float(initial_cost)
    report = LMReport(cost, cost, 0, 0, False, settings.lambda_initial)
    timings = report.timings
    lam = settings.lambda_initial
    damper = _Damper(settings.damping, problem) if propose is None else None
    damps_structure = bool(getattr(problem, "damps_structure", False))
    for it in range(1, settings.max_iterations + 1):
        report.iterations = it
        gfg = None  # the previous linearisation is freed before the next one is built (peak memory)
        t0 = time.perf_counter()
        gfg = problem.linearize()
        timings["linearize"] += time.perf_counter() - t0
        accepted = None
        if propose is not None:
            t0 = time.perf_counter()
            delta = propose(gfg)
            timings["solve"] += time.perf_counter() - t0
            report.solves += 1
            for _ in range(settings.max_backtracks + 1):
                t0 = time.perf_counter()
                trial_cost, state = problem.trial(delta)
                timings["evaluate"] += time.perf_counter() - t0
                if np.isfinite(trial_cost) and trial_cost <= cost:
                    accepted = (np.asarray(delta.vector()), trial_cost, state)
                    break
                delta = delta.scale(0.5)
        else:
            damper.linearized(gfg)
            while lam <= settings.lambda_max:
                report.solves += 1
                t0 = time.perf_counter()
                system = problem.structure_damped(lam) if damps_structure else gfg
                try:
                    delta = _solve(damper.damped(system, lam), settings, ordering_cache)
                except RuntimeError:  # indeterminate system: more damping
                    delta = None
                timings["solve"] += time.perf_counter() - t0
                if delta is not None and np.isfinite(vec := np.asarray(delta.vector())).all():
                    t0 = time.perf_counter()
                    trial_cost, state = problem.trial(delta)
                    timings["evaluate"] += time.perf_counter() - t0
                    if np.isfinite(trial_cost) and trial_cost <= cost:
                        accepted = (vec, trial_cost, state)
                        lam = max(lam / settings.lambda_factor, settings.lambda_min)
                        break
                    if np.isfinite(trial_cost) and _tiny_change(cost, trial_cost, settings):
                        break  # a rejected step that changes the cost by less than the tolerances: converged
                lam *= settings.lambda_factor
        if accepted is None:  # no descent along the step at any damping: a minimum within tolerance
            report.converged = True
            break
        step, trial_cost, state = accepted
        new_cost = float(problem.accept(state, trial_cost))
        done = (new_cost <= settings.absolute_tolerance or _tiny_change(cost, new_cost, settings)
                or _max_abs(step) <= settings.step_tolerance)
        cost = new_cost
        if done:
            report.converged = True
            break
    report.final_cost = cost
    report.final_lambda = lam
    return report


class NonlinearProblem:
    """An :class:`LMProblem` over a ``gtsam.NonlinearFactorGraph`` and ``gtsam.Values`` (pose graphs:
    no structure). ``values`` holds the current state after :func:`levenberg_marquardt`."""

    def __init__(self, graph, values):
        self.graph = graph
        self.values = values

    def cost(self) -> float:
        return float(self.graph.error(self.values))

    def linearize(self):
        return self.graph.linearize(self.values)

    def trial(self, delta) -> tuple[float, object]:
        values = self.values.retract(delta)
        return float(self.graph.error(values)), values

    def accept(self, state, cost: float) -> float:
        self.values = state
        return cost
