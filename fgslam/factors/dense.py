"""Dense bundle adjustment of the DROID-SLAM family: keyframe Sim(3) poses and per-pixel inverse depth.

DROID-SLAM section 3.3 (eqs. 4-5). Every source keyframe ``i`` owns an inverse-depth map ``d_i`` at
the frame graph's resolution (1/8 of the image); an edge ``(i, j)`` of the frame graph carries a target
correspondence field ``p*_ij`` (where each pixel of ``i`` is seen in ``j``: the current reprojection
plus a flow revision) and a per-pixel, per-axis confidence ``w_ij``. The cost (GTSAM convention) is::

    E = 0.5 sum_(i,j) sum_p || pi(T_WCj^-1 T_WCi X_i(p, d_i(p))) - p*_ij(p) ||^2_{w_ij(p)}
        (+ 0.5 sum_i sum_p w_prior (d_i(p) - 1 / z_sensor_i(p))^2     RGB-D, fgslam.factors.depth)

Residuals and Jacobians come from :func:`fgslam.factors.reprojection.reproject_inv_depth` (one row per
pixel and edge, :class:`fgslam.factors.visual_block.InverseDepthBlock` evaluates them); the RGB-D term from
:func:`fgslam.factors.depth.depth_prior` (rows with no pose Jacobian). Each depth couples only to its
own rows, so the depth block of the normal equations is diagonal and the Schur complement is taken per
pixel (:func:`fgslam.factors.schur.schur_reduce`), with DROID's per-pixel damping ``eta`` added to the
depth block (eq. 5: ``C + eta``, the damping the learned update operator predicts; a constant from the
config otherwise).

Blocks (the backend's contract, :mod:`fgslam.factors.blocks`):

- :class:`DenseSourceBlock`: one source keyframe with all its outgoing edges; its Schur-reduced system
  is one :class:`~fgslam.factors.blocks.LinearPiece` over the source key and its targets.
- :class:`DenseBlock`: several source keyframes (a window, or the whole map for global optimisation);
  ``pieces="per_source"`` gives one piece per source keyframe (what GTSAM's sparse elimination wants),
  ``"merged"`` one piece over all keys (a small window).

Pixel grid: pixel ``(x, y)`` of a map of size ``(h, w)`` sits at ``uv = (x, y)`` in the map's own pixel
coordinates, with the map's intrinsics ``K`` (e.g. ``PinholeCamera.scaled(1 / 8)``); ``p*_ij`` is given in
the same coordinates (of the target keyframe's map, same intrinsics). Conventions otherwise as in
:mod:`fgslam.factors.schur` (tangent ``[w, u, lambda]``, right perturbation, float64).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from .blocks import LinearPiece
from ..core.lie import Sim3
from .depth import DepthPriorConfig, depth_prior, depth_priors
from .reprojection import ReprojectionConfig, reproject_inv_depth
from .schur import POSE_DIM, SlotGroups
from .visual_block import BlockConfig, BlockResiduals, InverseDepthBlock, VisualBlock

logger = logging.getLogger(__name__)

__all__ = ["DenseBlock", "DenseBlockConfig", "DenseEdge", "DenseKeyframe", "DenseSourceBlock", "DenseStereo", "pixel_grid"]


@dataclass
class DenseBlockConfig:
    """Tunables of the dense BA blocks."""

    block: BlockConfig = field(default_factory=BlockConfig)  # structure_damping: eta where no per-pixel damping is given
    reprojection: ReprojectionConfig = field(default_factory=ReprojectionConfig)
    depth_prior: DepthPriorConfig = field(default_factory=DepthPriorConfig)  # RGB-D term (keyframes with sensor depth)
    pieces: Literal["per_source", "merged"] = "per_source"  # linear pieces of a DenseBlock: one per source keyframe, or one


@dataclass
class DenseKeyframe:
    """A source keyframe: its pose key, inverse-depth map ``(h, w)`` (the initial structure), and
    optionally its sensor depth ``(h, w)`` in metres (RGB-D; 0 / NaN: no reading) and DROID's per-pixel
    damping ``eta`` ``(h, w)`` (>= 0)."""

    key: int
    inverse_depth: torch.Tensor | np.ndarray
    sensor_depth: torch.Tensor | np.ndarray | None = None
    damping: torch.Tensor | np.ndarray | None = None
    stereo: "DenseStereo | None" = None


@dataclass
class DenseStereo:
    """The right image of a stereo keyframe: ``uv_target`` ``(h, w, 2)`` where each grid pixel of the
    left map is seen in the right image's grid (non-finite: no measurement), ``weight`` ``(h, w, 2)`` or
    ``(h, w)`` its confidence, ``K_right`` the right grid's intrinsics and ``T_CRCL`` the calibrated
    metric left-to-right extrinsics (4x4), fixed in the factor: the rows depend on the source's inverse
    depths only (``fgslam.factors.depth.reproject_stereo`` with no target pose)."""

    uv_target: torch.Tensor | np.ndarray
    weight: torch.Tensor | np.ndarray
    K_right: torch.Tensor | np.ndarray
    T_CRCL: torch.Tensor | np.ndarray


@dataclass
class DenseEdge:
    """Edge ``(i, j)`` of the frame graph: ``uv_target`` ``(h, w, 2)`` is ``p*_ij`` (pixels of ``j``'s map;
    non-finite: no measurement) and ``weight`` ``(h, w, 2)`` or ``(h, w)`` the confidence ``w_ij`` (>= 0)."""

    source: int  # pose key of i
    target: int  # pose key of j
    uv_target: torch.Tensor | np.ndarray
    weight: torch.Tensor | np.ndarray


def pixel_grid(h: int, w: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """``(h * w, 2)`` pixel coordinates ``(x, y)`` of an ``(h, w)`` map, row-major (pixel ``y * w + x``)."""
    y, x = torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")
    return torch.stack((x.reshape(-1), y.reshape(-1)), dim=-1)


def _tensor(x, dtype=torch.float64) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x, dtype=dtype)


class DenseSourceBlock(VisualBlock):
    """One source keyframe ``i`` (its inverse-depth map is the structure) with its outgoing edges.

    Keys: ``(key_i, targets...)`` in the order of the edges. Rows: one per pixel and edge (from an
    :class:`~fgslam.factors.visual_block.InverseDepthBlock`), then one per pixel with a valid sensor depth
    (RGB-D prior; pose slots ``(0, 0)`` with zero pose Jacobians, so it only enters the depth block).
    """

    has_structure = True

    def __init__(self, keyframe: DenseKeyframe, edges: Sequence[DenseEdge], K, config: DenseBlockConfig | None = None):
        super().__init__()
        self.dense_config = config or DenseBlockConfig()
        self.config = self.dense_config.block
        d0 = _tensor(keyframe.inverse_depth)
        if d0.ndim != 2:
            raise ValueError(f"inverse_depth must be an (h, w) map, got shape {tuple(d0.shape)}")
        self.shape = (int(d0.shape[0]), int(d0.shape[1]))
        h, w = self.shape
        n_pix = h * w
        targets: list[int] = []
        for e in edges:
            if int(e.source) != int(keyframe.key):
                raise ValueError(f"edge ({e.source}, {e.target}) does not start at source keyframe {keyframe.key}")
            if int(e.target) == int(keyframe.key):
                raise ValueError(f"edge ({e.source}, {e.target}) ends at its own source keyframe")
            if int(e.target) not in targets:
                targets.append(int(e.target))
        self.keys = (int(keyframe.key), *targets)
        self.edge_targets = tuple(int(e.target) for e in edges)
        grid = pixel_grid(h, w)
        self._K = torch.as_tensor(K, dtype=torch.float64)
        self._flow = self._flow_rows(edges, d0.reshape(-1))
        # RGB-D prior rows: the pixels whose sensor depth is valid (fixed for the keyframe)
        self._prior_idx = torch.zeros(0, dtype=torch.long)
        self._prior_value = torch.zeros(0, dtype=torch.float64)
        self._prior_weight = torch.zeros(0, dtype=torch.float64)
        if keyframe.sensor_depth is not None:
            z = _tensor(keyframe.sensor_depth)
            if tuple(z.shape) != self.shape:
                raise ValueError(f"sensor_depth shape {tuple(z.shape)} differs from the map's {self.shape}")
            z = z.reshape(-1).to(torch.float64)
            reading = torch.isfinite(z) & (z > 0)  # 0, NaN, inf, negative: no reading
            inv_z = torch.where(reading, 1.0 / torch.where(reading, z, torch.ones_like(z)), torch.full_like(z, float("nan")))
            priors = depth_priors(inv_z.numpy(), self.dense_config.depth_prior)
            self._prior_idx = torch.as_tensor(priors.idx, dtype=torch.long)
            self._prior_value = torch.as_tensor(priors.value, dtype=torch.float64)
            self._prior_weight = torch.as_tensor(priors.weight, dtype=torch.float64)
        # stereo rows: every grid pixel of the left map seen in the keyframe's own right image
        self._stereo = None
        if keyframe.stereo is not None:
            st = keyframe.stereo
            uv_r, w_r = self._edge_rows([DenseEdge(keyframe.key, -1, st.uv_target, st.weight)])
            self._stereo = (grid, uv_r, w_r, _tensor(st.K_right), _tensor(st.T_CRCL))
        self._stack_rows()
        if keyframe.damping is not None:
            eta = _tensor(keyframe.damping)
            if tuple(eta.shape) != self.shape or bool((eta < 0).any()) or not bool(torch.isfinite(eta).all()):
                raise ValueError(f"damping must be a finite, non-negative {self.shape} map")
            self.damping = eta.reshape(-1).contiguous()
        else:
            self.damping = torch.full((n_pix,), float(self.config.structure_damping), dtype=torch.float64)
        self._structure = torch.zeros(0, dtype=torch.float64)
        self.set_structure(d0.reshape(-1))
        self.num_invalid = 0

    def _flow_rows(self, edges: Sequence[DenseEdge], structure: torch.Tensor) -> InverseDepthBlock:
        """The flow rows of ``edges``: one per pixel and edge whose weight is not zero on both axes (a
        row of zero weight adds nothing to the cost, the gradient or the information: left out, so
        that the linearisation costs what the measured pixels cost)."""
        h, w = self.shape
        n_pix = h * w
        uv_target, weights = self._edge_rows(edges)
        targets = list(self.keys[1:])
        target_slot = torch.cat([torch.full((n_pix,), 1 + targets.index(int(e.target))) for e in edges]) \
            if edges else torch.zeros(0, dtype=torch.long)
        pixel = torch.arange(n_pix).repeat(len(edges))
        keep = (weights > 0).any(-1)
        if not bool(keep.all()):
            uv_target, weights, target_slot, pixel = uv_target[keep], weights[keep], target_slot[keep], pixel[keep]
        grid = pixel_grid(h, w)
        return InverseDepthBlock(
            self.keys, torch.zeros(int(pixel.numel()), dtype=torch.long), target_slot, grid[pixel], uv_target,
            pixel, weights, self._K, structure, config=self.config, reprojection=self.dense_config.reprojection,
        )

    def _stack_rows(self) -> None:
        """Slots, structure indices and slot groups of the flow, prior and stereo rows (in that order)."""
        n_flow = int(self._flow.slots.shape[0])
        n_prior = int(self._prior_idx.numel())
        n_stereo = 0 if self._stereo is None else self.shape[0] * self.shape[1]
        self.slots = torch.cat([self._flow.slots, torch.zeros(n_prior + n_stereo, 2, dtype=torch.long)])
        self.struct_idx = torch.cat([self._flow.struct_idx, self._prior_idx, torch.arange(n_stereo)])
        groups = self._flow.groups if n_flow else SlotGroups((0,), ())
        if n_prior + n_stereo:
            groups = SlotGroups(groups.bounds + (n_flow + n_prior + n_stereo,), groups.slots + ((0, 0),))
        self.groups = groups

    def _edge_rows(self, edges: Sequence[DenseEdge]) -> tuple[torch.Tensor, torch.Tensor]:
        """Flattened ``(E h w, 2)`` targets and weights; non-finite targets get zero weight."""
        h, w = self.shape
        uvs, ws = [], []
        for e in edges:
            uv = _tensor(e.uv_target)
            wt = _tensor(e.weight)
            if wt.ndim == 2:
                wt = wt[..., None].expand(h, w, 2)
            if tuple(uv.shape) != (h, w, 2) or tuple(wt.shape) != (h, w, 2):
                raise ValueError(f"edge ({e.source}, {e.target}): uv_target {tuple(uv.shape)} / weight "
                                 f"{tuple(wt.shape)} do not match the map's {(h, w)}")
            ok = torch.isfinite(uv).all(-1, keepdim=True)
            uvs.append(torch.where(ok, uv, torch.zeros((), dtype=uv.dtype)).reshape(-1, 2))
            ws.append(torch.where(ok, wt, torch.zeros((), dtype=wt.dtype)).reshape(-1, 2))
        if not uvs:
            return torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, 2, dtype=torch.float64)
        return torch.cat(uvs), torch.cat(ws)

    # ------------------------------------------------------------------ measurements
    def set_edges(self, edges: Sequence[DenseEdge]) -> None:
        """New targets ``p*_ij`` and confidences ``w_ij`` for the same edges (a source's next revision)."""
        if tuple(int(e.target) for e in edges) != self.edge_targets:
            raise ValueError(f"set_edges: targets {[int(e.target) for e in edges]} differ from the block's "
                             f"{list(self.edge_targets)} (build a new block for a new frame graph)")
        self._flow = self._flow_rows(edges, self._structure)
        self._stack_rows()
        self._system = None
        self._damped = None

    def set_damping(self, damping: torch.Tensor | np.ndarray) -> None:
        """DROID's per-pixel damping ``eta`` ``(h, w)`` (e.g. the update operator's latest prediction)."""
        eta = _tensor(damping)
        if tuple(eta.shape) != self.shape or bool((eta < 0).any()) or not bool(torch.isfinite(eta).all()):
            raise ValueError(f"damping must be a finite, non-negative {self.shape} map")
        self.damping = eta.reshape(-1).contiguous()

    # ------------------------------------------------------------------ structure
    @property
    def structure(self) -> torch.Tensor:
        return self._structure

    @property
    def inverse_depth(self) -> torch.Tensor:
        """The current inverse-depth map ``(h, w)``."""
        return self._structure.reshape(self.shape)

    def clamp_structure(self, structure: torch.Tensor) -> torch.Tensor:
        return self._flow.clamp_structure(structure)

    def set_structure(self, structure: torch.Tensor) -> None:
        self._structure = self.clamp_structure(torch.as_tensor(structure, dtype=torch.float64).reshape(-1))

    # ------------------------------------------------------------------ residuals
    def evaluate(self, poses: Sim3, structure: torch.Tensor, jacobians: bool) -> BlockResiduals:
        flow = self._flow.evaluate(poses, structure, jacobians)
        self.num_invalid = flow.num_invalid
        n_prior = int(self._prior_idx.numel())
        if n_prior == 0 and self._stereo is None:
            return flow
        dtype = torch.float64
        rs, ws, Es = [flow.r], [flow.weights], [flow.E]
        if n_prior:
            prior = depth_prior(structure.to(dtype)[self._prior_idx], self._prior_value, self._prior_weight)
            zero = torch.zeros(n_prior, dtype=dtype)
            rs.append(torch.stack((prior.residual, zero), -1))
            ws.append(torch.stack((prior.weight, zero), -1))
            Es.append(torch.stack((prior.J_d, zero), -1))
        if self._stereo is not None:
            grid, uv_r, w_r, K_right, T_CRCL = self._stereo
            identity = (torch.eye(3, dtype=dtype), torch.zeros(3, dtype=dtype), torch.ones((), dtype=dtype))
            st = reproject_inv_depth(grid, structure.to(dtype), identity, identity, self._flow.K, uv_r, K_right,
                                     T_CtCj=T_CRCL, config=self.dense_config.reprojection)
            rs.append(st.residual)
            ws.append(torch.where(st.valid[:, None], w_r, torch.zeros((), dtype=dtype)))
            Es.append(st.J_d)
        n_self = sum(int(r.shape[0]) for r in rs[1:])
        r, weights = torch.cat(rs), torch.cat(ws)
        if not jacobians:
            return BlockResiduals(r=r, weights=weights, num_invalid=flow.num_invalid)
        J0 = torch.zeros(n_self, 2, POSE_DIM, dtype=dtype)
        return BlockResiduals(r=r, weights=weights, E=torch.cat(Es), J=[torch.cat([Jc, J0]) for Jc in flow.J],
                              num_invalid=flow.num_invalid)

    def back_substitute(self, delta) -> torch.Tensor:
        """Depth update (P,) for the pose update ``delta`` at the last linearisation point: a
        ``gtsam.VectorValues`` (keys it lacks are held fixed: zero update, as in a window solve) or a
        ``(7 k,)`` array over ``self.keys``."""
        if not isinstance(delta, (np.ndarray, torch.Tensor)):
            zero = np.zeros(POSE_DIM)
            delta = np.concatenate([np.asarray(delta.at(key)) if delta.exists(key) else zero for key in self.keys])
        return super().back_substitute(delta)

    def linearize_damping(self) -> torch.Tensor:
        """The per-pixel damping ``eta`` in the depth block of the linearisation (DROID eq. 5)."""
        return self.damping


class DenseBlock:
    """Dense BA block over several source keyframes (module docstring): keys, linear pieces, cost and
    the concatenated inverse-depth maps as structure (the backend's block contract)."""

    has_structure = True

    def __init__(self, keyframes: Sequence[DenseKeyframe], edges: Sequence[DenseEdge], K,
                 config: DenseBlockConfig | None = None):
        self.config = config or DenseBlockConfig()
        sources = [int(kf.key) for kf in keyframes]
        if len(set(sources)) != len(sources):
            raise ValueError(f"source keyframes repeat a key: {sources}")
        unknown = sorted({int(e.source) for e in edges} - set(sources))
        if unknown:
            raise ValueError(f"edges start at keys without a source keyframe: {unknown}")
        self.sources = [DenseSourceBlock(kf, [e for e in edges if int(e.source) == int(kf.key)], K, self.config)
                        for kf in keyframes]
        keys: list[int] = []
        for block in self.sources:
            keys.extend(k for k in block.keys if k not in keys)
        self.keys = tuple(keys)
        sizes = [b.num_structs for b in self.sources]
        self._bounds = np.concatenate([[0], np.cumsum(sizes)]).astype(int).tolist()

    def source(self, key: int) -> DenseSourceBlock:
        """The block of source keyframe ``key``."""
        for block in self.sources:
            if block.keys[0] == int(key):
                return block
        raise KeyError(f"no source keyframe with key {key}")

    def _split(self, structure: torch.Tensor) -> list[torch.Tensor]:
        structure = torch.as_tensor(structure, dtype=torch.float64).reshape(-1)
        if structure.numel() != self._bounds[-1]:
            raise ValueError(f"structure has {structure.numel()} entries, the block {self._bounds[-1]}")
        return [structure[a:b] for a, b in zip(self._bounds[:-1], self._bounds[1:])]

    @property
    def structure(self) -> torch.Tensor:
        return torch.cat([b.structure for b in self.sources]) if self.sources else torch.zeros(0, dtype=torch.float64)

    def set_structure(self, structure: torch.Tensor) -> None:
        for block, part in zip(self.sources, self._split(structure)):
            block.set_structure(part)

    def clamp_structure(self, structure: torch.Tensor) -> torch.Tensor:
        parts = [b.clamp_structure(p) for b, p in zip(self.sources, self._split(structure))]
        return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.float64)

    def linearize(self, values) -> list[LinearPiece]:
        return self._combined([piece for block in self.sources for piece in block.linearize(values)])

    def linearize_damped(self, lam: float) -> list[LinearPiece]:
        """The last linearisation with ``lam`` added to every pixel's information (the backend's LM damping
        of the depths; :meth:`DenseSourceBlock.linearize_damped`)."""
        return self._combined([piece for block in self.sources for piece in block.linearize_damped(lam)])

    def clear_damping(self) -> None:
        for block in self.sources:
            block.clear_damping()

    def _combined(self, pieces: list[LinearPiece]) -> list[LinearPiece]:
        """The sources' pieces, summed into one over ``self.keys`` unless ``config.pieces`` is per source."""
        if self.config.pieces == "per_source" or not pieces:
            return pieces
        index = {key: n for n, key in enumerate(self.keys)}
        dim = POSE_DIM
        H = np.zeros((dim * len(self.keys),) * 2)
        g = np.zeros(dim * len(self.keys))
        c = 0.0
        for piece in pieces:
            cols = np.concatenate([np.arange(dim * index[k], dim * index[k] + dim) for k in piece.keys])
            H[np.ix_(cols, cols)] += piece.H
            g[cols] += piece.g
            c += piece.c
        return [LinearPiece(self.keys, H, g, c)]

    def back_substitute(self, delta) -> torch.Tensor:
        """Structure update for the pose update ``delta`` (``gtsam.VectorValues``, or a ``(7 k,)`` array
        over ``self.keys``) at the last linearisation point."""
        if isinstance(delta, (np.ndarray, torch.Tensor)):
            flat = torch.as_tensor(np.asarray(delta), dtype=torch.float64).reshape(len(self.keys), POSE_DIM)
            index = {key: n for n, key in enumerate(self.keys)}
            parts = [b.back_substitute(torch.cat([flat[index[k]] for k in b.keys])) for b in self.sources]
        else:
            parts = [b.back_substitute(delta) for b in self.sources]
        return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.float64)

    def cost(self, values, structure=None) -> float:
        if structure is None:
            return float(sum(b.cost(values) for b in self.sources))
        return float(sum(b.cost(values, p) for b, p in zip(self.sources, self._split(structure))))

    def refine_structure(self, values, steps: int | None = None) -> float:
        return float(sum(b.refine_structure(values, steps) for b in self.sources))
