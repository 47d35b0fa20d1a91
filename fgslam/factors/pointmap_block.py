"""The pointmap family's pose-only block: matched pointmaps between keyframes over their Sim(3) keys.

MASt3R-SLAM section 3.5 (eqs. 6-8, 10-11): an edge ``(i, j)`` of the keyframe graph carries N matches,
each pairing the canonical point ``X_j^j`` of a pixel of keyframe j with the canonical point ``X_i^i`` of
its match in keyframe i and a match confidence ``q``. With ``T_CiCj = T_WCi^-1 T_WCj`` the residuals are
those of :mod:`fgslam.factors.pointmap` (reference ``k = i``, frame ``f = j``):

- ``ray`` mode: ray rows ``psi(T_CiCj X_j^j) - psi(X_i^i)`` (3) and the weak distance row (1)
  (:func:`~fgslam.factors.pointmap.ray_dist_residuals`), for uncalibrated / generic cameras;
- ``calibrated`` mode: pixel rows ``pi(T_CiCj X_j^j) - uv_i`` (2) and the log-depth row (1)
  (:func:`~fgslam.factors.pointmap.calibrated_residuals`), which needs the matched pixels ``uv_i``.

Their Jacobians w.r.t. the relative pose are chained to the two global poses by
:func:`~fgslam.factors.pointmap.relative_to_global`. Weighting (eq. 6): each row group (the ray 3-vector
and the distance row; the pixel 2-vector and the log-depth row) is whitened by ``sqrt(q) / sigma``
(the residual config) and robustified by the kernel of ``robust`` (Huber by default) applied to the
group's whitened norm ``e``: the cost is ``sum rho(e)`` and the IRLS weight ``w(e) = rho'(e) / e``
(:mod:`fgslam.factors.robust`), so that ``g`` is the exact gradient of the cost and ``H`` its
Gauss-Newton Hessian.

The block has no structure (``has_structure = False``): every edge's N matches are summed into one
:class:`~fgslam.factors.blocks.LinearPiece` over its two keys (14 x 14; GTSAM's factor from it has at
most 15 rows: :func:`fgslam.factors.schur.to_gaussian_factor`), which is the per-edge block compressed to
a few rows of MASt3R-SLAM's second-order backend.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from .blocks import LinearPiece
from ..core.errors import DataError
from ..core.lie import Sim3
from .configs import PointmapBlockConfig  # the config: torch-free (a run's config loads without torch)
from .pointmap import calibrated_prepared, prepare_matches, ray_dist_prepared, relative_to_global_normal
from .robust import kernel_cost, kernel_weight
from .schur import torch_threads

logger = logging.getLogger(__name__)

__all__ = ["PointmapBlock", "PointmapBlockConfig", "PointmapEdge"]

# row groups of each mode: (ray 3-vector, distance) / (pixel 2-vector, log depth)
_GROUPS = {"ray": ((0, 3), (3, 4)), "calibrated": ((0, 2), (2, 3))}


@dataclass
class PointmapEdge:
    """Matches of one edge (module docstring): ``key_i`` the reference keyframe (whose pixels are matched),
    ``key_j`` the other; ``X_i_in_i`` / ``X_j_in_j`` ``(N, 3)`` the matched canonical points; ``weight``
    ``(N,)`` the match confidences q >= 0 (None: 1); ``uv_i`` ``(N, 2)`` the matched pixels of i
    (calibrated mode)."""

    key_i: int
    key_j: int
    X_i_in_i: np.ndarray | torch.Tensor
    X_j_in_j: np.ndarray | torch.Tensor
    weight: np.ndarray | torch.Tensor | None = None
    uv_i: np.ndarray | torch.Tensor | None = None


def _tensor(x, shape_tail: tuple[int, ...], n: int | None, what: str) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x, dtype=torch.float64)
    if t.shape[1:] != shape_tail or (n is not None and t.shape[0] != n) or t.ndim != 1 + len(shape_tail):
        raise DataError(f"pointmap block: {what} has shape {tuple(t.shape)}, expected ({n if n is not None else 'N'}"
                        f"{''.join(', ' + str(s) for s in shape_tail)})")
    return t


class _Edge:
    def __init__(self, edge: PointmapEdge, config: PointmapBlockConfig):
        self.key_i, self.key_j = int(edge.key_i), int(edge.key_j)
        if self.key_i == self.key_j:
            raise DataError(f"pointmap block: an edge joins key {self.key_i} to itself")
        self.X_i = _tensor(edge.X_i_in_i, (3,), None, "X_i_in_i")
        n = self.X_i.shape[0]
        self.X_j = _tensor(edge.X_j_in_j, (3,), n, "X_j_in_j")
        self.weight = torch.ones(n, dtype=torch.float64) if edge.weight is None else _tensor(edge.weight, (), n, "weight")
        self.weight = torch.where(torch.isfinite(self.weight) & (self.weight >= config.robust.min_confidence),
                                  self.weight, torch.zeros((), dtype=torch.float64))
        if bool((self.weight < 0).any()):
            raise DataError("pointmap block: match weights must be >= 0")
        self.uv_i = None
        if config.mode == "calibrated":
            if edge.uv_i is None:
                raise DataError("pointmap block: calibrated mode needs the matched pixels uv_i of every edge")
            self.uv_i = _tensor(edge.uv_i, (2,), n, "uv_i")
        # what does not change with the poses, made once (the block is linearised and evaluated many times)
        self.prepared = prepare_matches(self.X_j, self.X_i, self.weight, config.residual.min_norm)


class PointmapBlock:
    """Pose-only block of pointmap edges (module docstring): the backend's block contract
    (:class:`fgslam.factors.blocks.Block`) with ``has_structure = False``; one linear piece per edge."""

    has_structure = False

    def __init__(self, edges: Sequence[PointmapEdge], config: PointmapBlockConfig | None = None, K=None):
        self.config = config or PointmapBlockConfig()
        if self.config.mode not in _GROUPS:
            raise DataError(f"pointmap block: unknown mode {self.config.mode!r} (expected ray or calibrated)")
        if self.config.mode == "calibrated" and K is None:
            raise DataError("pointmap block: calibrated mode needs the intrinsics K = [fx, fy, cx, cy]")
        self.K = None if K is None else torch.as_tensor(np.asarray(K, np.float64))
        self.edges = [_Edge(e, self.config) for e in edges]
        keys: list[int] = []
        for e in self.edges:
            keys.extend(k for k in (e.key_i, e.key_j) if k not in keys)
        self.keys = tuple(keys)

    # ------------------------------------------------------------------ evaluation
    def _poses(self, values) -> dict[int, Sim3]:
        poses = Sim3.from_gtsam([values.atSimilarity3(key) for key in self.keys])
        return {key: poses[n] for n, key in enumerate(self.keys)}

    def _residuals(self, edge: _Edge, T_CiCj: Sim3, jacobians: bool = True):
        cfg = self.config
        if cfg.mode == "ray":
            return ray_dist_prepared(T_CiCj, edge.prepared, cfg.residual, jacobians=jacobians)
        return calibrated_prepared(T_CiCj, edge.prepared, edge.uv_i, self.K, cfg.residual, jacobians=jacobians)

    def _edge_terms(self, edge: _Edge, poses: dict[int, Sim3], jacobians: bool):
        """``T_CiCj``, whitened residuals ``(N, m)``, per-group kernel costs and weights ``(N, groups)``,
        and (with ``jacobians``) the whitened Jacobian ``(N, m, 7)`` w.r.t. the relative pose."""
        T_CiCj = poses[edge.key_i].inverse() @ poses[edge.key_j]
        res = self._residuals(edge, T_CiCj, jacobians)
        e, Jw = res.whitened()
        rb = self.config.robust
        norms = torch.stack([torch.linalg.vector_norm(e[:, a:b], dim=-1) for a, b in _GROUPS[self.config.mode]], -1)
        cost = kernel_cost(norms, rb.kind, rb.delta)
        w = kernel_weight(norms, rb.kind, rb.delta) if jacobians else None
        return T_CiCj, e, cost, w, Jw

    def whitened_residuals(self, values) -> list[torch.Tensor]:
        """Per edge the whitened residuals ``(N, m)`` at ``values`` (before the robust kernel)."""
        with torch_threads(self.config.threads):
            poses = self._poses(values)
            return [self._edge_terms(edge, poses, False)[1] for edge in self.edges]

    def inliers(self, values, threshold: float) -> list[torch.Tensor]:
        """Per edge, the matches that count as inliers at ``values``: valid residuals, weight > 0 and the
        first row group's (ray / pixel) whitened norm at most ``threshold``."""
        out = []
        with torch_threads(self.config.threads):
            poses = self._poses(values)
            for edge in self.edges:
                T_CiCj = poses[edge.key_i].inverse() @ poses[edge.key_j]
                res = self._residuals(edge, T_CiCj, jacobians=False)
                e, _ = res.whitened()
                a, b = _GROUPS[self.config.mode][0]
                out.append(res.valid & (edge.weight > 0) & (torch.linalg.vector_norm(e[:, a:b], dim=-1) <= threshold))
        return out

    def cost(self, values, structure=None) -> float:
        """GTSAM-convention cost ``sum rho(e)`` over every edge's row groups at ``values`` (no structure)."""
        with torch_threads(self.config.threads):
            poses = self._poses(values)
            return float(sum(float(self._edge_terms(edge, poses, False)[2].sum()) for edge in self.edges))

    def linearize(self, values) -> list[LinearPiece]:
        """One :class:`LinearPiece` per edge over ``(key_i, key_j)``: ``H = J^T W J``, ``g = J^T W e`` (IRLS
        weights ``W`` of the kernel per row group), ``c = 2 cost``. Batched: each edge's matches are
        reduced once over the 7 columns of its relative pose, then chained to the two keys
        (:func:`~fgslam.factors.pointmap.relative_to_global_normal`)."""
        pieces = []
        groups = _GROUPS[self.config.mode]
        with torch_threads(self.config.threads):
            poses = self._poses(values)
            for edge in self.edges:
                T_CiCj, e, cost, w, J = self._edge_terms(edge, poses, True)
                row_w = torch.cat([w[:, n:n + 1].expand(-1, b - a) for n, (a, b) in enumerate(groups)], -1)
                Jr = J.reshape(-1, 7)
                WJ = row_w.reshape(-1, 1) * Jr
                H, g = relative_to_global_normal(WJ.T @ Jr, WJ.T @ e.reshape(-1), T_CiCj)
                pieces.append(LinearPiece((edge.key_i, edge.key_j), H.numpy(), g.numpy(), 2.0 * float(cost.sum())))
        return pieces
