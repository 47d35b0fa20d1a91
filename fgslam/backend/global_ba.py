"""Global bundle adjustment of a patch graph (DPV-SLAM sec. 3.2): every keyframe pose and every
patch inverse depth of the active and inactive edges, with a sparse reduced camera system.

The backend's part: the problem as plain arrays and its solve (a picklable top-level function, run
in a worker process); the patch frontend builds the problem from its graph
(:meth:`fgslam.frontends.patch.contributor.PatchContributor.global_ba_job`).

Problem (:class:`GlobalBAProblem`): F frames with Sim(3) poses ``T_WC`` (4x4 ``[[s R, t], [0, 1]]``;
the scale of each pose is *held*: the update is SE(3), tangent ``[w, u]`` of ``fgslam.core.lie.Sim3``'s
``[w, u, lambda]`` with lambda = 0, right perturbation ``T <- T Exp(xi)``), P patches (each owned by
one source frame, one inverse depth each) and N edges ``(src, tgt, right)``: patch centre
``uv_src`` of frame ``src`` seen at ``uv`` in frame ``tgt`` (its right image through ``T_CRCL``
when ``right``), residual ``pi(T_CtCj T_WCtgt^-1 T_WCsrc X(uv_src, d)) - uv`` in pixels, weight
``weight * robust``. RGB-D priors ``d[prior_idx] ~ prior_value``. Frames flagged ``fixed`` are the
gauge (monocular: at least two, which also fix the map's scale).

Why not one :class:`~.ba.PatchBlock` through :meth:`fgslam.backend.Backend.optimize_window`: that block's reduced
system is dense over all its frames (7F x 7F), fine for a local window and impossible for
thousands of keyframes. Here the Schur complement is taken *per source frame*: a patch touches
only its source frame and the frames it is observed in, so each source frame ``i`` contributes a
dense ``(6 S_i)^2`` block over its slots (itself and its targets, ``S_i`` about
``2 * patch_lifetime + 1``), computed for all frames at once with batched products and the
batched Schur elimination of :func:`fgslam.factors.schur.eliminate_structure`, and the global
system ``sum_i`` of those blocks is sparse (banded plus loop couplings). It is solved by the
backend's one Levenberg-Marquardt loop (:func:`fgslam.backend.solver.levenberg_marquardt`):
one ``gtsam.HessianFactor`` per source frame over its variable slots (from the compressed
Jacobian, :func:`fgslam.factors.schur.to_gaussian_factor`), Marquardt's scaled damping
``H + lambda diag(H)`` as unary factors beside them, GTSAM's multifrontal Cholesky in a METIS
ordering computed once per problem. Depths are back-substituted per patch in each trial step.

Robustness: ``robust_rounds`` rounds, each re-weighting the edges with Huber weights of the residuals
at its start; the first one cuts no edge (loop edges start with large residuals and must act before
they are judged), later ones give zero weight to residuals above ``outlier_threshold`` pixels. Plain
least squares in the first round (``huber_first_round: false``) lets stale inactive edges drag the
map: on the street-loop clip the keyframe ATE after the first loop went to 2.2 m instead of 0.31 m.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from ..core.errors import OptimizationError
from ..factors.depth import depth_prior
from ..factors.reprojection import ReprojectionConfig, reproject_edges
from ..factors.robust import kernel_weight
from ..factors.schur import eliminate_structure, information_inverse, to_gaussian_factor, torch_threads
from ..core.lie import Sim3, sim3_matrix_components
from .config import GlobalBAConfig
from .solver import LMSettings, levenberg_marquardt

logger = logging.getLogger(__name__)

POSE_DOF = 6  # held scale: rotation + translation of the Sim(3) tangent [w, u, lambda]


@dataclass
class GlobalBAProblem:
    """Input of :func:`global_bundle_adjustment` (shapes in the module docstring's notation)."""

    T_WC: np.ndarray  # (F, 4, 4) Sim(3) camera-to-world
    fixed: np.ndarray  # (F,) bool: pose held
    src: np.ndarray  # (N,) source frame of each edge
    tgt: np.ndarray  # (N,) target frame
    right: np.ndarray  # (N,) bool: target is the right image
    uv_src: np.ndarray  # (N, 2) patch centre in the source frame (pixels)
    uv: np.ndarray  # (N, 2) observed pixel in the target image
    weight: np.ndarray  # (N,) >= 0 (confidence / sigma^2)
    struct_idx: np.ndarray  # (N,) patch of each edge in [0, P)
    inv_depth: np.ndarray  # (P,) initial inverse depths
    K: np.ndarray  # (4,) fx, fy, cx, cy of the left images
    K_right: Optional[np.ndarray] = None  # (4,) right intrinsics (right edges)
    T_CRCL: Optional[np.ndarray] = None  # (4, 4) left-to-right extrinsic (right edges)
    prior_idx: Optional[np.ndarray] = None  # (M,) patches with a depth prior
    prior_value: Optional[np.ndarray] = None  # (M,) prior inverse depth
    prior_weight: Optional[np.ndarray] = None  # (M,) prior weight (1 / sigma^2)

    def check(self) -> None:
        F = int(np.asarray(self.T_WC).shape[0])
        n = int(np.asarray(self.src).shape[0])
        P = int(np.asarray(self.inv_depth).shape[0])
        if np.asarray(self.T_WC).shape != (F, 4, 4) or np.asarray(self.fixed).shape != (F,):
            raise OptimizationError("global BA: T_WC must be (F, 4, 4) and fixed (F,)")
        for name, shape in (("tgt", (n,)), ("right", (n,)), ("uv_src", (n, 2)), ("uv", (n, 2)),
                            ("weight", (n,)), ("struct_idx", (n,))):
            if np.asarray(getattr(self, name)).shape != shape:
                raise OptimizationError(f"global BA: {name} must have shape {shape}, got {np.asarray(getattr(self, name)).shape}")
        if n and (min(self.src.min(), self.tgt.min()) < 0 or max(self.src.max(), self.tgt.max()) >= F):
            raise OptimizationError(f"global BA: edge frames must lie in [0, {F})")
        if n and (self.struct_idx.min() < 0 or self.struct_idx.max() >= P):
            raise OptimizationError(f"global BA: struct_idx must lie in [0, {P})")
        if bool(np.asarray(self.right).any()) and (self.K_right is None or self.T_CRCL is None):
            raise OptimizationError("global BA: right-image edges need K_right and T_CRCL")
        w = np.asarray(self.weight)
        if not (np.isfinite(w).all() and (w >= 0).all()):
            raise OptimizationError("global BA: weights must be finite and non-negative")
        if not (np.isfinite(self.T_WC).all() and np.isfinite(self.inv_depth).all()):
            raise OptimizationError("global BA: poses and inverse depths must be finite")
        if n:
            owner = np.full(P, -1, np.int64)
            owner[self.struct_idx] = self.src
            if (owner[self.struct_idx] != self.src).any():
                raise OptimizationError("global BA: every patch must belong to one source frame")


@dataclass
class GlobalBAResult:
    """Output of :func:`global_bundle_adjustment`."""

    T_WC: np.ndarray  # (F, 4, 4) optimised poses (fixed ones unchanged)
    inv_depth: np.ndarray  # (P,) optimised inverse depths
    robust: np.ndarray  # (N,) robust weight of the last round (0: outlier or invalid)
    residual: np.ndarray  # (N,) final residual norm (pixels; inf where the projection is invalid)
    initial_cost: float  # 0.5 sum weight |r|^2 at the start (given weights)
    final_cost: float  # the same at the end (given weights, inliers of the last round)
    iterations: int  # accepted + rejected LM steps over all rounds
    seconds: float
    num_edges: int
    num_variables: int  # optimised poses
    timings: dict = field(default_factory=dict)  # seconds per stage (linearize, construct, solve, evaluate)
    linearizations: int = 0  # systems built (each solved once per LM step, accepted or rejected)
    linear_solver: str = "gtsam"  # what solved them: GTSAM's multifrontal Cholesky (the only one)


# ------------------------------------------------------------------------------------------------
@dataclass
class _Chunk:
    """Edges ``lo:hi`` (sorted by source frame) of whole source frames, with their slot layout:
    each source frame's slots are itself (slot 0) and its other targets in increasing order."""

    lo: int
    hi: int
    ns: int  # source frames in the chunk
    S: int  # slots per source frame (padded)
    slot_tgt: torch.Tensor  # (n,) slot of each edge's target
    slot_var: torch.Tensor  # (ns, S) variable index of each slot (-1: fixed frame or padding)
    patches: torch.Tensor  # (Pc,) global patch indices owned by the chunk's source frames
    owner: torch.Tensor  # (Pc,) their source frame in [0, ns)
    rank: torch.Tensor  # (Pc,) their rank within it
    Kmax: int  # most patches of one source frame
    patch_local: torch.Tensor  # (n,) each edge's patch in [0, Pc)
    pair: torch.Tensor  # (n,) each edge's (source, target) pair in [0, Q)
    pair_rank: torch.Tensor  # (n,) its rank within the pair
    L: int  # most edges of one pair
    pair_src: torch.Tensor  # (Q,) source frame of each pair, in [0, ns)
    pair_slot: torch.Tensor  # (Q,) slot of its target


def _make_chunk(lo: int, hi: int, src: np.ndarray, tgt: np.ndarray, sidx: np.ndarray, F: int,
                variable_index: np.ndarray) -> _Chunk:
    s, t = src[lo:hi], tgt[lo:hi]
    pair = s * F + t
    upair, inv = np.unique(pair, return_inverse=True)
    p_src, p_tgt = upair // F, upair % F
    other = p_tgt != p_src
    cum = np.cumsum(other)
    first = np.searchsorted(p_src, p_src, side="left")
    before = np.where(first > 0, cum[np.maximum(first - 1, 0)], 0)  # non-self pairs of earlier sources
    p_slot = np.where(other, cum - before, 0)  # inclusive count within the source: 1, 2, ...
    srcs = np.unique(s)
    ns = len(srcs)
    S = int(p_slot.max()) + 1 if p_slot.size else 1
    slot_frame = np.full((ns, S), -1, np.int64)
    slot_frame[:, 0] = srcs
    slot_frame[np.searchsorted(srcs, p_src[other]), p_slot[other]] = p_tgt[other]
    slot_var = np.where(slot_frame >= 0, variable_index[np.maximum(slot_frame, 0)], -1)
    src_local = np.searchsorted(srcs, s)
    patches, patch_local = np.unique(sidx[lo:hi], return_inverse=True)
    owner = np.zeros(len(patches), np.int64)
    owner[patch_local] = src_local
    rank, kmax = _rank_in_groups(owner, ns)
    prank, lmax = _rank_in_groups(inv, len(upair))
    as_t = torch.as_tensor
    return _Chunk(lo, hi, ns, S, as_t(p_slot[inv]), as_t(slot_var), as_t(patches), as_t(owner), as_t(rank), kmax,
                  as_t(patch_local), as_t(inv), as_t(prank), lmax, as_t(np.searchsorted(srcs, p_src)), as_t(p_slot))


def _rank_in_groups(group: np.ndarray, num_groups: int) -> tuple[np.ndarray, int]:
    """Rank of each element within its group (in order of appearance) and the largest group size:
    the padded layout ``(num_groups, max size)`` of grouped elements."""
    order = np.argsort(group, kind="stable")
    counts = np.bincount(group, minlength=num_groups)
    starts = np.cumsum(counts) - counts
    rank = np.empty(len(group), np.int64)
    rank[order] = np.arange(len(group)) - starts[group[order]]
    return rank, int(counts.max()) if counts.size else 1


class _Problem:
    """Evaluation, linearisation and updates of one global BA problem (torch float64)."""

    def __init__(self, prob: GlobalBAProblem, cfg: GlobalBAConfig, reprojection: ReprojectionConfig):
        f64 = torch.float64
        self.cfg = cfg
        self.reprojection = reprojection
        fixed = np.asarray(prob.fixed, bool)
        F = len(fixed)
        self.var_frames = np.nonzero(~fixed)[0]
        variable_index = np.full(F, -1, np.int64)
        variable_index[self.var_frames] = np.arange(len(self.var_frames))
        self.V = len(self.var_frames)
        self.P = int(np.asarray(prob.inv_depth).shape[0])
        src = np.asarray(prob.src, np.int64)
        self.order = o = np.argsort(src, kind="stable")
        src_s, tgt_s, sidx_s = src[o], np.asarray(prob.tgt, np.int64)[o], np.asarray(prob.struct_idx, np.int64)[o]
        self.src, self.tgt = torch.as_tensor(src_s), torch.as_tensor(tgt_s)
        self.var_of_src = torch.as_tensor(variable_index[src_s])
        self.var_of_tgt = torch.as_tensor(variable_index[tgt_s])
        self.right = torch.as_tensor(np.asarray(prob.right, bool)[o])
        self.uv_src = torch.as_tensor(np.asarray(prob.uv_src, np.float64)[o])
        self.uv = torch.as_tensor(np.asarray(prob.uv, np.float64)[o])
        self.base_w = torch.as_tensor(np.asarray(prob.weight, np.float64)[o])
        self.sidx = torch.as_tensor(sidx_s)
        self.n = int(src_s.shape[0])
        # chunks of whole source frames, about cfg.chunk_edges edges each
        bounds = np.flatnonzero(np.diff(src_s)) + 1  # first edge of each source frame but the first
        cuts, lo = [], 0
        while lo < self.n:
            k = int(np.searchsorted(bounds, lo + self.cfg.chunk_edges))
            hi = int(bounds[k]) if k < len(bounds) else self.n
            cuts.append((lo, hi))
            lo = hi
        self.chunks = [_make_chunk(a, b, src_s, tgt_s, sidx_s, F, variable_index) for a, b in cuts]
        self.K = torch.as_tensor(np.asarray(prob.K, np.float64))
        self.K_right = None if prob.K_right is None else torch.as_tensor(np.asarray(prob.K_right, np.float64))
        self.T_CRCL = None if prob.T_CRCL is None else torch.as_tensor(np.asarray(prob.T_CRCL, np.float64))
        self.robust = torch.ones(self.n, dtype=f64)
        if prob.prior_idx is not None and len(prob.prior_idx):
            self.prior_idx = torch.as_tensor(np.asarray(prob.prior_idx, np.int64))
            self.prior_value = torch.as_tensor(np.asarray(prob.prior_value, np.float64))
            self.prior_w = torch.as_tensor(np.asarray(prob.prior_weight, np.float64))
        else:
            self.prior_idx = None
        self.timings = {"linearize": 0.0, "construct": 0.0, "solve": 0.0, "evaluate": 0.0}
        self.linearizations = 0
        self.ordering: list = []  # GTSAM's elimination ordering, computed once per problem (the LM loop's cache)

    # ---------------------------------------------------------------- evaluation
    def _project(self, T: torch.Tensor, d: torch.Tensor, lo: int, hi: int, jacobians: bool):
        """Residuals (n, 2), validity (n,) [and J_d (n, 2), J_i, J_j (n, 2, 6)] of edges lo:hi."""
        R, t, s = sim3_matrix_components(T)
        si, ti = self.src[lo:hi], self.tgt[lo:hi]
        uv_s, uv_o, de = self.uv_src[lo:hi], self.uv[lo:hi], d[self.sidx[lo:hi]]
        Ti, Tj = (R[si], t[si], s[si]), (R[ti], t[ti], s[ti])
        sides = dict(right=self.right[lo:hi], K_right=self.K_right, T_CRCL=self.T_CRCL, config=self.reprojection)
        if jacobians:
            res = reproject_edges(uv_s, de, Ti, Tj, self.K, uv_o, **sides)
            return res.residual, res.valid, res.J_d, res.J_Ti[..., :POSE_DOF], res.J_Tj[..., :POSE_DOF]
        uv, valid = reproject_edges(uv_s, de, Ti, Tj, self.K, **sides)
        return torch.where(valid[:, None], uv - uv_o, torch.zeros((), dtype=torch.float64)), valid, None, None, None

    def weights(self) -> torch.Tensor:
        return self.base_w * self.robust

    def cost(self, T: torch.Tensor, d: torch.Tensor, weights: torch.Tensor | None = None) -> float:
        """0.5 sum w |r|^2 (+ priors) with invalid projections at zero weight."""
        t0 = time.perf_counter()
        w_all = self.weights() if weights is None else weights
        total = 0.0
        for c in self.chunks:
            r, ok, *_ = self._project(T, d, c.lo, c.hi, jacobians=False)
            total += float((w_all[c.lo:c.hi] * ok * (r * r).sum(1)).sum())
        if self.prior_idx is not None:
            prior = depth_prior(d[self.prior_idx], self.prior_value, self.prior_w)
            total += float((prior.weight * prior.residual ** 2).sum())
        self.timings["evaluate"] += time.perf_counter() - t0
        return 0.5 * total

    def residual_norms(self, T: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(n,) residual norms and validity, sorted edge order."""
        norms, valid = torch.zeros(self.n, dtype=torch.float64), torch.zeros(self.n, dtype=torch.bool)
        for c in self.chunks:
            r, ok, *_ = self._project(T, d, c.lo, c.hi, jacobians=False)
            norms[c.lo:c.hi], valid[c.lo:c.hi] = torch.linalg.vector_norm(r, dim=1), ok
        return norms, valid

    # ---------------------------------------------------------------- linearisation
    def linearize(self, T: torch.Tensor, d: torch.Tensor) -> "_ReducedSystem":
        """Reduced system over the variable poses, one factor per source frame (each source
        frame's dense ``Hloc``, ``gloc`` over its slots, :meth:`_ReducedSystem.add_sources`); the
        model is ``dx^T H dx + 2 g^T dx + c`` (twice the cost). Keeps what back-substitution needs."""
        t0 = time.perf_counter()
        f64 = torch.float64
        D = POSE_DOF
        t_system = 0.0  # time spent building the GTSAM factors (timed apart as "construct")
        system = _ReducedSystem(self.V)
        w_all = self.weights()
        C = torch.zeros(self.P, dtype=f64)
        b = torch.zeros(self.P, dtype=f64)
        FE_i = torch.zeros(self.n, D, dtype=f64)  # per edge: E^T W J_src and E^T W J_tgt
        FE_j = torch.zeros(self.n, D, dtype=f64)
        prior_C = torch.zeros(self.P, dtype=f64)
        prior_b = torch.zeros(self.P, dtype=f64)
        if self.prior_idx is not None:
            prior = depth_prior(d[self.prior_idx], self.prior_value, self.prior_w)
            prior_C.index_add_(0, self.prior_idx, prior.weight * prior.J_d ** 2)
            prior_b.index_add_(0, self.prior_idx, prior.weight * prior.J_d * prior.residual)
        for c in self.chunks:
            lo, hi, S, ns = c.lo, c.hi, c.S, c.ns
            r, ok, Jd, Ji, Jj = self._project(T, d, lo, hi, jacobians=True)
            w = (w_all[lo:hi] * ok)[:, None]
            pl = c.patch_local
            # J^T W J and J^T W r per (source, target) pair: one batched product over padded pairs
            Q, L = int(c.pair_src.shape[0]), c.L
            sw = w.sqrt()[..., None]
            A = torch.zeros(Q, L, 2, 2 * D + 1, dtype=f64)
            A[c.pair, c.pair_rank] = torch.cat([sw * Ji, sw * Jj, sw * r[..., None]], 2)
            A = A.reshape(Q, 2 * L, 2 * D + 1)
            AtA = torch.bmm(A.transpose(1, 2), A)  # (Q, 13, 13)
            Hs = torch.zeros(ns * S * S, D, D, dtype=f64)
            base = c.pair_src * S * S
            ps = c.pair_slot
            Hij = AtA[:, :D, D:2 * D]
            Hs.index_add_(0, base, AtA[:, :D, :D])
            Hs.index_add_(0, base + ps, Hij)
            Hs.index_add_(0, base + ps * S, Hij.transpose(1, 2))
            Hs.index_add_(0, base + ps * S + ps, AtA[:, D:2 * D, D:2 * D])
            gs = torch.zeros(ns * S, D, dtype=f64)
            gs.index_add_(0, c.pair_src * S, AtA[:, :D, -1])
            gs.index_add_(0, c.pair_src * S + ps, AtA[:, D:2 * D, -1])
            wE = w * Jd
            Pc = int(c.patches.shape[0])
            Cc = torch.zeros(Pc, dtype=f64).index_add_(0, pl, (wE * Jd).sum(1)) + prior_C[c.patches]
            bc = torch.zeros(Pc, dtype=f64).index_add_(0, pl, (wE * r).sum(1)) + prior_b[c.patches]
            C[c.patches], b[c.patches] = Cc, bc
            fi = wE[:, 0, None] * Ji[:, 0] + wE[:, 1, None] * Ji[:, 1]
            fj = wE[:, 0, None] * Jj[:, 0] + wE[:, 1, None] * Jj[:, 1]
            FE_i[lo:hi], FE_j[lo:hi] = fi, fj
            Fp = torch.zeros(Pc * S, D, dtype=f64)
            Fp.index_add_(0, pl * S, fi)
            Fp.index_add_(0, pl * S + c.slot_tgt, fj)
            # per source frame: its patches' structure eliminated from its slots' block (one batch)
            Fpad = torch.zeros(ns, c.Kmax, S * D, dtype=f64)
            Fpad[c.owner, c.rank] = Fp.reshape(Pc, S * D)
            Cpad = torch.zeros(ns, c.Kmax, dtype=f64)  # padding: no information, left out
            Cpad[c.owner, c.rank] = Cc
            bpad = torch.zeros(ns, c.Kmax, dtype=f64)
            bpad[c.owner, c.rank] = bc
            Hloc = Hs.reshape(ns, S, S, D, D).permute(0, 1, 3, 2, 4).reshape(ns, S * D, S * D)
            reduced = eliminate_structure(Hloc, gs.reshape(ns, S * D), 0.0, Fpad, bpad, Cpad, self.cfg.min_information)
            t1 = time.perf_counter()
            system.add_sources(c.slot_var, reduced.H, reduced.g)
            t_system += time.perf_counter() - t1
        inv_C = information_inverse(C, self.cfg.min_information)
        self._back = (FE_i, FE_j, inv_C, b)
        self.timings["construct"] += t_system
        self.linearizations += 1
        self.timings["linearize"] += time.perf_counter() - t0 - t_system
        return system

    def back_substitute(self, dx: torch.Tensor) -> torch.Tensor:
        """Inverse-depth update (P,) for the pose update ``dx`` (V, 6) at the last linearisation:
        ``dd_p = -(b_p + sum_e FE_e dx) / C_p``."""
        FE_i, FE_j, inv_C, b = self._back
        dx_pad = torch.cat([dx, torch.zeros(1, POSE_DOF, dtype=dx.dtype)])  # index -1: fixed, zero
        contrib = (FE_i * dx_pad[self.var_of_src]).sum(1) + (FE_j * dx_pad[self.var_of_tgt]).sum(1)
        Fdx = torch.zeros(self.P, dtype=torch.float64).index_add_(0, self.sidx, contrib)
        return -inv_C * (b + Fdx)


class _ReducedSystem:
    """The reduced camera system ``H dx = -g`` over the V variable poses (gtsam key = variable
    index) as one ``gtsam.HessianFactor`` per source frame over the keys of its variable slots,
    built from the source's compressed Jacobian (:func:`fgslam.factors.schur.to_gaussian_factor`)
    in a ``gtsam.GaussianFactorGraph``, and the diagonal of H (Marquardt damping).

    :meth:`add_sources` receives one chunk: ``slot_var`` (ns, S) variable index of each slot (-1:
    fixed frame or padding, dropped), ``Hloc`` (ns, 6S, 6S), ``gloc`` (ns, 6S)."""

    def __init__(self, V: int):
        import gtsam  # deferred: gtsam

        self.V = V
        self.graph = gtsam.GaussianFactorGraph()
        self.diag = torch.zeros(V + 1, POSE_DOF, dtype=torch.float64)  # row V: fixed / padding

    def add_sources(self, slot_var: torch.Tensor, Hloc: torch.Tensor, gloc: torch.Tensor) -> None:
        """Add one chunk of source frames (class docstring)."""
        D = POSE_DOF
        ns, S = slot_var.shape
        rows = torch.where(slot_var >= 0, slot_var, self.V).reshape(-1)
        self.diag.index_add_(0, rows, torch.diagonal(Hloc, dim1=1, dim2=2).reshape(ns * S, D))
        sv, H, g = slot_var.numpy(), Hloc.numpy(), gloc.numpy()
        for i in range(ns):
            slots = np.flatnonzero(sv[i] >= 0)
            k = len(slots)
            if k == 0:
                continue
            if slots[-1] == k - 1:  # variable slots lead (dropped ones are padding): no gather
                H_i, g_i = H[i, :D * k, :D * k], g[i, :D * k]
            else:
                idx = (slots[:, None] * D + np.arange(D)).reshape(-1)
                H_i, g_i = H[i][np.ix_(idx, idx)], g[i, idx]
            self.graph.push_back(to_gaussian_factor(sv[i, slots].tolist(), H_i, g_i, None, dim=D))

    def hessian_diagonal(self) -> dict[int, np.ndarray]:
        """``{key: diag(H) of its 6 rows}`` (the LM loop's Marquardt damping)."""
        diag = self.diag[: self.V].numpy()
        return dict(enumerate(diag))

    def dense(self) -> tuple[np.ndarray, np.ndarray]:
        """(H (6V, 6V), g (6V,)) as dense arrays (small problems, tests)."""
        import gtsam  # deferred: gtsam

        ordering = gtsam.Ordering()
        for key in range(self.V):
            ordering.push_back(key)
        H, eta = self.graph.hessian(ordering)
        return np.asarray(H), -np.asarray(eta)  # gtsam's information vector is -g


class _LMProblem:
    """The global BA as a problem of the backend's LM loop: state ``(T (F, 4, 4), d (P,))``; a step
    ``delta`` (keys 0..V-1, 6 each) retracts the variable poses and back-substitutes the depths."""

    def __init__(self, prob: _Problem, T: torch.Tensor, d: torch.Tensor):
        self.prob, self.T, self.d = prob, T, d
        self.system: _ReducedSystem | None = None

    def cost(self) -> float:
        return self.prob.cost(self.T, self.d)

    def linearize(self):
        self.system = None  # freed before the next linearisation builds its own (peak memory)
        self.system = self.prob.linearize(self.T, self.d)
        return self.system.graph

    def hessian_diagonal(self) -> dict[int, np.ndarray]:
        return self.system.hessian_diagonal()

    def trial(self, delta) -> tuple[float, object]:
        prob = self.prob
        dx = torch.as_tensor(np.asarray(delta.vector())).reshape(prob.V, POSE_DOF)  # keys 0..V-1 in order
        T_new = _retract(self.T, prob.var_frames, dx)
        d_new = (self.d + prob.back_substitute(dx)).clamp_min(prob.cfg.min_structure)
        new_cost = prob.cost(T_new, d_new) if bool(torch.isfinite(d_new).all()) else float("inf")
        return new_cost, (T_new, d_new)

    def accept(self, state, cost: float) -> float:
        self.T, self.d = state
        return cost


def _retract(T: torch.Tensor, frames: np.ndarray, dx: torch.Tensor) -> torch.Tensor:
    """``T_f <- T_f Exp([w, u, 0])`` for the given frames."""
    out = T.clone()
    if len(frames) == 0:
        return out
    xi = torch.cat([dx, torch.zeros(dx.shape[0], 1, dtype=dx.dtype)], 1)
    idx = torch.as_tensor(frames)
    out[idx] = T[idx] @ Sim3.exp(xi).matrix()
    return out


def global_bundle_adjustment(problem: GlobalBAProblem, config: GlobalBAConfig | None = None,
                             reprojection: ReprojectionConfig | None = None) -> GlobalBAResult:
    """Optimise every non-fixed pose (held scale) and every patch inverse depth (module docstring).

    Raises :class:`~fgslam.core.errors.OptimizationError` on inconsistent input; never returns NaN (a
    step that produces non-finite values is rejected like one that raises the cost).
    """
    cfg = config or GlobalBAConfig()
    cfg.validate()
    problem.check()
    start = time.perf_counter()
    reprojection = reprojection or ReprojectionConfig()
    with torch_threads(cfg.threads if cfg.threads > 0 else (os.cpu_count() or 1)):
        prob = _Problem(problem, cfg, reprojection)
        T = torch.as_tensor(np.asarray(problem.T_WC, np.float64)).clone()
        d = torch.as_tensor(np.asarray(problem.inv_depth, np.float64)).clone().clamp_min(cfg.min_structure)
        initial_cost = prob.cost(T, d, prob.base_w)
        steps = 0
        settings = LMSettings(max_iterations=cfg.iterations, lambda_initial=cfg.lambda_initial,
                              lambda_factor=cfg.lambda_factor, lambda_max=cfg.lambda_max,
                              relative_tolerance=cfg.relative_tolerance, damping="marquardt", ordering="metis")
        for round_ in range(cfg.robust_rounds):
            if round_ > 0 or cfg.huber_first_round:
                prob.robust = _robust_weights(prob, T, d, cfg, cut=round_ > 0)
            if prob.V == 0 or prob.n == 0:
                continue
            lm = _LMProblem(prob, T, d)
            report = levenberg_marquardt(lm, settings, ordering_cache=prob.ordering)
            lm.system = None
            T, d = lm.T, lm.d
            steps += report.solves
            prob.timings["solve"] += report.timings["solve"]
        norms, valid = prob.residual_norms(T, d)
        final_robust = prob.robust if cfg.robust_rounds > 1 else _robust_weights(prob, T, d, cfg)
        inlier = final_robust > 0
        final_cost = prob.cost(T, d, prob.base_w * inlier)
    # back to the caller's edge order
    inv_order = np.empty(prob.n, np.int64)
    inv_order[prob.order] = np.arange(prob.n)
    residual = torch.where(valid, norms, torch.full_like(norms, float("inf"))).numpy()[inv_order]
    seconds = time.perf_counter() - start
    logger.info("global BA: %d poses, %d patches, %d edges: cost %.4g -> %.4g in %d steps (%.2f s)",
                prob.V, int((torch.bincount(prob.sidx, minlength=prob.P) > 0).sum()), prob.n, initial_cost, final_cost, steps, seconds)
    return GlobalBAResult(T_WC=T.numpy(), inv_depth=d.numpy(), robust=final_robust.numpy()[inv_order],
                          residual=residual, initial_cost=initial_cost, final_cost=final_cost, iterations=steps,
                          seconds=seconds, num_edges=prob.n, num_variables=prob.V, timings=dict(prob.timings),
                          linearizations=prob.linearizations)


def _robust_weights(prob: _Problem, T: torch.Tensor, d: torch.Tensor, cfg: GlobalBAConfig,
                    cut: bool = True) -> torch.Tensor:
    """Huber weights of the whitened residuals; zero when invalid and (``cut``) above the outlier
    threshold."""
    norms, valid = prob.residual_norms(T, d)
    white = prob.base_w.sqrt() * norms
    w = kernel_weight(white, "huber", cfg.huber_delta)
    keep = valid & (norms <= cfg.outlier_threshold) if cut else valid
    return torch.where(keep, w, torch.zeros_like(w))
