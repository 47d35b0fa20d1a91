"""Visual blocks: measurements on a few keyframe poses with their own scalar structure, eliminated
when linearised (:func:`fgslam.factors.schur.schur_reduce`; docs/architecture.md section 5).

A :class:`VisualBlock` owns measurements and structure and offers ``linearize(values) ->
[LinearPiece(keys, H, g, c)]`` (:class:`fgslam.factors.blocks.Block`), ``back_substitute(delta)``, ``cost(values)`` and ``refine_structure(values)``
(``values``: a ``gtsam.Values`` of Similarity3 T_WC). :class:`InverseDepthBlock` implements it with
``fgslam.factors.reprojection``; a frontend builds one block per source keyframe (its inverse-depth
map or patches, with all outgoing edges) and hands it to ``fgslam.backend.Backend.set_blocks``::

    block = InverseDepthBlock(keys=[pose_key(i), pose_key(j1), pose_key(j2)],
                              source_slot=zeros, target_slot=slot_of_each_row, uv_source=uv_i,
                              uv_target=uv_i_reprojected_plus_flow, struct_idx=pixel_or_patch_id,
                              weights=confidences, K=K, inverse_depth=d_i)
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..core.config import MAX_ITERATIONS, MAX_LAMBDA, MAX_SCALAR, MAX_THREADS, ranged
from ..core.errors import OptimizationError
from ..core.lie import Sim3
from .blocks import LinearPiece
from .reprojection import ReprojectionConfig, reproject, reproject_inv_depth
from .schur import SchurSystem, SlotGroups, per_structure_cost, schur_reduce, structure_gauss_newton_step, torch_threads

logger = logging.getLogger(__name__)


@dataclass
class BlockResiduals:
    """Weighted residuals of a block at given poses/structure (shapes as in :func:`schur_reduce`).

    ``J`` is a list of S pose-Jacobian columns (N, m, 7) (see :func:`schur_reduce`); ``E`` and
    ``J`` are None when Jacobians were not requested; ``num_invalid`` counts measurements that
    got zero weight because they are degenerate (behind a camera, non-finite...).
    """

    r: torch.Tensor
    weights: torch.Tensor
    E: torch.Tensor | None = None
    J: list[torch.Tensor] | None = None
    num_invalid: int = 0


@dataclass
class BlockConfig:
    """Tunables shared by visual blocks."""

    structure_damping: float = ranged(0.0, ge=0, le=MAX_LAMBDA)  # lambda_s added to each structure's information C_p
    min_information: float = ranged(1e-12, ge=0, le=MAX_SCALAR)  # structures with C_p at or below this are not eliminated
    refine_steps: int = ranged(2, ge=0, le=MAX_ITERATIONS)  # per-structure Gauss-Newton steps of refine_structure() at fixed poses
    min_structure: float = ranged(1e-6, gt=0, le=MAX_SCALAR)  # lower clamp of the structure (inverse depth stays positive)
    threads: int = ranged(1, ge=0, le=MAX_THREADS)  # torch threads inside linearize/cost/refine (small dense work: 1 is fastest)


class VisualBlock(abc.ABC):
    """Measurements on ``k`` pose keys with their own scalar structure, eliminated when linearised.

    Subclasses implement :meth:`evaluate`; rows must be stored grouped by pose-slot tuple
    (``self.slots`` sorted, ``self.groups`` set) so that linearisation needs no sort.
    The block's state is its structure (P,) (float64 torch tensor).
    """

    keys: tuple[int, ...]
    has_structure = True  # fgslam.factors.blocks.Block: the structure is eliminated in linearize()
    slots: torch.Tensor  # (N, S) pose slots of each measurement
    struct_idx: torch.Tensor  # (N,) structure of each measurement
    groups: SlotGroups
    config: BlockConfig

    def __init__(self) -> None:
        self._system: SchurSystem | None = None
        self._damped: SchurSystem | None = None  # the last linearisation with the backend's structure damping

    # --- to implement
    @abc.abstractmethod
    def evaluate(self, poses: Sim3, structure: torch.Tensor, jacobians: bool) -> BlockResiduals:
        """Residuals (N, m) and weights (N, m) at ``poses`` (k,) (T_WC of the block's keys) and
        ``structure`` (P,); with ``jacobians`` also E (N, m) and pose Jacobians J (S tensors (N, m, 7))."""

    @property
    @abc.abstractmethod
    def structure(self) -> torch.Tensor:
        """Current structure (P,)."""

    @abc.abstractmethod
    def set_structure(self, structure: torch.Tensor) -> None:
        """Replace the structure (projected by :meth:`clamp_structure`)."""

    def clamp_structure(self, structure: torch.Tensor) -> torch.Tensor:
        """Project a structure onto its valid domain (default: unchanged)."""
        return structure

    # --- generic machinery
    @property
    def num_structs(self) -> int:
        return int(self.structure.shape[0])

    def poses_from_values(self, values) -> Sim3:
        """The block's poses (k,) from a ``gtsam.Values`` holding Similarity3 at ``self.keys``."""
        return Sim3.from_gtsam([values.atSimilarity3(key) for key in self.keys])

    def linearize(self, values) -> list[LinearPiece]:
        """``[LinearPiece(keys, H, g, c)]``: the Schur-reduced system at ``values`` and the current
        structure; the reduced GTSAM-convention cost model is ``0.5 (dx^T H dx + 2 g^T dx + c)``."""
        with torch_threads(self.config.threads):
            res = self.evaluate(self.poses_from_values(values), self.structure, jacobians=True)
            self._system = schur_reduce(
                res.r, res.J, self.slots, res.E, self.struct_idx, res.weights, len(self.keys),
                self.num_structs, self.linearize_damping(), self.groups, self.config.min_information,
            )
            self._damped = None
        return self._pieces()

    def linearize_damping(self) -> float | torch.Tensor:
        """What :meth:`linearize` adds to every structure's information: ``config.structure_damping``
        (a subclass may give one value per structure)."""
        return self.config.structure_damping

    def _pieces(self, sys_: SchurSystem | None = None) -> list[LinearPiece]:
        sys_ = self._system if sys_ is None else sys_
        return [LinearPiece(self.keys, sys_.H.numpy(), sys_.g.numpy(), float(sys_.c))]

    def linearize_damped(self, lam: float) -> list[LinearPiece]:
        """The last linearisation's pieces with ``lam`` added to every structure's information
        (:meth:`fgslam.factors.schur.SchurSystem.damped`: the backend's LM damping of the structure);
        :meth:`back_substitute` follows the damped system until :meth:`clear_damping` or the next
        :meth:`linearize`."""
        if self._system is None:
            raise OptimizationError("linearize_damped() called before linearize()")
        with torch_threads(self.config.threads):
            self._damped = self._system.damped(lam)
        return self._pieces(self._damped)

    def clear_damping(self) -> None:
        """Back to the last linearisation's own system (the optimisation that damped it has ended)."""
        self._damped = None

    def back_substitute(self, delta) -> torch.Tensor:
        """Structure update (P,) for the pose update ``delta`` (gtsam.VectorValues or (7k,) array)
        at the last linearisation point (through its damped system while the backend damps it)."""
        if self._system is None:
            raise OptimizationError("back_substitute() called before linearize()")
        if not isinstance(delta, (np.ndarray, torch.Tensor)):
            delta = np.concatenate([delta.at(key) for key in self.keys])
        system = self._system if self._damped is None else self._damped
        return system.back_substitute(torch.as_tensor(np.asarray(delta), dtype=torch.float64))

    def cost(self, values, structure: torch.Tensor | None = None) -> float:
        """GTSAM-convention cost ``0.5 sum w r^2`` at ``values`` and ``structure`` (default: current)."""
        structure = self.structure if structure is None else structure
        with torch_threads(self.config.threads):
            res = self.evaluate(self.poses_from_values(values), structure, jacobians=False)
            return 0.5 * float(per_structure_cost(res.r, self.struct_idx, res.weights, self.num_structs).sum())

    def refine_structure(self, values, steps: int | None = None) -> float:
        """Per-structure Gauss-Newton at fixed poses, warm-started from the current structure.

        A structure keeps a step only where its own cost does not increase. Returns the block's
        GTSAM-convention cost after refinement.
        """
        steps = self.config.refine_steps if steps is None else steps
        if steps <= 0:
            return self.cost(values)
        with torch_threads(self.config.threads):
            poses = self.poses_from_values(values)
            d = self.structure.clone()
            res = self.evaluate(poses, d, jacobians=True)
            cost_p = per_structure_cost(res.r, self.struct_idx, res.weights, self.num_structs)
            for it in range(steps):
                step = structure_gauss_newton_step(
                    res.r, res.E, self.struct_idx, res.weights, self.num_structs,
                    self.config.structure_damping, self.config.min_information,
                )
                trial = self.clamp_structure(d + step)
                res_t = self.evaluate(poses, trial, jacobians=True)
                cost_t = per_structure_cost(res_t.r, self.struct_idx, res_t.weights, self.num_structs)
                better = cost_t <= cost_p
                d = torch.where(better, trial, d)
                cost_p = torch.where(better, cost_t, cost_p)
                if bool(better.all()):
                    res = res_t
                elif it + 1 < steps:
                    res = self.evaluate(poses, d, jacobians=True)
            self.set_structure(d)
            return 0.5 * float(cost_p.sum())


class InverseDepthBlock(VisualBlock):
    """Inverse-depth reprojection measurements with one inverse depth per structure variable.

    Measurement ``n``: source pixel ``uv_source[n]`` of the keyframe in pose slot
    ``source_slot[n]``, carrying inverse depth ``structure[struct_idx[n]]``, observed at
    ``uv_target[n]`` in the keyframe of slot ``target_slot[n]``, with weights ``weights[n]`` (2,)
    (per-axis confidences, DROID's w_ij; or (N,) shared by both axes). Residual and Jacobians come
    from :func:`fgslam.factors.reprojection.reproject_inv_depth` (tangent [w, u, lambda], right
    perturbation). Dense DROID pixels: one structure per pixel of the source keyframe and one
    measurement per pixel and edge. DPV-SLAM patches: one structure per patch and ``p*p``
    measurements (its pixels, :func:`~fgslam.factors.reprojection.flatten_patches`) per patch and edge.
    Rows with invalid geometry (behind a camera...) get zero weight and are counted in
    ``num_invalid`` after each evaluation.

    Args:
        keys: gtsam keys of the k poses (Similarity3 T_WC) the block touches; slots index into them.
        K: (4,) intrinsics ``[fx, fy, cx, cy]`` shared by all keyframes of the block.
        inverse_depth: (P,) initial structure.
    """

    def __init__(
        self,
        keys: Sequence[int],
        source_slot: torch.Tensor,
        target_slot: torch.Tensor,
        uv_source: torch.Tensor,
        uv_target: torch.Tensor,
        struct_idx: torch.Tensor,
        weights: torch.Tensor,
        K: torch.Tensor,
        inverse_depth: torch.Tensor,
        config: BlockConfig | None = None,
        reprojection: ReprojectionConfig | None = None,
    ):
        super().__init__()
        dtype = torch.float64
        self.keys = tuple(int(k) for k in keys)
        self.config = config or BlockConfig()
        self.reprojection = reprojection or ReprojectionConfig()
        n = int(uv_source.shape[0])
        weights = torch.as_tensor(weights, dtype=dtype)
        if weights.ndim == 1:
            weights = weights[:, None].expand(n, 2)
        slots = torch.stack([torch.as_tensor(source_slot).long(), torch.as_tensor(target_slot).long()], dim=1)
        if n and (int(slots.min()) < 0 or int(slots.max()) >= len(self.keys)):
            raise ValueError(f"pose slots must lie in [0, {len(self.keys)}), got [{int(slots.min())}, {int(slots.max())}]")
        order, self.groups = SlotGroups.sort_rows(slots)
        self._order = order  # internal row r holds input measurement order[r]
        self.slots = slots[order]
        self.uv_source = torch.as_tensor(uv_source, dtype=dtype)[order]
        self.uv_target = torch.as_tensor(uv_target, dtype=dtype)[order]
        self.struct_idx = torch.as_tensor(struct_idx).long()[order]
        self.weights = self._checked_weights(weights[order])
        self.K = torch.as_tensor(K, dtype=dtype)
        self._structure = torch.zeros(0, dtype=dtype)
        self.set_structure(torch.as_tensor(inverse_depth, dtype=dtype))
        self.num_invalid = 0
        self._pairs: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None

    @staticmethod
    def _checked_weights(weights: torch.Tensor) -> torch.Tensor:
        if bool((weights < 0).any()) or not bool(torch.isfinite(weights).all()):
            raise ValueError("weights must be finite and non-negative")
        return weights.contiguous()

    def set_observations(self, uv_target: torch.Tensor | None = None, weights: torch.Tensor | None = None) -> None:
        """Replace observed target pixels (N, 2) and/or weights (N, 2) or (N,), given in the order
        of the constructor's measurements (e.g. new flow revisions and confidences of an update)."""
        if uv_target is not None:
            self.uv_target = torch.as_tensor(uv_target, dtype=torch.float64)[self._order]
        if weights is not None:
            weights = torch.as_tensor(weights, dtype=torch.float64)
            if weights.ndim == 1:
                weights = weights[:, None].expand(weights.shape[0], 2)
            self.weights = self._checked_weights(weights[self._order])

    @property
    def structure(self) -> torch.Tensor:
        return self._structure

    def clamp_structure(self, structure: torch.Tensor) -> torch.Tensor:
        """Inverse depths clamped to ``config.min_structure`` (a step never flips a point behind its camera)."""
        return structure.to(torch.float64).clamp_min(self.config.min_structure)

    def set_structure(self, structure: torch.Tensor) -> None:
        self._structure = self.clamp_structure(structure)

    def evaluate(self, poses: Sim3, structure: torch.Tensor, jacobians: bool) -> BlockResiduals:
        dtype = torch.float64
        d_rows = structure.to(dtype)[self.struct_idx]
        R, t, s = poses.R.to(dtype), poses.t.to(dtype), poses.s.to(dtype)
        n = int(self.uv_source.shape[0])
        # one call for every edge: each edge's pose pair formed once, its rows pointed at it
        gi, gj, pair_index = self._pair_rows()
        T_i, T_j = (R[gi], t[gi], s[gi]), (R[gj], t[gj], s[gj])
        if jacobians:
            res = reproject_inv_depth(self.uv_source, d_rows, T_i, T_j, self.K, self.uv_target, config=self.reprojection,
                                      pair_index=pair_index)
            r, valid = res.residual, res.valid
        else:
            uv, valid = reproject(self.uv_source, d_rows, T_i, T_j, self.K, config=self.reprojection,
                                  pair_index=pair_index)
            res_g = uv - self.uv_target
            valid = valid & torch.isfinite(res_g).all(-1)
            r = torch.where(valid[:, None], res_g, torch.zeros((), dtype=dtype))
        self.num_invalid = int(valid.numel() - int(valid.sum()))
        if self.num_invalid:
            logger.debug("inverse-depth block: %d of %d measurements invalid (zero weight)", self.num_invalid, n)
        weights = torch.where(valid[:, None], self.weights, torch.zeros((), dtype=dtype))
        if not jacobians:
            return BlockResiduals(r=r, weights=weights, num_invalid=self.num_invalid)
        return BlockResiduals(r=r, weights=weights, E=res.J_d, J=[res.J_Ti, res.J_Tj], num_invalid=self.num_invalid)

    def _pair_rows(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Each edge's source and target slot ``(G,)`` and each row's edge ``(N,)`` (rows are grouped
        by edge; formed once per block)."""
        if self._pairs is None:
            bounds = torch.as_tensor(self.groups.bounds)
            slots = torch.as_tensor(self.groups.slots, dtype=torch.long).reshape(-1, 2)
            edge_of_row = torch.repeat_interleave(torch.arange(len(self.groups.slots)), bounds[1:] - bounds[:-1])
            self._pairs = (slots[:, 0], slots[:, 1], edge_of_row)
        return self._pairs
