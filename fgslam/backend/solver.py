"""The one Levenberg-Marquardt loop of fgslam (docs/design.md section 5).

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

With a ``propose`` step provider (iSAM2) the step comes from the provider once per iteration and a
step that raises the cost is halved up to ``max_backtracks`` times instead.

Stopping: the cost falls below ``absolute_tolerance``, the relative decrease below
``relative_tolerance``, the largest step component below ``step_tolerance``, the damping above
``lambda_max`` without an accepted step (a minimum within tolerance), or ``max_iterations``.
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
    """Damping factors for the variables of one linearisation (their dimensions and diagonal)."""

    def __init__(self, gfg, mode: str, problem):
        if mode == "marquardt":
            if not hasattr(problem, "hessian_diagonal"):
                raise TypeError("Marquardt damping needs the problem's hessian_diagonal()")
            diag = problem.hessian_diagonal()
            self.keys = list(diag)
            self.diags = [np.asarray(diag[k], dtype=np.float64) for k in self.keys]
            self.flat = np.concatenate(self.diags) if self.diags else np.zeros(0)
        else:
            zero = gfg.gradientAtZero()  # dimensions of the linearisation's variables
            self.keys = [int(k) for k in gfg.keyVector()]
            self.diags = [np.zeros(int(zero.dim(k))) for k in self.keys]
        self.mode = mode

    def damped(self, gfg, lam: float):
        import gtsam

        out = gtsam.GaussianFactorGraph()
        out.push_back(gfg)  # shares the linearised factors
        if self.mode == "identity":
            values = [np.full(d.size, lam) for d in self.diags]
        else:
            flat = damping_diagonal(self.flat, lam)
            values = np.split(flat, np.cumsum([d.size for d in self.diags])[:-1]) if self.diags else []
        for key, dvec in zip(self.keys, values):
            out.push_back(gtsam.HessianFactor(key, np.diag(dvec), np.zeros(dvec.size), 0.0))
        return out


def _max_abs(delta) -> float:
    vec = np.asarray(delta.vector())
    return float(np.abs(vec).max()) if vec.size else 0.0


def _solve(graph, settings: LMSettings, ordering_cache: list):
    import gtsam

    if settings.ordering == "metis":
        if not ordering_cache:
            ordering_cache.append(gtsam.Ordering.MetisGaussianFactorGraph(graph))
    elif not ordering_cache:
        ordering_cache.append(gtsam.Ordering.ColamdGaussianFactorGraph(graph))
    return graph.optimize(ordering_cache[0])


def levenberg_marquardt(problem: LMProblem, settings: LMSettings, propose: Callable | None = None,
                        ordering_cache: list | None = None) -> LMReport:
    """Minimise ``problem`` from its current state (module docstring). ``ordering_cache``: a list that
    holds the elimination ordering across calls on problems with the same keys (filled on first use).
    ``propose``: a step provider ``propose(gfg) -> gtsam.VectorValues`` (iSAM2) instead of the damped
    elimination."""
    ordering_cache = [] if ordering_cache is None else ordering_cache
    cost = float(problem.cost())
    report = LMReport(cost, cost, 0, 0, False, settings.lambda_initial)
    timings = report.timings
    lam = settings.lambda_initial
    for it in range(1, settings.max_iterations + 1):
        report.iterations = it
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
                    accepted = (delta, trial_cost, state)
                    break
                delta = delta.scale(0.5)
        else:
            damper = _Damper(gfg, settings.damping, problem)
            while lam <= settings.lambda_max:
                report.solves += 1
                t0 = time.perf_counter()
                try:
                    delta = _solve(damper.damped(gfg, lam), settings, ordering_cache)
                except RuntimeError:  # indeterminate system: more damping
                    delta = None
                timings["solve"] += time.perf_counter() - t0
                if delta is not None and np.isfinite(np.asarray(delta.vector())).all():
                    t0 = time.perf_counter()
                    trial_cost, state = problem.trial(delta)
                    timings["evaluate"] += time.perf_counter() - t0
                    if np.isfinite(trial_cost) and trial_cost <= cost:
                        accepted = (delta, trial_cost, state)
                        lam = max(lam / settings.lambda_factor, settings.lambda_min)
                        break
                lam *= settings.lambda_factor
        if accepted is None:  # no descent along the step at any damping: a minimum within tolerance
            report.converged = True
            break
        delta, trial_cost, state = accepted
        new_cost = float(problem.accept(state, trial_cost))
        done = (new_cost <= settings.absolute_tolerance
                or abs(cost - new_cost) <= settings.relative_tolerance * max(cost, np.finfo(float).tiny)
                or _max_abs(delta) <= settings.step_tolerance)
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
