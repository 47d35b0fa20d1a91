"""The patch graph's visual block: inverse-depth patch reprojections (left and right images) and
RGB-D depth priors, Schur-reduced in one vectorised pass (no Python loop over edges or frame pairs).

Measurements of :class:`PatchBlock`:

- edge ``n`` (DPV-SLAM eq. 3, patch centre): source pixel ``uv_src[n]`` of frame ``src[n]`` with the
  inverse depth ``structure[struct_idx[n]]`` of its patch, observed at ``uv_tgt[n]`` in frame
  ``tgt[n]``'s left image, or, when ``right[n]``, in its right image through the fixed metric
  extrinsic ``T_CRCL`` (``fgslam.factors.reprojection``'s ``T_CtCj``); residual
  ``pi(T_WCtgt^-1 T_WCsrc X) - uv_tgt`` in pixels (2 rows), weighted by ``weights[n]``;
- depth prior ``m`` (RGB-D): ``d - 1 / z_sensor`` (first row; the second has zero weight).

Frames are *local frame indices* ``0 .. F-1``: the first ``k`` are the block's pose slots (gtsam keys
``keys``, Sim(3) T_WC, tangent ``[w, u, lambda]``, right perturbation); the others are fixed poses
held by the block (frames outside the optimisation window): they enter residuals but get no Jacobian.

Layout: edges are stored grouped by (source frame, target frame, right) and padded to a common
length ``L`` (``Q`` groups), so pose-pair quantities are computed once per group and ``J^T W J`` is
one batched matrix product; padding rows have zero weight. Left-image groups come first, so
:func:`~fgslam.factors.reprojection.reproject_edges` evaluates each image side on a contiguous
slice. Depth priors go through :func:`fgslam.factors.depth.depth_prior`. The row order seen by the
:class:`~fgslam.factors.visual_block.VisualBlock` machinery is the ``Q * L`` padded edge rows followed by
the priors. The reduction is exactly :func:`fgslam.factors.schur.schur_reduce`'s (same
``SchurSystem`` for back-substitution).
"""

from __future__ import annotations

import numpy as np
import torch

from ...factors.blocks import LinearPiece
from ...core.errors import OptimizationError
from ...factors.depth import depth_prior
from ...factors.reprojection import ReprojectionConfig, reproject_edges
from ...factors.schur import POSE_DIM, SlotGroups, eliminate_structure, torch_threads
from ...factors.visual_block import BlockConfig, BlockResiduals, VisualBlock
from ...core.lie import Sim3


class PatchBlock(VisualBlock):
    """Patch edges (+ optional right-image edges and depth priors) over variable and fixed frames.

    Args:
        keys: gtsam keys of the k variable frames (local frames ``0 .. k-1``).
        fixed_R, fixed_t, fixed_s: (F-k, 3, 3), (F-k, 3), (F-k,) fixed T_WC of local frames ``k .. F-1``.
        src, tgt: (N,) local frame of each edge's source and target.
        right: (N,) bool, target is the right image (needs ``K_right`` and ``T_CRCL``).
        uv_src, uv_tgt: (N, 2) patch centre in the source and observed pixel in the target.
        weights: (N,) non-negative weights (confidence / sigma^2 times robust weight), or (N, 2): one
            per residual row (u, v).
        struct_idx: (N,) patch of each edge in ``[0, P)``.
        K: (4,) left intrinsics; ``K_right`` (4,) right intrinsics; ``T_CRCL`` (4, 4) left-to-right.
        inverse_depth: (P,) initial inverse depths.
        prior_idx, prior_value, prior_weight: (M,) depth priors ``d[prior_idx] ~ prior_value``.
    """

    def __init__(
        self, keys, fixed_R, fixed_t, fixed_s, src, tgt, right, uv_src, uv_tgt, weights, struct_idx,
        K, inverse_depth, K_right=None, T_CRCL=None, prior_idx=None, prior_value=None, prior_weight=None,
        config: BlockConfig | None = None, reprojection: ReprojectionConfig | None = None,
    ):
        super().__init__()
        f64 = torch.float64
        self.keys = tuple(int(k) for k in keys)
        self.config = config or BlockConfig()
        self.reprojection = reprojection or ReprojectionConfig()
        k = len(self.keys)
        self.fixed_R = torch.as_tensor(fixed_R, dtype=f64).reshape(-1, 3, 3)
        self.fixed_t = torch.as_tensor(fixed_t, dtype=f64).reshape(-1, 3)
        self.fixed_s = torch.as_tensor(fixed_s, dtype=f64).reshape(-1)
        num_frames = k + int(self.fixed_s.shape[0])
        # the index bookkeeping in numpy (small arrays: torch's per-call overhead dominated), tensors at the end
        src = np.asarray(src, dtype=np.int64).reshape(-1)
        tgt = np.asarray(tgt, dtype=np.int64).reshape(-1)
        right = np.asarray(right, dtype=bool).reshape(-1)
        n = int(src.shape[0])
        self.num_edges = n
        if right.any() and (K_right is None or T_CRCL is None):
            raise OptimizationError("PatchBlock: right-image edges need K_right and T_CRCL")
        if n and (int(src.max()) >= num_frames or int(tgt.max()) >= num_frames or int(min(src.min(), tgt.min())) < 0):
            raise OptimizationError(f"PatchBlock: edge frames must lie in [0, {num_frames})")
        self.K = torch.as_tensor(K, dtype=f64)
        self.K_right = None if K_right is None else torch.as_tensor(K_right, dtype=f64)
        self.T_CRCL = None if T_CRCL is None else torch.as_tensor(np.asarray(T_CRCL), dtype=f64)

        # --- group edges by (src, tgt, right), pad to length L
        key = right.astype(np.int64) * (num_frames * num_frames) + src * num_frames + tgt
        order = np.argsort(key, kind="stable")
        uniq, counts = np.unique(key[order], return_counts=True)  # sorted keys: their runs
        q = int(uniq.shape[0])
        L = int(counts.max()) if q else 0
        starts = np.cumsum(counts) - counts
        rank = np.arange(n) - np.repeat(starts, counts)
        group = np.repeat(np.arange(q), counts)
        self.num_groups, self.length = q, L
        nf = max(num_frames, 1)
        g_src, g_tgt = (uniq % (nf * nf)) // nf, uniq % nf
        self.g_right = torch.from_numpy(uniq >= nf * nf)
        self.g_src, self.g_tgt = torch.from_numpy(g_src), torch.from_numpy(g_tgt)
        pad = np.asarray(K, dtype=np.float64)[2:4]
        uv_src_p = np.broadcast_to(pad, (q, L, 2)).copy()
        uv_tgt_p = np.broadcast_to(pad, (q, L, 2)).copy()
        uv_src_p[group, rank] = np.asarray(uv_src, dtype=np.float64).reshape(n, 2)[order]
        uv_tgt_p[group, rank] = np.asarray(uv_tgt, dtype=np.float64).reshape(n, 2)[order]
        self.uv_src, self.uv_tgt = torch.from_numpy(uv_src_p), torch.from_numpy(uv_tgt_p)
        edge_w = np.zeros((q, L, 2))
        w_in = np.asarray(weights, dtype=np.float64)
        edge_w[group, rank] = (np.broadcast_to(w_in[:, None], (n, 2)) if w_in.ndim == 1 else w_in)[order]
        edge_idx = np.zeros((q, L), dtype=np.int64)
        edge_idx[group, rank] = np.asarray(struct_idx, dtype=np.int64).reshape(-1)[order]
        row_of_edge = np.empty(n, dtype=np.int64)  # caller's edge n -> padded row
        row_of_edge[order] = group * L + rank
        self._row_of_edge = torch.from_numpy(row_of_edge)

        # --- priors
        if prior_idx is None:
            prior_idx, prior_value, prior_weight = np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
        self.prior_value = torch.as_tensor(prior_value, dtype=f64).reshape(-1)
        prior_idx = np.asarray(prior_idx, dtype=np.int64).reshape(-1)
        m = int(prior_idx.shape[0])
        prior_rows = np.zeros((m, 2))
        prior_rows[:, 0] = np.asarray(prior_weight, dtype=np.float64).reshape(-1)
        weights_all = np.concatenate([edge_w.reshape(-1, 2), prior_rows])
        if (weights_all < 0).any() or not np.isfinite(weights_all).all():
            raise OptimizationError("PatchBlock: weights must be finite and non-negative")
        self.weights = torch.from_numpy(weights_all)
        self.struct_idx = torch.from_numpy(np.concatenate([edge_idx.reshape(-1), prior_idx]))
        # pose slots (fixed frames and priors: the dummy slot k, cropped away)
        g_a, g_b = np.where(g_src < k, g_src, k), np.where(g_tgt < k, g_tgt, k)
        self.g_a, self.g_b = torch.from_numpy(g_a), torch.from_numpy(g_b)
        dummy = np.full(m, k, dtype=np.int64)
        self.slots = torch.from_numpy(np.stack([np.concatenate([np.repeat(g_a, L), dummy]),
                                                np.concatenate([np.repeat(g_b, L), dummy])], 1))
        self.groups = SlotGroups((0, q * L + m), ((k, k),))  # unused: linearize() has its own grouping
        self._structure = torch.zeros(0, dtype=f64)
        self.set_structure(torch.as_tensor(inverse_depth, dtype=f64))
        self.num_invalid = 0
        self._valid = torch.ones(q * L + m, dtype=torch.bool)
        self._memo = None  # (R, t, s, structure, BlockResiduals, valid, has Jacobians) of the last evaluation

    @property
    def structure(self) -> torch.Tensor:
        return self._structure

    def clamp_structure(self, structure: torch.Tensor) -> torch.Tensor:
        """Inverse depths clamped to ``config.min_structure`` (the solver's trial cost then sees the
        structure it would adopt)."""
        return structure.to(torch.float64).clamp_min(self.config.min_structure)

    def set_structure(self, structure: torch.Tensor) -> None:
        self._structure = self.clamp_structure(structure)

    def poses_from_values(self, values) -> Sim3:
        if not self.keys:
            return Sim3.identity((0,))
        return super().poses_from_values(values)

    def _all_poses(self, poses: Sim3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        R = torch.cat([poses.R.reshape(-1, 3, 3), self.fixed_R])
        t = torch.cat([poses.t.reshape(-1, 3), self.fixed_t])
        s = torch.cat([poses.s.reshape(-1), self.fixed_s])
        return R, t, s

    def evaluate(self, poses: Sim3, structure: torch.Tensor, jacobians: bool) -> BlockResiduals:
        """Residuals (see :class:`VisualBlock`) through a one-entry memo of the last evaluation.

        The solver asks for the same state more than once: the initial cost and then the first
        linearisation (so a fresh block's first evaluation includes the Jacobians), and the last
        accepted trial's cost and then :meth:`residuals`. A request at the memo's poses and
        structure is answered from it (a residual-only request also from a Jacobian evaluation).
        """
        R, t, s = self._all_poses(poses)
        structure = structure.to(torch.float64)
        memo = self._memo
        if memo is None:
            jacobians = True
        elif ((memo[6] or not jacobians) and torch.equal(memo[3], structure) and torch.equal(memo[0], R)
                and torch.equal(memo[1], t) and torch.equal(memo[2], s)):
            self._valid, self.num_invalid = memo[5], memo[4].num_invalid
            return memo[4]
        out = self._evaluate(R, t, s, structure, jacobians)
        self._memo = (R, t, s, structure.clone(), out, self._valid, jacobians)
        return out

    def _evaluate(self, R: torch.Tensor, t: torch.Tensor, s: torch.Tensor, structure: torch.Tensor,
                  jacobians: bool) -> BlockResiduals:
        f64 = torch.float64
        q, L = self.num_groups, self.length
        m = int(self.prior_value.shape[0])
        d_edge = structure[self.struct_idx[: q * L]].reshape(q, L)
        si, ti = self.g_src, self.g_tgt
        T_i = (R[si][:, None], t[si][:, None], s[si][:, None])
        T_j = (R[ti][:, None], t[ti][:, None], s[ti][:, None])
        sides = dict(right=self.g_right, K_right=self.K_right, T_CRCL=self.T_CRCL, config=self.reprojection)
        if jacobians:
            res = reproject_edges(self.uv_src, d_edge, T_i, T_j, self.K, self.uv_tgt, **sides)
            r_e, valid_e = res.residual.reshape(-1, 2), res.valid.reshape(-1)
        else:
            uv, ok = reproject_edges(self.uv_src, d_edge, T_i, T_j, self.K, **sides)
            r_e = torch.where(ok[..., None], uv - self.uv_tgt, torch.zeros((), dtype=f64)).reshape(-1, 2)
            valid_e = ok.reshape(-1)
        # depth priors: first row d - d_sensor (weighted at construction), second row unused
        prior = depth_prior(structure[self.struct_idx[q * L:]], self.prior_value, self.weights[q * L:, 0])
        r_p = torch.zeros(m, 2, dtype=f64)
        r_p[:, 0] = prior.residual
        r = torch.cat([r_e, r_p])
        valid = torch.cat([valid_e, prior.valid])
        self.num_invalid = int((~valid_e & (self.weights[: q * L, 0] > 0)).sum())
        self._valid = valid
        weights = torch.where(valid[:, None], self.weights, torch.zeros((), dtype=f64))
        if not jacobians:
            return BlockResiduals(r=r, weights=weights, num_invalid=self.num_invalid)
        E_p = torch.zeros(m, 2, dtype=f64)
        E_p[:, 0] = prior.J_d
        E = torch.cat([res.J_d.reshape(-1, 2), E_p])
        # Pose Jacobians of the edge rows w.r.t. source and target, each (q, L, 2, 7), kept on the
        # block for linearize() (prior rows have none); BlockResiduals.J stays None.
        self._J_src, self._J_tgt = res.J_Ti, res.J_Tj
        return BlockResiduals(r=r, weights=weights, E=E, J=None, num_invalid=self.num_invalid)

    def residuals(self, values) -> tuple[torch.Tensor, torch.Tensor]:
        """Edge residuals (N, 2) and geometric validity (N,) at ``values``, in the caller's edge order."""
        with torch_threads(self.config.threads):
            res = self.evaluate(self.poses_from_values(values), self.structure, jacobians=False)
        rows = self._row_of_edge
        return res.r[rows], self._valid[rows]

    def linearize(self, values) -> list[LinearPiece]:
        """Schur-reduced ``[LinearPiece(keys, H, g, c)]`` as in :meth:`VisualBlock.linearize`, batched over groups."""
        f64 = torch.float64
        k = len(self.keys)
        kk = k + 1
        d = POSE_DIM
        q, L = self.num_groups, self.length
        with torch_threads(self.config.threads):
            res = self.evaluate(self.poses_from_values(values), self.structure, jacobians=True)
            W, r, E = res.weights, res.r, res.E
            ne = q * L
            # whitened pose Jacobians of the edge rows, fixed frames' columns zeroed: (q, L, 2, 7) each
            sqrt_w = W.sqrt()
            sw = sqrt_w[:ne].reshape(q, L, 2)
            X_i = (sw * (self.g_a < k).to(f64)[:, None, None])[..., None] * self._J_src
            X_j = (sw * (self.g_b < k).to(f64)[:, None, None])[..., None] * self._J_tgt
            Xi, Xj = X_i.reshape(q, 2 * L, d), X_j.reshape(q, 2 * L, d)
            Xit = Xi.transpose(1, 2)
            H_ii, H_ij, H_jj = torch.bmm(Xit, Xi), torch.bmm(Xit, Xj), torch.bmm(Xj.transpose(1, 2), Xj)
            pa, pb = self.g_a, self.g_b
            Hb = torch.zeros(kk * kk, d, d, dtype=f64)
            Hb.index_add_(0, pa * kk + pa, H_ii)
            Hb.index_add_(0, pa * kk + pb, H_ij)
            Hb.index_add_(0, pb * kk + pa, H_ij.transpose(1, 2))
            Hb.index_add_(0, pb * kk + pb, H_jj)
            H = Hb.reshape(kk, kk, d, d).permute(0, 2, 1, 3).reshape(kk * d, kk * d)[: k * d, : k * d]
            sr = sqrt_w * r
            sr_e = sr[:ne].reshape(q, 1, 2 * L)
            g = torch.zeros(kk, d, dtype=f64)
            g.index_add_(0, pa, torch.bmm(sr_e, Xi).reshape(q, d))
            g.index_add_(0, pb, torch.bmm(sr_e, Xj).reshape(q, d))
            g = g.reshape(-1)[: k * d]
            c = float((sr * sr).sum())
            P = self.num_structs
            idx = self.struct_idx
            se = sqrt_w * E
            C = torch.zeros(P, dtype=f64).index_add_(0, idx, (se * se).sum(1)) + self.config.structure_damping
            bvec = torch.zeros(P, dtype=f64).index_add_(0, idx, (se * sr).sum(1))
            se0, se1 = se[:ne, 0].reshape(q, L, 1), se[:ne, 1].reshape(q, L, 1)
            FE_i = (se0 * X_i[:, :, 0] + se1 * X_i[:, :, 1]).reshape(ne, d)
            FE_j = (se0 * X_j[:, :, 0] + se1 * X_j[:, :, 1]).reshape(ne, d)
            row_a, row_b = self.slots[:ne, 0], self.slots[:ne, 1]
            F = torch.zeros(P * kk, d, dtype=f64)
            F.index_add_(0, idx[:ne] * kk + row_a, FE_i)
            F.index_add_(0, idx[:ne] * kk + row_b, FE_j)
            F = F.reshape(P, kk * d)[:, : k * d]
            self._system = eliminate_structure(H, g, c, F, bvec, C, self.config.min_information)
        return [LinearPiece(self.keys, self._system.H.numpy(), self._system.g.numpy(), self._system.c)]
