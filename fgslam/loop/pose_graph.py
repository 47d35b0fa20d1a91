"""Sim(3) pose-graph loop correction (DPV-SLAM sec. 3.3, eqs. 5-7) with false-loop rejection.

Variables are the keyframe poses ``T_WC_k`` (``fgslam.core.lie.Sim3``, ``X_W = s R X_C + t``), gtsam key
``k`` = keyframe index. Terms (all gtsam built-ins, solved by the backend's one Levenberg-Marquardt
loop, :func:`fgslam.backend.solver.levenberg_marquardt`, with GTSAM's LM defaults):

* smoothness (eq. 5's first sum): ``BetweenFactorSimilarity3(k, k+1, T_WC_k^-1 T_WC_k+1)`` from the
  poses *before* the correction, sigmas ``smooth_sigmas`` (tangent [w(3) rad, u(3), log s]; u is in
  the units of the keyframes' local frames);
* loops (eq. 5's second sum): ``BetweenFactorSimilarity3(i, j, T_CiCj)`` for each verified loop
  (``T_CiCj`` from :func:`fgslam.loop.sim3_estimation.estimate_sim3_ransac`, ``X_Ci = T_CiCj X_Cj``),
  sigmas ``loop_sigmas``, wrapped in a robust kernel (``gtsam.noiseModel.Robust``: Huber or Cauchy);
* gauge: ``PriorFactorSimilarity3`` holding keyframe 0 (all 7 dof) at its current pose;
* ``hold_scale`` (metric maps: stereo, RGB-D; :func:`optimize_sim3_pose_graph`): every keyframe keeps
  its scale, i.e. the graph is an SE(3) pose graph. Each keyframe gets a ``PriorFactorSimilarity3`` at
  its current pose that constrains only the log-scale (precision 0 on rotation and translation,
  sigma ``hold_scale_sigma`` on log s), each loop measurement's scale is replaced by the one the held
  scales imply (``s_j / s_i``: 1 on a metric map; a scale the verification estimated is noise there),
  and the returned poses carry the input scales exactly (``scale_correction`` is 1). The plausibility
  gate's and the pairwise check's scale tests then pass trivially.

Residual of a between term: ``r = Log(Z_ij^-1 T_i^-1 T_j)`` (see :mod:`fgslam.factors.sim3`).

False loops (issue 5, item 4; geometric verification happened upstream in RANSAC), in this order:

1. validity: indices in range, i != j, finite measurement with positive scale (else ``invalid``);
2. plausibility gate, before any solve: the correction a loop asks for,
   ``C = T_WC_j^-1 (T_WC_i Z_ij)`` (where the loop puts keyframe j, seen from where it is now), must
   have a rotation angle <= ``max_correction_rotation_deg``, a position change
   ``|t(T_WC_i Z_ij) - t_WC_j|`` <= ``max_correction_translation_fraction`` x the current path length
   between i and j (drift grows with distance travelled, so this is unit-free) and
   ``|log s(C)| <= max_correction_log_scale`` (else ``implausible``, logged, never solved with);
3. pairwise consistency (PCM-like, :func:`pairwise_support`): a loop needs
   ``min_pairwise_support`` other loops nearby whose cycle with it closes (else ``unsupported``).
   Real revisits are detected on several consecutive keyframes; a random false loop is alone;
4. robust solve and chi-square test: a first least-squares solve (``l2_first_solve``: at the
   drifted start every loop is a huge residual, where a kernel would weigh true and false loops down
   alike), then LM with the robust kernel; a loop is inconsistent when its whitened squared residual
   ``sum((r / loop_sigmas)^2)`` at the solution exceeds the ``consistency_probability`` quantile of
   chi2(7), or when the sum over its group (active loops with ends within ``pairwise_window``)
   exceeds the chi2(7 n) quantile (a consistent cluster of false loops, e.g. perceptual aliasing,
   passes the pairwise check and is half-fitted by bending the graph). Per round only the worst
   ones (chi2 >= ``rejection_ratio`` x the round's largest) are removed, rejected loops that fit
   again are re-admitted, and the graph is re-solved, until the set is stable (``max_rounds``
   solves at most). Then up to ``max_readmission_trials`` groups of
   rejected loops (smallest asked correction first) are tried on top of the accepted set and kept
   when every loop then passes the test (a loop alone in its region cannot fit a solution made
   without it). Rejected loops are ``inconsistent``.

Tuning note: ``smooth_sigmas`` must cover the odometry's real drift per keyframe step. If they are
much tighter, the robust optimum prefers leaving a loop with a large correction unsatisfied
(its kernel cost grows only linearly), and the chi-square test then rejects true loops.

After the solve: non-keyframe poses follow their anchor keyframe (:func:`correct_dependent_poses`)
and, for frontends whose keyframe scale is a gauge (dense, patch), the scale change is folded into
the depths (:func:`fold_scale_into_depths`, DPV-SLAM's ``d_i <- d_i / s_i``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from ..backend.pose_graph import LoopPoseGraph
from ..backend.solver import LMSettings
from ..core.errors import OptimizationError
from ..factors.sim3 import SIM3_DOF, sim3_between_residual
from ..core.lie import Sim3
from .records import PoseGraphConfig  # the config lives with loop closure's: torch-free (a run's config loads without torch)

logger = logging.getLogger(__name__)


@dataclass
class LoopDecision:
    """What happened to one input loop. ``reason`` is ``"accepted"``, ``"invalid: ..."``,
    ``"implausible: ..."`` (gate), ``"unsupported: ..."`` (pairwise consistency) or
    ``"inconsistent: ..."`` (chi-square after the robust solve)."""

    index: int  # position in the input
    i: int
    j: int
    accepted: bool
    reason: str
    rotation_deg: float  # correction the loop asked for at the input poses (gate quantities)
    translation_fraction: float
    log_scale: float
    chi2: float  # whitened squared residual at the final solution (nan if never evaluated)


@dataclass
class PoseGraphResult:
    """Output of :func:`optimize_sim3_pose_graph`.

    ``T_WC`` (K,) corrected keyframe poses; ``scale_correction`` (K,) = ``s_new / s_old`` per keyframe
    (the ``s_i`` of :func:`fold_scale_into_depths`); ``accepted`` (L,) bool per input loop, with the
    reasons in ``loops``. Errors are gtsam's ``0.5 * sum of whitened squared residuals`` (robust
    kernels applied) of the final graph at the input and at the corrected poses.
    """

    T_WC: Sim3
    scale_correction: torch.Tensor
    accepted: np.ndarray
    loops: list[LoopDecision]
    rounds: int
    iterations: int  # LM iterations summed over all solves (warm start, rounds, trials)
    initial_error: float
    final_error: float
    solve_time_s: float  # wall time of the whole call: gate, graph building, all LM solves, checks
    lm_time_s: float  # wall time inside the LM solves (all rounds)

    @property
    def n_rejected(self) -> int:
        return int((~self.accepted).sum())


def _rotation_angle_deg(R: torch.Tensor) -> torch.Tensor:
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(cos))


def loop_corrections(T_WC: Sim3, loop_i: np.ndarray, loop_j: np.ndarray, T_CiCj: Sim3) -> tuple[np.ndarray, ...]:
    """Gate quantities per loop at poses ``T_WC`` (K,): rotation (deg), position change / path
    length between i and j, and |log scale| of ``C = T_WC_j^-1 (T_WC_i T_CiCj)`` (each (L,))."""
    t = T_WC.t.detach().to(torch.float64)
    cum = torch.cat([t.new_zeros(1), torch.cumsum(torch.linalg.vector_norm(t[1:] - t[:-1], dim=-1), 0)])
    ii, jj = torch.as_tensor(loop_i), torch.as_tensor(loop_j)
    T_j_loop = T_WC[ii] @ T_CiCj
    C = T_WC[jj].inverse() @ T_j_loop
    path = (cum[jj] - cum[ii]).abs()
    dpos = torch.linalg.vector_norm(T_j_loop.t - t[jj], dim=-1)
    no_path = torch.where(dpos > 0, torch.full_like(path, math.inf), torch.zeros_like(path))
    frac = torch.where(path > 0, dpos / path.clamp_min(torch.finfo(path.dtype).tiny), no_path)
    return (
        _rotation_angle_deg(C.R).numpy(),
        frac.numpy(),
        torch.log(C.s).abs().numpy(),
    )


def pairwise_support(
    T_WC: Sim3, loop_i: np.ndarray, loop_j: np.ndarray, T_CiCj: Sim3, cfg: PoseGraphConfig
) -> np.ndarray:
    """Number of consistent partners (L,) of each loop (pairwise consistency, as in PCM).

    Two loops a = (i_a, j_a, Z_a), b = (i_b, j_b, Z_b) whose ends are within ``pairwise_window``
    keyframes of each other (after orienting both with i < j) close the cycle
    ``E = Z_a^-1 T_iaib Z_b T_jbja`` with ``T_xy = T_WC_x^-1 T_WC_y`` from the current poses; E is the
    identity up to loop noise and the odometry drift along i_a..i_b and j_b..j_a. They are
    consistent when angle(E) <= m sqrt2 sigma_rot + pairwise_drift_rotation_deg,
    |t(E)| <= m sqrt2 sigma_t + pairwise_drift_fraction x (path i_a..i_b + path j_a..j_b) and
    |log s(E)| <= m sqrt2 sigma_s + pairwise_drift_fraction, with m = ``pairwise_sigma_multiple`` and
    the sigmas the largest of ``loop_sigmas``' rotation / translation / scale parts.
    """
    L = loop_i.size
    if L < 2:
        return np.zeros(L, dtype=np.int64)
    flip = loop_i > loop_j
    a_end = np.where(flip, loop_j, loop_i)
    b_end = np.where(flip, loop_i, loop_j)
    Z = T_CiCj.to(torch.float64)
    flip_t = torch.from_numpy(flip)
    Z_inv = Z.inverse()
    Z = Sim3(torch.where(flip_t[:, None, None], Z_inv.R, Z.R), torch.where(flip_t[:, None], Z_inv.t, Z.t),
             torch.where(flip_t, Z_inv.s, Z.s))
    pa, pb = np.triu_indices(L, k=1)
    w = cfg.pairwise_window
    near = (np.abs(a_end[pa] - a_end[pb]) <= w) & (np.abs(b_end[pa] - b_end[pb]) <= w)
    pa, pb = pa[near], pb[near]
    support = np.zeros(L, dtype=np.int64)
    if pa.size == 0:
        return support
    t = T_WC.t.detach().to(torch.float64)
    cum = torch.cat([t.new_zeros(1), torch.cumsum(torch.linalg.vector_norm(t[1:] - t[:-1], dim=-1), 0)]).numpy()
    A_i, A_j, B_i, B_j = (torch.from_numpy(x) for x in (a_end[pa], b_end[pa], a_end[pb], b_end[pb]))
    ta, tb = torch.from_numpy(pa), torch.from_numpy(pb)
    E = Z[ta].inverse() @ (T_WC[A_i].inverse() @ T_WC[B_i]) @ Z[tb] @ (T_WC[B_j].inverse() @ T_WC[A_j])
    sig = np.asarray(cfg.loop_sigmas, dtype=np.float64)
    m = cfg.pairwise_sigma_multiple * math.sqrt(2.0)
    path = np.abs(cum[a_end[pa]] - cum[a_end[pb]]) + np.abs(cum[b_end[pa]] - cum[b_end[pb]])
    rot_ok = _rotation_angle_deg(E.R).numpy() <= np.degrees(m * sig[:3].max()) + cfg.pairwise_drift_rotation_deg
    trans_ok = torch.linalg.vector_norm(E.t, dim=-1).numpy() <= m * sig[3:6].max() + cfg.pairwise_drift_fraction * path
    scale_ok = torch.log(E.s).abs().numpy() <= m * sig[6] + cfg.pairwise_drift_fraction
    ok = rot_ok & trans_ok & scale_ok
    np.add.at(support, pa[ok], 1)
    np.add.at(support, pb[ok], 1)
    return support


def loop_chi2(T_WC: Sim3, loop_i: np.ndarray, loop_j: np.ndarray, T_CiCj: Sim3, loop_sigmas) -> np.ndarray:
    """Whitened squared residual ``sum((Log(Z^-1 T_i^-1 T_j) / sigma)^2)`` per loop (L,)."""
    ii, jj = torch.as_tensor(loop_i), torch.as_tensor(loop_j)
    r = sim3_between_residual(T_WC[ii], T_WC[jj], T_CiCj)[0]
    sig = torch.as_tensor(loop_sigmas, dtype=r.dtype)
    return ((r / sig) ** 2).sum(-1).numpy()


def smooth_sigmas(T_WC: Sim3, cfg: PoseGraphConfig) -> np.ndarray:
    """(K-1, 7) sigmas of the smoothness terms (see ``PoseGraphConfig.smooth_sigmas_per_distance``)."""
    sig = np.asarray(cfg.smooth_sigmas, dtype=np.float64)
    t = T_WC.t.detach().numpy()
    step = np.linalg.norm(np.diff(t, axis=0), axis=1)
    median = float(np.median(step)) if step.size else 0.0
    if not cfg.smooth_sigmas_per_distance or not median > 0:
        return np.broadcast_to(sig, (step.size, SIM3_DOF))
    factor = np.sqrt(np.maximum(step / median, cfg.min_step_fraction))
    return factor[:, None] * sig


def _held_scale_loops(T_WC: Sim3, loop_i: np.ndarray, loop_j: np.ndarray, T_CiCj: Sim3) -> Sim3:
    """Loop measurements with the scale the held keyframe scales imply, ``s_j / s_i`` (rotation and
    translation kept); loops with out-of-range indices keep theirs (the gate rejects them)."""
    K = T_WC.shape[0]
    in_range = (loop_i >= 0) & (loop_i < K) & (loop_j >= 0) & (loop_j < K)
    s = T_WC.s
    ratio = s[torch.from_numpy(np.where(in_range, loop_j, 0))] / s[torch.from_numpy(np.where(in_range, loop_i, 0))]
    held = torch.where(torch.from_numpy(in_range), ratio, T_CiCj.s)
    return Sim3(T_CiCj.R, T_CiCj.t, held)


def _loop_groups(loop_i: np.ndarray, loop_j: np.ndarray, members: np.ndarray, window: int) -> list[np.ndarray]:
    """Connected groups of the loops ``members`` whose (oriented) ends are within ``window`` keyframes."""
    if members.size == 0:
        return []
    a = np.minimum(loop_i[members], loop_j[members])
    b = np.maximum(loop_i[members], loop_j[members])
    near = (np.abs(a[:, None] - a[None]) <= window) & (np.abs(b[:, None] - b[None]) <= window)
    label = np.arange(members.size)
    changed = True
    while changed:  # label propagation to the smallest index of each component
        new = np.where(near, label[None, :], members.size).min(axis=1)
        changed = not np.array_equal(new, label)
        label = new
    return [members[label == g] for g in np.unique(label)]


class _LoopGraph:
    """The backend's loop-closure graph (:class:`fgslam.backend.pose_graph.LoopPoseGraph`) with this
    module's settings: LM settings of :class:`PoseGraphConfig`, chi-square of every candidate loop."""

    def __init__(self, T_WC: Sim3, loop_i, loop_j, T_CiCj: Sim3, cfg: PoseGraphConfig, hold_scale: bool,
                 smooth_scale: np.ndarray | None = None):
        self.cfg = cfg
        sigmas = smooth_sigmas(T_WC, cfg)
        if smooth_scale is not None:
            sigmas = sigmas * np.asarray(smooth_scale, dtype=np.float64).reshape(-1, 1)
        self.graph = LoopPoseGraph(T_WC, loop_i, loop_j, T_CiCj, sigmas, cfg.loop_sigmas,
                                   cfg.prior_sigma, cfg.hold_scale_sigma if hold_scale else None,
                                   cfg.robust_kernel, cfg.robust_param)
        self.loop_i, self.loop_j, self.T_CiCj = loop_i, loop_j, T_CiCj
        self.initial, self.base = self.graph.initial, self.graph.base

    @property
    def iterations(self) -> int:
        return self.graph.iterations

    @property
    def lm_time_s(self) -> float:
        return self.graph.lm_time_s

    def solve(self, active: np.ndarray, start, robust: bool = True, max_iterations: int | None = None):
        """LM on prior + smoothness + the ``active`` loops from ``start``; returns (graph, values)."""
        cfg = self.cfg
        settings = LMSettings(
            max_iterations=cfg.max_iterations if max_iterations is None else max_iterations,
            lambda_initial=cfg.lambda_initial, lambda_factor=cfg.lambda_factor, lambda_max=cfg.lambda_max,
            relative_tolerance=cfg.relative_error_tol, absolute_decrease_tolerance=cfg.absolute_error_tol,
        )
        return self.graph.solve(active, start, settings, robust)

    def poses(self, values) -> Sim3:
        return self.graph.poses(values)

    def chi2(self, values) -> np.ndarray:
        return loop_chi2(self.poses(values), self.loop_i, self.loop_j, self.T_CiCj, self.cfg.loop_sigmas)


def _inconsistent(chi2: np.ndarray, active: np.ndarray, loop_i, loop_j, cfg: PoseGraphConfig) -> np.ndarray:
    """Loops failing the chi-square test: their own chi2 exceeds the chi2(7) quantile, or, for
    active loops, the sum over their group (active loops with ends within ``pairwise_window``) exceeds
    the chi2(7 n) quantile: a consistent cluster of false loops that the graph bends to half-fit
    shows as many moderately large residuals, which only the joint test catches."""
    from scipy.special import chdtri  # deferred: scipy

    p_out = 1.0 - cfg.consistency_probability
    bad = chi2 > chdtri(SIM3_DOF, p_out)
    for g in _loop_groups(loop_i, loop_j, np.flatnonzero(active), cfg.pairwise_window):
        if g.size > 1 and chi2[g].sum() > chdtri(SIM3_DOF * g.size, p_out):
            bad[g] = True
    return bad


def _gate(T_WC: Sim3, loop_i, loop_j, T_CiCj: Sim3, cfg: PoseGraphConfig, reasons: list[str]):
    """Validity + plausibility gate; fills ``reasons`` and returns (ok (L,), rot_deg, frac, log_s)."""
    L = loop_i.size
    K = T_WC.shape[0]
    Zm = T_CiCj.matrix().numpy()
    bad_index = (loop_i < 0) | (loop_i >= K) | (loop_j < 0) | (loop_j >= K) | (loop_i == loop_j)
    bad_meas = ~(np.isfinite(Zm).all(axis=(1, 2)) & (T_CiCj.s.numpy() > 0))
    for l in np.flatnonzero(bad_index | bad_meas):
        why = "keyframe index out of range or i == j" if bad_index[l] else "non-finite measurement"
        reasons[l] = "invalid: " + why
        logger.warning("loop %d (%d, %d) rejected: %s", l, loop_i[l], loop_j[l], reasons[l])
    ok = ~(bad_index | bad_meas)
    rot_deg, frac, log_s = np.full(L, np.nan), np.full(L, np.nan), np.full(L, np.nan)
    idx = np.flatnonzero(ok)
    if idx.size:
        Z = T_CiCj[torch.from_numpy(idx)]
        rot_deg[idx], frac[idx], log_s[idx] = loop_corrections(T_WC, loop_i[idx], loop_j[idx], Z)
    for l in idx:
        why = []
        if not rot_deg[l] <= cfg.max_correction_rotation_deg:
            why.append(f"rotation {rot_deg[l]:.1f} deg > {cfg.max_correction_rotation_deg}")
        if not frac[l] <= cfg.max_correction_translation_fraction:
            why.append(f"position change {frac[l]:.3g} x path > {cfg.max_correction_translation_fraction}")
        if not log_s[l] <= cfg.max_correction_log_scale:
            why.append(f"|log scale| {log_s[l]:.3g} > {cfg.max_correction_log_scale}")
        if why:
            reasons[l] = "implausible: " + "; ".join(why)
            ok[l] = False
            logger.warning("loop %d (%d, %d) rejected: %s", l, loop_i[l], loop_j[l], reasons[l])
    return ok, rot_deg, frac, log_s


def optimize_sim3_pose_graph(
    T_WC: Sim3,
    loop_i,
    loop_j,
    T_CiCj: Sim3,
    config: PoseGraphConfig | None = None,
    hold_scale: bool = False,
    smooth_scale: np.ndarray | None = None,
) -> PoseGraphResult:
    """Correct keyframe poses ``T_WC`` (K,) with loops ``(loop_i[l], loop_j[l], T_CiCj[l])``.

    ``T_CiCj`` (L,) is the measured similarity from keyframe j's camera frame to keyframe i's
    (``X_Ci = T_CiCj X_Cj``; a perfect loop has ``T_CiCj = T_WC_i^-1 T_WC_j``). Loops with bad
    indices (out of range, i == j) or non-finite / non-positive-scale (scale: without ``hold_scale``)
    measurements are rejected as ``invalid``; the other checks are in the module docstring. With no
    accepted loop the poses come back unchanged. ``hold_scale`` (metric maps): every keyframe keeps
    its scale and each loop's measured scale is replaced by ``s_j / s_i`` (module docstring);
    ``scale_correction`` is then 1. ``smooth_scale`` (K-1,) multiplies the smoothness sigmas between
    consecutive keyframes (a joined map's session boundaries: a weak link that only fixes the gauge of a
    session no loop ties; None: 1). Raises ``OptimizationError`` if gtsam fails or returns non-finite
    poses, ValueError for inconsistent input shapes, ConfigError for an invalid config.
    """
    from scipy.special import chdtri  # deferred: scipy

    cfg = PoseGraphConfig() if config is None else config
    cfg.validate()
    T_WC = T_WC.to(torch.float64)
    if T_WC.s.dim() != 1 or T_WC.shape[0] < 1:
        raise ValueError(f"optimize_sim3_pose_graph: T_WC must have shape (K,), K >= 1, got {tuple(T_WC.shape)}")
    K = T_WC.shape[0]
    if not (torch.isfinite(T_WC.matrix()).all() and (T_WC.s > 0).all()):
        raise ValueError("optimize_sim3_pose_graph: keyframe poses T_WC must be finite with positive scale")
    loop_i = np.asarray(loop_i, dtype=np.int64).reshape(-1)
    loop_j = np.asarray(loop_j, dtype=np.int64).reshape(-1)
    L = loop_i.size
    if loop_j.size != L or tuple(T_CiCj.shape) != (L,):
        raise ValueError(f"optimize_sim3_pose_graph: {L} loop_i, {loop_j.size} loop_j, T_CiCj {tuple(T_CiCj.shape)}")
    if smooth_scale is not None and np.asarray(smooth_scale).shape != (K - 1,):
        raise ValueError(f"optimize_sim3_pose_graph: smooth_scale must have shape ({K - 1},)")
    t_start = time.perf_counter()
    T_CiCj = T_CiCj.to(torch.float64)
    if hold_scale and L:
        T_CiCj = _held_scale_loops(T_WC, loop_i, loop_j, T_CiCj)

    # 1. validity and plausibility gate
    reasons = ["accepted"] * L
    ok, rot_deg, frac, log_s = _gate(T_WC, loop_i, loop_j, T_CiCj, cfg, reasons)
    # 2. pairwise consistency
    if cfg.min_pairwise_support > 0 and ok.any():
        idx = np.flatnonzero(ok)
        support = pairwise_support(T_WC, loop_i[idx], loop_j[idx], T_CiCj[torch.from_numpy(idx)], cfg)
        for l, n_support in zip(idx, support):
            if n_support < cfg.min_pairwise_support:
                reasons[l] = f"unsupported: {n_support} consistent partner loops < {cfg.min_pairwise_support}"
                ok[l] = False
                logger.warning("loop %d (%d, %d) rejected: %s", l, loop_i[l], loop_j[l], reasons[l])
    cand = np.flatnonzero(ok)
    lg = _LoopGraph(T_WC, loop_i[cand], loop_j[cand], T_CiCj[torch.from_numpy(cand)], cfg, hold_scale, smooth_scale)

    # 3. robust solves with chi-square rejection (worst first) and re-admission
    chi2_thr = float(chdtri(SIM3_DOF, 1.0 - cfg.consistency_probability))  # chi2(7) quantile
    active = np.ones(cand.size, dtype=bool)
    graph, values, rounds = lg.base, lg.initial, 0
    chi2 = np.full(cand.size, np.nan)
    if cand.size and cfg.l2_first_solve and cfg.robust_kernel != "none":
        # Least squares from the drifted start, where every loop (true or false) is a huge residual
        # that a robust kernel would weigh down alike; the robust rounds start from its solution.
        _, values = lg.solve(active, values, robust=False, max_iterations=cfg.l2_max_iterations)
    while cand.size and rounds < cfg.max_rounds:
        graph, values = lg.solve(active, values)
        rounds += 1
        chi2 = lg.chi2(values)
        bad = active & _inconsistent(chi2, active, lg.loop_i, lg.loop_j, cfg)
        if bad.any():
            bad &= chi2 >= cfg.rejection_ratio * chi2[bad].max()
        new_active = (active & ~bad) | (~active & (chi2 <= chi2_thr))
        logger.info(
            "pose graph round %d: %d loops active, %d inconsistent, %d re-admitted (LM %d iterations, %.3f s)",
            rounds, active.sum(), (active & ~new_active).sum(), (~active & new_active).sum(),
            lg.iterations, lg.lm_time_s,
        )
        if np.array_equal(new_active, active):
            break
        active = new_active
        if rounds == cfg.max_rounds:  # the result must be the solve of the final set
            graph, values = lg.solve(active, values)
            chi2 = lg.chi2(values)
    # 4. re-admission trials: a rejected loop cannot fit a solution computed without it when nothing
    # else corrects its region. Groups of rejected loops (ends within pairwise_window), the one asking
    # for the smallest correction first, are tried on top of the accepted set and kept if every
    # active loop then passes the chi-square test.
    if (~active).any() and cfg.max_readmission_trials > 0:
        groups = _loop_groups(lg.loop_i, lg.loop_j, np.flatnonzero(~active), cfg.pairwise_window)
        groups.sort(key=lambda g: float(np.min(frac[cand[g]])))
        for g in groups[: cfg.max_readmission_trials]:
            trial = active.copy()
            trial[g] = True
            g_graph, g_values = lg.solve(trial, values)
            g_chi2 = lg.chi2(g_values)
            fits = not (trial & _inconsistent(g_chi2, trial, lg.loop_i, lg.loop_j, cfg)).any()
            logger.info("pose graph: re-admission trial of %d loops: %s", len(g), "kept" if fits else "refused")
            if fits:
                active, graph, values, chi2 = trial, g_graph, g_values, g_chi2
    T_new = lg.poses(values)
    if not (torch.isfinite(T_new.matrix()).all() and (T_new.s > 0).all()):
        raise OptimizationError(f"Sim(3) pose graph on {K} keyframes returned non-finite poses")
    if hold_scale:  # the priors held the scales to ~hold_scale_sigma; hand back the exact ones
        logger.debug("pose graph (hold_scale): largest |log scale change| %.3g before projection",
                     float(torch.log(T_new.s / T_WC.s).abs().max()))
        T_new = Sim3(T_new.R, T_new.t, T_WC.s.clone())

    accepted = np.zeros(L, dtype=bool)
    accepted[cand[active]] = True
    chi2_all = np.full(L, np.nan)
    chi2_all[cand] = chi2
    for l in cand[~active]:
        reasons[l] = f"inconsistent: chi2 {chi2_all[l]:.3g} (per-loop threshold {chi2_thr:.3g}, or its group's sum)"
        logger.warning("loop %d (%d, %d) rejected: %s", l, loop_i[l], loop_j[l], reasons[l])
    decisions = [
        LoopDecision(int(l), int(loop_i[l]), int(loop_j[l]), bool(accepted[l]), reasons[l],
                     float(rot_deg[l]), float(frac[l]), float(log_s[l]), float(chi2_all[l]))
        for l in range(L)
    ]
    solve_time = time.perf_counter() - t_start
    logger.info(
        "Sim(3) pose graph: %d keyframes, %d/%d loops accepted, %d rounds, %.3f s",
        K, accepted.sum(), L, rounds, solve_time,
    )
    return PoseGraphResult(
        T_WC=T_new,
        scale_correction=T_new.s / T_WC.s,
        accepted=accepted,
        loops=decisions,
        rounds=rounds,
        iterations=lg.iterations,
        initial_error=float(graph.error(lg.initial)),
        final_error=float(graph.error(values)),
        solve_time_s=solve_time,
        lm_time_s=lg.lm_time_s,
    )


def relative_to_anchor(T_WK: Sim3, anchor, T_WF: Sim3) -> Sim3:
    """Poses of frames F relative to their anchor keyframes: ``T_KF = T_WK[anchor]^-1 T_WF`` (M,)."""
    return T_WK[torch.as_tensor(anchor, dtype=torch.long)].inverse() @ T_WF


def correct_dependent_poses(T_WK_new: Sim3, anchor, T_KF: Sim3) -> Sim3:
    """Corrected world poses of non-keyframes ``T_WF = T_WK_new[anchor] @ T_KF`` (M,).

    ``anchor`` (M,) is each frame's keyframe index and ``T_KF`` (M,) its pose relative to that
    keyframe (:func:`relative_to_anchor` on the poses before the correction). The frame moves rigidly
    with its keyframe, Sim(3) scale included.
    """
    return T_WK_new[torch.as_tensor(anchor, dtype=torch.long)] @ T_KF


def fold_scale_into_depths(T_WC_old: Sim3, T_WC_new: Sim3, inv_depth: torch.Tensor) -> tuple[Sim3, torch.Tensor]:
    """Move the pose-graph scale change into the depths (DPV-SLAM: ``d_i <- d_i / s_i``).

    With ``s_i = s_new_i / s_old_i`` (``PoseGraphResult.scale_correction``), keyframe i keeps its
    old scale ``s_old_i`` and the new rotation and translation, and its inverse depths ``d``
    (shape (K, ...), ``X_Ci = (x, y, 1) / d``) become ``d / s_i`` (depths ``z * s_i``; points in
    camera i ``X_Ci * s_i``). World points are unchanged:
    ``s_new R X / d = s_old R X / (d / s_i)``. Returns ``(T_WC_folded (K,), inv_depth_new)``.
    """
    s_i = T_WC_new.s / T_WC_old.s
    folded = Sim3(T_WC_new.R, T_WC_new.t, T_WC_old.s.expand_as(T_WC_new.s).clone())
    shape = (-1,) + (1,) * (inv_depth.dim() - 1)
    return folded, inv_depth / s_i.to(inv_depth.dtype).reshape(shape)
