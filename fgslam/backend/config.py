"""Configuration of the backend (YAML section ``map`` of a run config; ``configs/map.yaml``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from ..core.config import MAX_COUNT, MAX_ITERATIONS, MAX_LAMBDA, MAX_SCALAR, MAX_THREADS, check_ranges, ranged
from ..core.errors import ConfigError

#: Accepted spellings of ``map.solver`` and the solver they name (``python_lm``: the name before the
#: backend, kept as an alias; ``gtsam_lm``, the outer loop around gtsam's own optimizer, is gone: the
#: one LM loop of :mod:`fgslam.backend.solver` reaches the same optimum).
SOLVER_ALIASES: dict[str, str] = {"lm": "lm", "python_lm": "lm", "isam2": "isam2"}


@dataclass
class GaugeConfig:
    """Gauge freedom handling (docs/architecture.md section 4). Which keyframes carry the anchor prior and
    the range is :meth:`fgslam.backend.Backend.set_gauge`'s choice (default: the oldest keyframe and
    the oldest two)."""

    # A gauge factor only picks one point on a family of equal-cost solutions, so the optimum meets
    # it exactly whatever its sigma; moderate sigmas keep the system well conditioned and avoid the
    # stiffness of near-hard nonlinear penalties (the range) in LM. This holds while every other
    # factor is invariant along the gauge: with Sim(3) loop constraints that change keyframe scales,
    # turn hold_scale off (pointmap) or fold the correction into the depths and call set_pose().
    fix_anchor: bool = True  # 7-dof prior on the anchor keyframe at its pose when it became anchor (set_gauge)
    anchor_sigma: float = ranged(1e-3, gt=0, le=MAX_SCALAR)  # sigma of the anchor prior (tangent units)
    hold_scale: bool = True  # log-scale prior on every free keyframe at its scale when an optimisation starts
    scale_sigma: float = ranged(1e-3, gt=0, le=MAX_SCALAR)  # sigma of the log-scale priors
    world_scale_range: bool = True  # fix the distance between the scale pair of keyframes (monocular)
    range_sigma: float = ranged(1e-3, gt=0, le=MAX_SCALAR)  # sigma of that range constraint, relative to the initial distance


@dataclass
class WindowConfig:
    """What happens to keys outside the window of :meth:`~fgslam.backend.Backend.optimize_window`."""

    # fixed: every key outside the window keeps its value (factors reaching it are conditioned on it);
    # marginalize: the persistent built-in factors (loops, user factors) over keys outside the window
    # are linearised at the current estimate and those keys eliminated, leaving a linear prior on the
    # window keys they connect to. Contributors' blocks and the gauge are never marginalised: a
    # frontend rebuilds its blocks (with the frames it holds fixed) for every optimisation.
    leaving: Literal["fixed", "marginalize"] = "fixed"
    marginal_regularization: float = ranged(1e-9, ge=0, le=MAX_SCALAR)  # precision added to eliminated keys (directions no factor observes)
    # A window runs a few LM iterations per frame (the frontend's count, e.g. patch.ba.iterations):
    lambda_factor: float = ranged(1000.0, gt=1, le=MAX_SCALAR)  # LM damping multiplier after a rejected step (the pose Hessian dwarfs damping below ~1e4: x10 retries the same step)
    refine_steps: int = ranged(0, ge=0, le=MAX_ITERATIONS)  # structure Gauss-Newton steps at fixed poses before/after a window optimisation (LM updates the structure jointly anyway)


@dataclass
class PoseGraphCorrectionConfig:
    """Odometry terms of :meth:`~fgslam.backend.Backend.correct_pose_graph` (tangent [w(3), u(3), log s])."""

    rotation_sigma: float = ranged(1e-2, gt=0, le=MAX_SCALAR)  # rad, between consecutive keyframes
    translation_sigma: float = ranged(1e-1, gt=0, le=MAX_SCALAR)  # in the keyframes' local units
    log_scale_sigma: float = ranged(1e-2, gt=0, le=MAX_SCALAR)  # log-scale between consecutive keyframes


@dataclass
class BackendConfig:
    """Solver choice and tolerances of :class:`fgslam.backend.Backend` (YAML section ``map``)."""

    solver: Literal["lm", "python_lm", "isam2"] = "lm"  # lm (python_lm: alias) or isam2 (fgslam/backend/window.py)
    max_iterations: int = ranged(30, ge=1, le=MAX_ITERATIONS)  # LM iterations per optimisation unless the caller gives its own count
    relative_tolerance: float = ranged(1e-10, ge=0, le=MAX_SCALAR)  # stop when the relative cost decrease falls below this
    absolute_tolerance: float = ranged(1e-14, ge=0, le=MAX_SCALAR)  # stop when the cost falls below this
    step_tolerance: float = ranged(1e-12, ge=0, le=MAX_SCALAR)  # stop when the largest tangent step component falls below this
    lambda_initial: float = ranged(1e-6, gt=0, le=MAX_LAMBDA)  # initial LM damping (identity, on the pose tangents)
    lambda_factor: float = ranged(10.0, gt=1, le=MAX_SCALAR)  # LM damping multiplier on rejection / divisor on acceptance (global, pose graph; windows: window.lambda_factor)
    lambda_min: float = ranged(1e-12, gt=0, le=MAX_LAMBDA)  # smallest LM damping
    lambda_max: float = ranged(1e8, gt=0, le=MAX_LAMBDA)  # LM gives up (converged) when rejected steps push lambda above this
    refine_steps: int = ranged(2, ge=0, le=MAX_ITERATIONS)  # structure Gauss-Newton steps at fixed poses before and after a global optimisation (windows: window.refine_steps)
    refine_each_iteration: bool = False  # also refine after every accepted step (else: joint updates only)
    damp_structure: bool = False  # solver lm (isam2 ignores it): the LM damping also covers the blocks' eliminated structure (inverse depths): each damped solve re-eliminates it with lambda added to its information, so a rejected step shrinks the depth step too
    max_backtracks: int = ranged(6, ge=0, le=MAX_ITERATIONS)  # step halvings when an isam2 step raises the true cost
    threads: int = ranged(1, ge=0, le=MAX_THREADS)  # torch threads during optimisation (small dense solves: 1 is fastest)
    gauge: GaugeConfig = field(default_factory=GaugeConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    pose_graph: PoseGraphCorrectionConfig = field(default_factory=PoseGraphCorrectionConfig)

    @property
    def solver_kind(self) -> str:
        """``lm`` or ``isam2`` (aliases resolved)."""
        kind = SOLVER_ALIASES.get(self.solver)
        if kind is None:
            raise ConfigError(f"map.solver: unknown solver {self.solver!r} (expected lm or isam2; python_lm is an alias of lm)")
        return kind

    def validate(self) -> None:
        """Raise :class:`ConfigError` naming the key of an invalid choice."""
        _ = self.solver_kind


@dataclass
class GlobalBAConfig:
    """Tunables of :func:`fgslam.backend.global_ba.global_bundle_adjustment` (the patch frontend's
    ``patch.proximity.ba``)."""

    iterations: int = ranged(10, ge=1, le=MAX_ITERATIONS)  # Levenberg-Marquardt iterations per robust round
    robust_rounds: int = ranged(2, ge=1, le=MAX_ITERATIONS)  # rounds, each re-weighting the edges from the previous one's residuals
    huber_first_round: bool = True  # round 1 Huber-weighted from the initial residuals (no outlier cut); else plain least squares
    huber_delta: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # Huber threshold on the whitened residual (later rounds)
    outlier_threshold: float = ranged(6.0, gt=0, le=MAX_SCALAR)  # edges above this many pixels after a round get zero weight
    lambda_initial: float = ranged(1e-4, gt=0, le=MAX_LAMBDA)  # Marquardt damping: H + lambda diag(H)
    lambda_factor: float = ranged(10.0, gt=1, le=MAX_SCALAR)  # damping multiplier on rejection / divisor on acceptance
    lambda_max: float = ranged(1e4, gt=0, le=MAX_LAMBDA)  # rejected steps pushing lambda above this end the round (at a minimum)
    relative_tolerance: float = ranged(1e-6, ge=0, le=MAX_SCALAR)  # stop a round when the relative cost decrease falls below this
    min_structure: float = ranged(1e-6, gt=0, le=MAX_SCALAR)  # inverse depths are clamped to at least this
    min_information: float = ranged(1e-12, ge=0, le=MAX_SCALAR)  # patches with less information are not updated
    chunk_edges: int = ranged(200_000, ge=1, le=MAX_COUNT)  # edges linearised per batch (bounds memory: about 300 bytes per edge)
    threads: int = ranged(0, ge=0, le=MAX_THREADS)  # torch threads; 0: every core (large batched work, unlike the local BA; tracking waits for it)

    def validate(self) -> None:
        check_ranges(self, "patch.proximity.ba.")
