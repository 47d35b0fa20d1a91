"""Pose-graph optimisation of g2o graphs (SE(2) and SE(3)) with the backend's one Levenberg-Marquardt
loop (:func:`fgslam.backend.solver.levenberg_marquardt` on gtsam factors, gtsam's LM defaults).

Conventions:

* gtsam keys are the g2o vertex ids; a vertex value is ``T_W_i`` (``gtsam.Pose2`` / ``gtsam.Pose3``) and
  an edge ``(i, j)`` is a ``BetweenFactor`` on ``T_i_j = T_W_i^-1 T_W_j``.
* gtsam tangents: Pose2 ``[x, y, theta]`` (same as g2o), Pose3 ``[w(3), v(3)]`` (rotation first, g2o
  is translation first: the information matrix is permuted accordingly).
* Gauge: a prior (``PGOConfig.prior_variance``) holds the FIX vertices of the file, or the first vertex
  when there are none, at their file pose (identity when the file has no vertex lines), as gtsam's
  own g2o examples do.
* Cost: gtsam's ``graph.error`` = 0.5 * sum of squared Mahalanobis residuals, prior included.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from ..backend.solver import LMSettings, NonlinearProblem, levenberg_marquardt
from ..core.config import MAX_ITERATIONS, MAX_LAMBDA, MAX_SCALAR, check_ranges, ranged
from ..core.errors import ConfigError, DataError, FormatError, OptimizationError
from ..io.g2o import PoseGraph, read_g2o, write_g2o

if TYPE_CHECKING:  # gtsam is imported lazily (heavy import)
    import gtsam

logger = logging.getLogger(__name__)

#: Permutation from g2o's 3-D tangent order [t, r] to gtsam's Pose3 order [r, t] (self-inverse).
_G2O_TO_GTSAM_SE3 = np.array([3, 4, 5, 0, 1, 2])


@dataclass
class PGOConfig:
    """Tunables of :func:`optimize_pose_graph` (defaults are gtsam's LM defaults). The LM loop is the
    backend's (multifrontal Cholesky elimination, identity damping); :func:`lm_params` gives gtsam's
    own LM the same settings (benchmarks, tests)."""

    init: Literal["chordal", "as-is"] = "chordal"  # chordal: InitializePose3 (3-D) / LAGO (2-D); as-is: file poses
    max_iterations: int = ranged(100, ge=0, le=MAX_ITERATIONS)  # LM iteration cap
    relative_error_tol: float = ranged(1e-5, ge=0, le=MAX_SCALAR)  # stop when the relative cost decrease falls below this
    absolute_error_tol: float = ranged(1e-5, ge=0, le=MAX_SCALAR)  # stop when the absolute cost decrease falls below this
    error_tol: float = ranged(0.0, ge=0, le=MAX_SCALAR)  # stop when the cost falls below this
    lambda_initial: float = ranged(1e-5, gt=0, le=MAX_LAMBDA)  # initial LM damping
    lambda_factor: float = ranged(10.0, gt=1, le=MAX_SCALAR)  # damping multiplier on a rejected/accepted step
    lambda_upper_bound: float = ranged(1e5, gt=0, le=MAX_LAMBDA)  # LM gives up when the damping exceeds this
    ordering: Literal["COLAMD", "METIS"] = "COLAMD"  # elimination ordering
    prior_variance: float = ranged(1e-6, gt=0, le=MAX_SCALAR)  # variance of every tangent component of the gauge prior
    # Edges whose information matrix is not positive definite: reject the file, or drop them (counted).
    indefinite_information: Literal["error", "drop"] = "error"

    def validate(self) -> None:
        """Raise ConfigError for values gtsam would misbehave on: a field outside its declared range
        (for configs built in code; ``load_config`` checks the ranges itself)."""
        check_ranges(self)


@dataclass
class PGOResult:
    """Outcome of :func:`optimize_pose_graph`.

    Attributes:
        graph: the input graph with ``poses`` replaced by the optimised ``T_W_i`` (same parameterisation,
            rows in ``graph.ids`` order).
        initial_cost: gtsam cost at the initial estimate (after initialisation).
        final_cost: gtsam cost at the optimum.
        iterations: LM iterations performed (accepted steps).
        converged: a stopping test held (tolerances, or no descent at any damping), not the iteration cap.
        init_time_s: seconds spent building the graph and initialising.
        read_time_s: seconds spent reading the file (0 when the graph did not come from a file).
        optimize_time_s: seconds spent in LM.
        dropped_edges: edges with non-positive-definite information given zero weight (left out).
        cost_history: cost after each LM iteration.
    """

    graph: PoseGraph
    initial_cost: float
    final_cost: float
    iterations: int
    converged: bool
    init_time_s: float
    optimize_time_s: float
    dropped_edges: int = 0
    read_time_s: float = 0.0
    cost_history: list[float] = field(default_factory=list)

    def summary(self) -> dict:
        """JSON-ready summary (no poses)."""
        return {
            "file": self.graph.source,
            "dim": self.graph.dim,
            "vertices": self.graph.num_vertices,
            "edges": self.graph.num_edges,
            "dropped_edges": self.dropped_edges,
            "initial_cost": self.initial_cost,
            "final_cost": self.final_cost,
            "iterations": self.iterations,
            "converged": self.converged,
            "read_time_s": self.read_time_s,
            "init_time_s": self.init_time_s,
            "optimize_time_s": self.optimize_time_s,
            "time_s": self.read_time_s + self.init_time_s + self.optimize_time_s,
        }


def pose_to_gtsam(dim: int, pose: np.ndarray) -> gtsam.Pose2 | gtsam.Pose3:
    """``[x, y, theta]`` -> Pose2, ``[x, y, z, qx, qy, qz, qw]`` -> Pose3."""
    import gtsam  # deferred: gtsam

    if dim == 2:
        return gtsam.Pose2(float(pose[0]), float(pose[1]), float(pose[2]))
    qx, qy, qz, qw = (float(v) for v in pose[3:7])
    return gtsam.Pose3(gtsam.Rot3.Quaternion(qw, qx, qy, qz), np.asarray(pose[:3], dtype=np.float64))


def pose_from_gtsam(dim: int, pose: gtsam.Pose2 | gtsam.Pose3) -> np.ndarray:
    """Inverse of :func:`pose_to_gtsam` (quaternion with qw >= 0)."""
    if dim == 2:
        return np.array([pose.x(), pose.y(), pose.theta()])
    q = pose.rotation().toQuaternion()
    quat = np.array([q.x(), q.y(), q.z(), q.w()])
    if quat[3] < 0:
        quat = -quat
    return np.concatenate([pose.translation(), quat])


def information_to_gtsam(dim: int, information: np.ndarray) -> np.ndarray:
    """g2o-ordered information matrix -> gtsam tangent order (Pose3: [r, t]; Pose2 unchanged)."""
    if dim == 2:
        return information
    return information[np.ix_(_G2O_TO_GTSAM_SE3, _G2O_TO_GTSAM_SE3)]


def gauge_prior_factors(graph: PoseGraph, config: PGOConfig) -> list:
    """Priors fixing the gauge: on the FIX vertices, else on the first vertex (at the file pose or identity)."""
    import gtsam  # deferred: gtsam

    anchors = graph.fixed if graph.fixed else [int(graph.ids[0])]
    row_of = {int(v): k for k, v in enumerate(graph.ids.tolist())}
    n_tan = 3 if graph.dim == 2 else 6
    noise = gtsam.noiseModel.Diagonal.Variances(np.full(n_tan, config.prior_variance))
    prior_cls = gtsam.PriorFactorPose2 if graph.dim == 2 else gtsam.PriorFactorPose3
    factors = []
    for vid in anchors:
        if graph.poses is not None:
            value = pose_to_gtsam(graph.dim, graph.poses[row_of[vid]])
        else:
            value = gtsam.Pose2() if graph.dim == 2 else gtsam.Pose3()
        factors.append(prior_cls(vid, value, noise))
    return factors


def build_factor_graph(graph: PoseGraph, config: PGOConfig) -> tuple[gtsam.NonlinearFactorGraph, int]:
    """Between factors with full information noise models plus the gauge prior.

    Returns the graph and the number of edges left out because of non-positive-definite information.
    """
    import gtsam  # deferred: gtsam

    skip = set(graph.indefinite_edges.tolist())
    if skip and config.indefinite_information == "error":
        first = int(graph.indefinite_edges[0])
        raise FormatError(
            f"{graph.source}:{int(graph.edge_lines[first])}: information matrix is not positive definite "
            f"({len(skip)} such edges; set indefinite_information=drop to leave them out)"
        )
    _check_connected(graph, skip)
    between_cls = gtsam.BetweenFactorPose2 if graph.dim == 2 else gtsam.BetweenFactorPose3
    fg = gtsam.NonlinearFactorGraph()
    for k, ((i, j), meas, info) in enumerate(zip(graph.edges.tolist(), graph.measurements, graph.information)):
        if k in skip:
            continue
        noise = gtsam.noiseModel.Gaussian.Information(information_to_gtsam(graph.dim, info))
        fg.add(between_cls(i, j, pose_to_gtsam(graph.dim, meas), noise))
    for factor in gauge_prior_factors(graph, config):
        fg.add(factor)
    if skip:
        logger.warning("%s: left out %d edges with non-positive-definite information", graph.source, len(skip))
    return fg, len(skip)


def _check_connected(graph: PoseGraph, skip: set[int]) -> None:
    """OptimizationError when the edges (minus ``skip``) leave the graph in several pieces (no gauge)."""
    parent = {int(v): int(v) for v in graph.ids.tolist()}

    def root(v: int) -> int:
        while parent[v] != v:
            parent[v] = parent[parent[v]]  # path halving
            v = parent[v]
        return v

    for k, (i, j) in enumerate(graph.edges.tolist()):
        if k not in skip:
            parent[root(i)] = root(j)
    roots = {v: root(v) for v in parent}
    n_components = len(set(roots.values()))
    if n_components > 1:
        anchor = int(graph.ids[0])
        stray = next(v for v, r in roots.items() if r != roots[anchor])
        raise OptimizationError(
            f"{graph.source}: the pose graph has {n_components} disconnected parts "
            f"(vertex {stray} is not connected to vertex {anchor}); a single gauge prior cannot fix them"
        )


def initial_estimate(graph: PoseGraph, factors: gtsam.NonlinearFactorGraph, init: str) -> gtsam.Values:
    """Initial ``T_W_i``: the file poses (``as-is``) or chordal relaxation (InitializePose3 / LAGO)."""
    import gtsam  # deferred: gtsam

    if init == "as-is":
        if graph.poses is None:
            raise DataError(
                f"{graph.source}: the file has no VERTEX lines, so init 'as-is' is impossible (use chordal)"
            )
        values = gtsam.Values()
        for vid, pose in zip(graph.ids.tolist(), graph.poses):
            values.insert(vid, pose_to_gtsam(graph.dim, pose))
        return values
    if init == "chordal":
        if graph.dim == 2:
            return gtsam.lago.initialize(diagonalised_pose2_graph(factors), _has_odometric_path(graph))
        return gtsam.InitializePose3.initialize(factors)
    raise ConfigError(f"unknown init '{init}' (valid: chordal, as-is)")


def _has_odometric_path(graph: PoseGraph) -> bool:
    """Whether an edge joins every pair of consecutive ids (LAGO's fast odometric spanning tree)."""
    pairs = {(min(i, j), max(i, j)) for i, j in graph.edges.tolist()}
    ids = np.sort(graph.ids)
    return all((int(a), int(b)) in pairs for a, b in zip(ids[:-1], ids[1:]))


def diagonalised_pose2_graph(factors: gtsam.NonlinearFactorGraph) -> gtsam.NonlinearFactorGraph:
    """Copy of a Pose2 graph whose full Gaussian noise models are replaced by their marginal variances.

    gtsam's LAGO only accepts diagonal noise models (it reads the theta sigma); the marginal variances
    (diagonal of the covariance) keep each edge's rotation uncertainty exact. Used for initialisation only.
    """
    import gtsam  # deferred: gtsam

    diagonal = gtsam.NonlinearFactorGraph()
    for k in range(factors.size()):
        factor = factors.at(k)
        if isinstance(factor, gtsam.BetweenFactorPose2):
            variances = np.diag(np.linalg.inv(factor.noiseModel().information()))
            factor = gtsam.BetweenFactorPose2(
                factor.keys()[0], factor.keys()[1], factor.measured(), gtsam.noiseModel.Diagonal.Variances(variances)
            )
        diagonal.add(factor)
    return diagonal


def lm_params(config: PGOConfig) -> gtsam.LevenbergMarquardtParams:
    """gtsam's own LM parameters with the settings of :func:`lm_settings` (side-by-side benchmarks)."""
    import gtsam  # deferred: gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(config.relative_error_tol)
    params.setAbsoluteErrorTol(config.absolute_error_tol)
    params.setErrorTol(config.error_tol)
    params.setlambdaInitial(config.lambda_initial)
    params.setlambdaFactor(config.lambda_factor)
    params.setlambdaUpperBound(config.lambda_upper_bound)
    params.setOrderingType(config.ordering)
    return params


def lm_settings(config: PGOConfig):
    """The backend LM loop's settings from the config."""
    return LMSettings(
        max_iterations=config.max_iterations, lambda_initial=config.lambda_initial,
        lambda_factor=config.lambda_factor, lambda_max=config.lambda_upper_bound,
        relative_tolerance=config.relative_error_tol, absolute_tolerance=config.error_tol,
        absolute_decrease_tolerance=config.absolute_error_tol, ordering=config.ordering.lower(),
    )


class _RecordingProblem(NonlinearProblem):
    """A :class:`~fgslam.backend.solver.NonlinearProblem` that records the cost after each accepted step."""

    def __init__(self, graph, values):
        super().__init__(graph, values)
        self.history: list[float] = []

    def accept(self, state, cost: float) -> float:
        self.history.append(float(cost))
        return super().accept(state, cost)


def optimize_pose_graph(graph: PoseGraph, config: PGOConfig | None = None) -> PGOResult:
    """Initialise and optimise ``graph`` with the backend's LM loop; returns costs, timings and optimised poses."""
    config = config or PGOConfig()
    config.validate()
    t0 = time.perf_counter()
    factors, dropped = build_factor_graph(graph, config)
    try:
        initial = initial_estimate(graph, factors, config.init)
    except RuntimeError as exc:  # gtsam raises e.g. IndeterminateLinearSystem for disconnected graphs
        raise OptimizationError(f"{graph.source}: {config.init} initialisation failed: {exc}") from exc
    initial_cost = factors.error(initial)
    if not math.isfinite(initial_cost):
        raise OptimizationError(f"{graph.source}: initial cost is not finite ({initial_cost})")
    t1 = time.perf_counter()

    problem = _RecordingProblem(factors, initial)
    try:
        report = levenberg_marquardt(problem, lm_settings(config))
    except RuntimeError as exc:
        raise OptimizationError(f"{graph.source}: Levenberg-Marquardt failed: {exc}") from exc
    t2 = time.perf_counter()
    values = problem.values
    final_cost = factors.error(values)
    iterations = len(problem.history)
    # no iteration at all (max_iterations 0): converged only when the start is already below error_tol
    converged = report.converged or (report.iterations == 0 and initial_cost <= config.error_tol)
    converged = converged and math.isfinite(final_cost)

    poses = np.stack([pose_from_gtsam(graph.dim, _at(values, graph.dim, vid)) for vid in graph.ids.tolist()])
    logger.info(
        "%s: cost %.6g -> %.6g in %d iterations (%.3f s)", graph.source, initial_cost, final_cost, iterations, t2 - t1
    )
    return PGOResult(
        graph=replace(graph, poses=poses),
        initial_cost=float(initial_cost),
        final_cost=float(final_cost),
        iterations=int(iterations),
        converged=converged,
        init_time_s=t1 - t0,
        optimize_time_s=t2 - t1,
        dropped_edges=dropped,
        cost_history=list(problem.history),
    )


def _at(values: gtsam.Values, dim: int, key: int) -> gtsam.Pose2 | gtsam.Pose3:
    return values.atPose2(key) if dim == 2 else values.atPose3(key)


def run_pgo(path: str | Path, config: PGOConfig | None = None, out: str | Path | None = None) -> PGOResult:
    """Read a g2o file, optimise it and (optionally) write the optimised graph to ``out``."""
    config = config or PGOConfig()
    t0 = time.perf_counter()
    graph = read_g2o(path, require_positive_definite=False)
    read_time = time.perf_counter() - t0
    result = replace(optimize_pose_graph(graph, config), read_time_s=read_time)
    if out is not None:
        write_g2o(out, result.graph)
    return result
