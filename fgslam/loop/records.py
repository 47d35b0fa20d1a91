"""Loop closure's data types: the ``loop_closure`` configuration (with the pose graph's and the Sim(3)
RANSAC's: this module imports no torch, so that a run's config loads without it), verification and loop records, and
the :class:`PoseCorrection` that moves a map's keyframes (its use: :mod:`fgslam.loop.closure`).

Conventions: poses are camera-to-world Sim(3) ``T_WC`` (``X_W = s R X_C + t``, 4x4
``[[s R, t], [0, 1]]``); keyframe ids are the caller's integers.

Corrections: a :class:`PoseCorrection` holds, for every keyframe of the pose-graph snapshot, the
world-frame update ``U_k = T_WC_new_k T_WC_old_k^-1`` (Sim(3)). The frontend applies it at a safe
point as ``T_WC <- U_k T_WC`` to its *current* pose of keyframe k (local refinements since the
snapshot are kept) and, for keyframes added after the snapshot, with the update of the nearest
corrected keyframe id (:meth:`PoseCorrection.update_for`). With ``fold_scale`` (frontends whose pose
scale is a fixed gauge: patch, dense) the scale part ``s_k`` of ``U_k`` is folded into the depths
(DPV-SLAM: ``d <- d / s_k``) and the pose keeps its old scale (:meth:`PoseCorrection.apply`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np

from ..core.config import (MAX_COUNT, MAX_FRAMES, MAX_ITERATIONS, MAX_KEYFRAMES, MAX_LAMBDA, MAX_SCALAR, MAX_SEED,
                           check_ranges, ranged)
from ..core.errors import ConfigError
from ..factors.configs import SIM3_DOF
from .bow import BowConfig
from .vlad import LoopFeaturesConfig

LOOP_MODES = ("off", "proximity", "classical", "both")
MINIMAL_SAMPLE = 3  # points that fix a Sim(3) (7 dof) in general position


# ----------------------------------------------------------------------------------- configs

@dataclass
class Sim3RansacConfig:
    """Tunables of :func:`fgslam.loop.sim3_estimation.estimate_sim3_ransac`."""

    error_metric: Literal["relative", "absolute"] = "relative"  # see the docstring of fgslam.loop.sim3_estimation
    inlier_threshold: float = ranged(0.05, gt=0, le=MAX_SCALAR)  # inlier when the 3-D error (relative: fraction of point range) is below
    min_inliers: int = ranged(20, ge=MINIMAL_SAMPLE, le=MAX_COUNT)  # fewer inliers than this: no solution
    max_iterations: int = ranged(500, ge=1, le=MAX_ITERATIONS)  # RANSAC hypotheses at most (degenerate samples count)
    confidence: float = ranged(0.999, gt=0, lt=1)  # adaptive stop: P(at least one all-inlier sample)
    min_sample_spread: float = ranged(1e-3, ge=0, le=MAX_SCALAR)  # coincident sample: largest singular value < this x median range
    min_sample_collinearity: float = ranged(0.05, ge=0, lt=1)  # collinear sample: sigma_2 / sigma_1 below this
    refine_iterations: int = ranged(3, ge=0, le=MAX_ITERATIONS)  # re-fit on all inliers and re-classify, at most this many times
    seed: int = ranged(0, ge=0, le=MAX_SEED)  # random generator seed (reproducible sampling)

    def validate(self) -> None:
        """Raise ConfigError naming the first invalid field."""
        if self.error_metric not in ("relative", "absolute"):
            raise ConfigError(f"Sim3RansacConfig.error_metric={self.error_metric!r}: expected relative or absolute")
        check_ranges(self, "Sim3RansacConfig.")


@dataclass
class PoseGraphConfig:
    """Tunables of :func:`fgslam.loop.pose_graph.optimize_sim3_pose_graph`. Sigmas are in tangent order [w(3), u(3), log s]."""

    smooth_sigmas: tuple[float, ...] = ranged((0.002, 0.002, 0.002, 0.02, 0.02, 0.02, 0.002), gt=0, le=MAX_SCALAR)  # consecutive keyframes
    loop_sigmas: tuple[float, ...] = ranged((0.01, 0.01, 0.01, 0.1, 0.1, 0.1, 0.01), gt=0, le=MAX_SCALAR)  # loop terms (rad, local units, log s)
    # Scale each smoothness sigma by sqrt(step / median step) (step = distance between consecutive
    # keyframes): drift accrues per distance travelled, so the correction is spread per distance.
    smooth_sigmas_per_distance: bool = True
    min_step_fraction: float = ranged(0.1, gt=0, le=1)  # floor of step / median step in that scaling (standstill)
    prior_sigma: float = ranged(1e-6, gt=0, le=MAX_SCALAR)  # gauge prior on keyframe 0, every tangent component
    robust_kernel: Literal["none", "huber", "cauchy"] = "huber"  # m-estimator on the loop terms
    robust_param: float = ranged(1.345, gt=0, le=MAX_SCALAR)  # kernel threshold in whitened units (Huber 95% efficiency constant)
    max_iterations: int = ranged(100, ge=1, le=MAX_ITERATIONS)  # LM iterations per solve
    relative_error_tol: float = ranged(1e-6, ge=0, le=MAX_SCALAR)  # LM stops when the relative cost decrease falls below this
    absolute_error_tol: float = ranged(1e-9, ge=0, le=MAX_SCALAR)  # LM stops when the absolute cost decrease falls below this
    lambda_initial: float = ranged(1e-5, gt=0, le=MAX_LAMBDA)  # initial LM damping (GTSAM's default)
    lambda_factor: float = ranged(10.0, gt=1, le=MAX_SCALAR)  # LM damping multiplier on a rejected / accepted step
    lambda_max: float = ranged(1e5, gt=0, le=MAX_LAMBDA)  # LM stops (no descent at any damping) above this
    consistency_probability: float = ranged(0.9999, gt=0, lt=1)  # chi2(7) quantile above which a loop is inconsistent
    max_rounds: int = ranged(8, ge=1, le=MAX_ITERATIONS)  # solves at most (reject inconsistent loops, re-admit consistent ones, re-solve)
    # Per round, reject only the inconsistent loops whose chi2 is >= this x the round's largest one
    # (worst first: a false loop distorts its neighbourhood, so true loops there look bad until it goes).
    rejection_ratio: float = ranged(0.1, ge=0, le=1)
    max_correction_rotation_deg: float = ranged(45.0, gt=0, le=180)  # plausibility gate: rotation a loop may correct
    max_correction_translation_fraction: float = ranged(0.3, gt=0, le=MAX_SCALAR)  # gate: position change / path length between i and j
    max_correction_log_scale: float = ranged(0.7, gt=0, le=MAX_SCALAR)  # gate: |log| of the scale change a loop may ask for (~x2)
    # Pairwise consistency: a loop needs this many consistent partner loops (0 disables the check).
    min_pairwise_support: int = ranged(1, ge=0, le=MAX_COUNT)
    pairwise_window: int = ranged(30, ge=1, le=MAX_KEYFRAMES)  # partners: both ends within this many keyframes of the loop's ends
    pairwise_sigma_multiple: float = ranged(5.0, ge=0, le=MAX_SCALAR)  # cycle tolerance, in loop sigmas (x sqrt 2: two loops)
    pairwise_drift_fraction: float = ranged(0.05, ge=0, le=MAX_SCALAR)  # plus this fraction of the odometry path inside the cycle
    pairwise_drift_rotation_deg: float = ranged(2.0, ge=0, le=180)  # plus this rotation (odometry drift inside the cycle)
    max_readmission_trials: int = ranged(3, ge=0, le=MAX_ITERATIONS)  # rejected loop groups tried again on the final accepted set
    l2_first_solve: bool = True  # first solve without kernel (every loop is a large residual at the start)
    l2_max_iterations: int = ranged(10, ge=1, le=MAX_ITERATIONS)  # LM iterations of that warm-start solve
    hold_scale_sigma: float = ranged(1e-9, gt=0, le=MAX_SCALAR)  # hold_scale: sigma of each keyframe's log-scale prior

    def validate(self) -> None:
        """Raise ConfigError naming the first invalid field."""
        check_ranges(self, "PoseGraphConfig.")
        for name in ("smooth_sigmas", "loop_sigmas"):
            if len(getattr(self, name)) != SIM3_DOF:
                raise ConfigError(f"PoseGraphConfig.{name}={getattr(self, name)!r}: need 7 finite sigmas > 0")
        if self.robust_kernel not in ("none", "huber", "cauchy"):
            raise ConfigError(f"PoseGraphConfig.robust_kernel={self.robust_kernel!r}: expected none, huber or cauchy")


@dataclass
class VerificationConfig:
    """Geometric verification of a retrieved keyframe pair."""

    max_hamming: int = ranged(64, ge=1, le=256)  # ORB match: largest Hamming distance (of 256 bits)
    ratio: float = ranged(0.8, gt=0, le=1)  # Lowe ratio test: best < ratio x second best
    min_matches: int = ranged(40, ge=1, le=MAX_COUNT)  # ORB matches q <-> c needed before triangulation
    max_epipolar_px: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # neighbour matches: distance to the epipolar line (pixels)
    min_parallax_deg: float = ranged(2.0, gt=0, lt=180)  # triangulation: smallest angle between the two rays
    max_reprojection_px: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # triangulation: largest reprojection error in either view
    min_triangulated: int = ranged(30, ge=1, le=MAX_COUNT)  # matched features with a 3-D point needed per side
    max_neighbours: int = ranged(4, ge=1, le=MAX_KEYFRAMES)  # neighbours tried per keyframe for triangulation
    min_points: int = ranged(25, ge=1, le=MAX_COUNT)  # q <-> c matches with a 3-D point on both sides
    ransac: Sim3RansacConfig = field(default_factory=Sim3RansacConfig)

    def validate(self) -> None:
        self.ransac.validate()


@dataclass
class RelocalizationConfig:
    """Relocalisation of a lost frame against the keyframe database (stricter than loop detection)."""

    min_score: float = ranged(0.05, ge=0, le=1)  # raw DBoW2 L1 score a candidate needs
    max_candidates: int = ranged(5, ge=1, le=MAX_KEYFRAMES)  # best-scored keyframes verified at most
    min_matches: int = ranged(50, ge=4, le=MAX_COUNT)  # ORB matches image <-> keyframe
    min_inliers: int = ranged(40, ge=4, le=MAX_COUNT)  # PnP RANSAC inliers
    pnp_reprojection_px: float = ranged(3.0, gt=0, le=MAX_SCALAR)  # PnP RANSAC inlier threshold
    pnp_iterations: int = ranged(200, ge=1, le=MAX_ITERATIONS)  # PnP RANSAC hypotheses
    pnp_confidence: float = ranged(0.999, gt=0, lt=1)  # PnP RANSAC early-stop confidence


@dataclass
class LoopClosureConfig:
    """Loop closure switches and tunables (``mode``: the frontend implements ``proximity``, this
    module ``classical``; ``both`` runs both, ``off`` neither)."""

    mode: Literal["off", "proximity", "classical", "both"] = "off"  # loop closure is opt-in
    bow: BowConfig = field(default_factory=BowConfig)
    features: LoopFeaturesConfig = field(default_factory=LoopFeaturesConfig)  # kind orb (bow) | xfeat (optional extra)
    verification: VerificationConfig = field(default_factory=VerificationConfig)
    pose_graph: PoseGraphConfig = field(default_factory=PoseGraphConfig)
    relocalization: RelocalizationConfig = field(default_factory=RelocalizationConfig)
    run_in_thread: bool = True            # worker threads (classical closer, global BA); False: synchronous (same results)
    # Reproducible runs: a background result is taken this many frames (safe points) after the frame
    # that handed over its work, waiting there when it is not ready (never "when it happens to finish")
    correction_delay_frames: int = ranged(3, ge=1, le=MAX_FRAMES)  # classical closer: keyframe -> its correction
    # proximity loop -> its global BA's result; street drive (1,100 frames, low load): 10 -> ATE 0.284 m and
    # 10 s stalls, 60 -> 0.255 m (0.266 m before, results applied when ready); a global BA takes 3-11 s there
    global_ba_delay_frames: int = ranged(60, ge=1, le=MAX_FRAMES)
    max_candidates: int = ranged(2, ge=1, le=MAX_KEYFRAMES)  # accepted BoW candidates verified per query keyframe
    fold_scale: bool = True               # frontend folds the scale correction into depths
    max_pose_graph_retries: int = ranged(3, ge=1, le=MAX_ITERATIONS)  # re-solves of a correction computed before another was applied
    # Pose-graph throttle (fgslam.loop.closure docstring): once a loop cluster has a correction, its
    # further loops are solved at most every solve_every described keyframes (1: after every verified loop) ...
    solve_every: int = ranged(5, ge=1, le=MAX_KEYFRAMES)
    cluster_gap: int = ranged(10, ge=1, le=MAX_KEYFRAMES)  # ... a loop > this many keyframes after the last one: new cluster

    def validate(self) -> None:
        if self.mode not in LOOP_MODES:
            raise ConfigError(f"loop_closure.mode={self.mode!r}: expected one of {', '.join(LOOP_MODES)}")
        check_ranges(self, "loop_closure.")
        self.verification.validate()
        self.pose_graph.validate()
        self.features.validate()

    @property
    def classical(self) -> bool:
        return self.mode in ("classical", "both")

    @property
    def proximity(self) -> bool:
        return self.mode in ("proximity", "both")


# ----------------------------------------------------------------------------------- results

@dataclass
class Verification:
    """Outcome of the geometric verification of (query, candidate). ``T_CqCc`` (4x4 Sim(3),
    ``X_Cq = T_CqCc X_Cc``) only when ``accepted``; ``reason`` says why not."""

    query_id: int
    candidate_id: int
    accepted: bool
    reason: str
    n_matches: int = 0
    n_points: int = 0                     # matches with a 3-D point on both sides
    n_inliers: int = 0
    rms_error: float = math.inf
    T_CqCc: np.ndarray | None = None
    bow_score: float = 0.0


@dataclass
class LoopRecord:
    """A verified loop and what the pose graph made of it (``status``: ``pending`` before any
    solve, ``accepted`` or the pose graph's rejection reason)."""

    query_id: int
    candidate_id: int
    T_CqCc: np.ndarray                    # 4x4 Sim(3) in the keyframes' current units
    n_inliers: int
    status: str = "pending"


@dataclass
class PoseCorrection:
    """A Sim(3) correction of keyframe poses (module docstring: how to apply it): from the
    classical closer's pose graph, or from a global bundle adjustment that ran on a snapshot
    (:mod:`fgslam.services.loops`). ``LoopCorrection`` is its former name.

    ``T_update[k]`` = ``T_WC_new_k T_WC_old_k^-1`` (4x4 Sim(3), world frame) for every keyframe of
    the snapshot; ``scale[k]`` = its scale ``s_new_k / s_old_k``; ``T_WC_new[k]`` the corrected
    pose of the snapshot (before folding). ``loops`` lists every verified loop with its status. From a
    metric closer every ``scale`` is 1 and ``fold_scale`` is False.
    """

    T_update: dict[int, np.ndarray]
    scale: dict[int, float]
    T_WC_new: dict[int, np.ndarray]
    loops: list[LoopRecord]
    fold_scale: bool
    n_accepted: int
    solve_time_s: float
    hold_older: bool = False  # keyframes older than every listed one keep their pose (a global BA of the current map)
    _ids: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._ids = np.array(sorted(self.T_update), dtype=np.int64)

    @classmethod
    def between(cls, T_WC_old: dict[int, np.ndarray], T_WC_new: dict[int, np.ndarray], solve_time_s: float = 0.0,
                fold_scale: bool = False, loops: Sequence[LoopRecord] = (), n_accepted: int = 0,
                hold_older: bool = False) -> "PoseCorrection":
        """The correction that takes every keyframe from ``T_WC_old[k]`` to ``T_WC_new[k]`` (4x4 Sim(3)
        each, same keys): ``U_k = T_new T_old^-1``, ``scale[k] = s_new / s_old``."""
        from ..core.lie import sim3_matrix_parts  # deferred: core.lie pulls torch (the config stays light)

        updates, scale = {}, {}
        for k, T_old in T_WC_old.items():
            T_new = np.asarray(T_WC_new[k], np.float64)
            updates[k] = T_new @ np.linalg.inv(T_old)
            scale[k] = float(sim3_matrix_parts(T_new)[2] / sim3_matrix_parts(T_old)[2])
        return cls(updates, scale, {k: np.asarray(T, np.float64) for k, T in T_WC_new.items()}, list(loops),
                   fold_scale, n_accepted, solve_time_s, hold_older)

    def update_for(self, kf_id: int) -> tuple[np.ndarray, float]:
        """``(U (4, 4), s)`` of keyframe ``kf_id``: its own update, or that of the corrected
        keyframe with the nearest id (ties: the older one) for keyframes outside the snapshot
        (with ``hold_older``, the identity for ids below every listed one)."""
        if kf_id in self.T_update:
            return self.T_update[kf_id], self.scale[kf_id]
        if self.hold_older and (len(self._ids) == 0 or kf_id < self._ids[0]):
            return np.eye(4), 1.0
        pos = int(np.searchsorted(self._ids, kf_id))
        near = [self._ids[p] for p in (pos - 1, pos) if 0 <= p < len(self._ids)]
        best = int(min(near, key=lambda k: (abs(int(k) - kf_id), k)))
        return self.T_update[best], self.scale[best]

    def apply_pose(self, kf_id: int, T_WC: np.ndarray) -> tuple[np.ndarray, float]:
        """Corrected 4x4 pose of keyframe ``kf_id`` from its current pose ``T_WC`` and the depth
        factor ``s`` (``inv_depth <- inv_depth / s``; 1 without ``fold_scale``)."""
        U, s = self.update_for(kf_id)
        T_new = _project_sim3(U @ np.asarray(T_WC, np.float64))
        if not self.fold_scale:
            return T_new, 1.0
        T_new[:3, :3] /= s                 # keep the old scale: T_new S(s)^-1
        return T_new, s

    def apply(self, T_WC_by_id: dict[int, np.ndarray]) -> tuple[dict[int, np.ndarray], dict[int, float]]:
        """:meth:`apply_pose` for every keyframe of a pose table; returns (poses, depth factors)."""
        poses, factors = {}, {}
        for k, T in T_WC_by_id.items():
            poses[k], factors[k] = self.apply_pose(int(k), T)
        return poses, factors

    @staticmethod
    def fold_relative(T_KF: np.ndarray, s: float) -> np.ndarray:
        """A frame's pose relative to its anchor keyframe after the anchor's scale ``s`` was folded
        into depths: ``S(s) T_KF S(s)^-1`` (translation times ``s``)."""
        out = np.array(T_KF, dtype=np.float64, copy=True)
        out[:3, 3] *= s
        return out


LoopCorrection = PoseCorrection  # former name


def _project_sim3(M: np.ndarray) -> np.ndarray:
    """The nearest ``[[s R, t], [0, 1]]`` (R in SO(3)): repeated corrections must not let rounding
    errors grow."""
    from ..core.lie import sim3_matrix_parts  # deferred: core.lie pulls torch (the config stays light)

    R, t, s = sim3_matrix_parts(M, project=True)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = s * R, t
    return out
