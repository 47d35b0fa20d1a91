"""Keyframes of the pointmap family and the measurement of an edge between two of them.

A :class:`PointmapKeyframe` holds the canonical pointmap ``X_k^k`` (fused by eq. 9), its confidence sum,
the working-resolution image (retrieval, PLY colours, re-adding it to a source) and, lazily, its
descriptors and ray image (MASt3R-SLAM section 3.2's reference side).

:func:`match_frame` matches a query pointmap expressed in the keyframe's frame into the keyframe
(iterative projective matching, warm started from the previous matches or from the projection of the
query points) and :func:`measure_edge` turns two keyframes and a relative-pose guess into a backend edge
(:class:`~fgslam.factors.pointmap_block.PointmapEdge`): match, refine the relative pose by the tracking
solver (the verification: enough valid matches and robust inliers) and keep the inlier matches. Both the
pointmap frontend (edges to the previous keyframe, loop and relocalisation edges) and the mixed-family
contributor (:mod:`.mix`) use them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import torch

from ...backend.keys import pose_key
from ...factors.pointmap_block import PointmapBlockConfig, PointmapEdge
from ...core.lie import Sim3
from .config import PointmapGraphConfig, PointmapTrackingConfig
from .descriptors import DescriptorConfig, dense_descriptors
from .matching import MatchingConfig, PointmapMatches, RayImage, match_pointmaps
from .tracking import TrackResult, track_pose

logger = logging.getLogger(__name__)

__all__ = ["EdgeMeasurement", "PointmapKeyframe", "even_subset", "match_frame", "measure_edge", "projected_uv"]


@dataclass
class PointmapKeyframe:
    """One keyframe (module docstring). ``X`` ``(H W, 3)`` and ``C`` ``(H W,)`` float32 tensors (row-major
    pixels); ``grey`` ``(H, W)`` uint8 and ``colour`` ``(H, W, 3)`` uint8 or None at the working resolution;
    ``depth`` / ``right``: what the source needs to re-add the frame (RGB-D / stereo)."""

    fid: int
    timestamp: float
    index: int
    H: int
    W: int
    X: torch.Tensor
    C: torch.Tensor
    grey: np.ndarray
    colour: np.ndarray | None = None
    depth: np.ndarray | None = None
    right: np.ndarray | None = None
    D: torch.Tensor | None = None
    surface: object | None = None  # the depth's DepthSurface (RGB-D depth alignment)
    _rays: RayImage | None = field(default=None, repr=False)

    def ray_image(self) -> RayImage:
        """The reference side of matching (cached until the pointmap changes: :meth:`changed`)."""
        if self._rays is None:
            self._rays = RayImage(self.X.view(self.H, self.W, 3), self.C.view(self.H, self.W))
        return self._rays

    def changed(self) -> None:
        self._rays = None

    def descriptors(self, config: DescriptorConfig) -> torch.Tensor:
        """``(H W, d)`` descriptors of the keyframe image (computed once, dropped by :meth:`release`)."""
        if self.D is None:
            self.D = torch.from_numpy(dense_descriptors(self.grey, config)[0].reshape(self.H * self.W, -1))
        return self.D

    def release(self) -> None:
        """Drop the caches (descriptors, ray image) of a keyframe no longer tracked against."""
        self.D = None
        self._rays = None


def projected_uv(X_in_k: torch.Tensor, K, W: int, H: int) -> torch.Tensor:
    """``(N, 2)`` pixels of points ``X_in_k (N, 3)`` projected by ``K = [fx, fy, cx, cy]`` (NaN behind the
    camera): the matching's warm start when no previous matches exist."""
    fx, fy, cx, cy = (float(k) for k in K)
    X = X_in_k.to(torch.float32)
    z = X[:, 2]
    ok = torch.isfinite(X).all(-1) & (z > 0)
    zs = torch.where(ok, z, torch.ones_like(z))
    uv = torch.stack((fx * X[:, 0] / zs + cx, fy * X[:, 1] / zs + cy), -1)
    return torch.where(ok[:, None], uv, torch.full_like(uv, float("nan")))


def match_frame(kf: PointmapKeyframe, X_q_in_k: torch.Tensor, query_valid: torch.Tensor, D_q: torch.Tensor | None,
                init_uv: torch.Tensor | None, K, matching: MatchingConfig, descriptors: DescriptorConfig) -> PointmapMatches:
    """Match query points ``X_q_in_k (N, 3)`` (in the keyframe's frame) into keyframe ``kf``; warm start
    ``init_uv (N, 2)`` or the projection of the query points."""
    if init_uv is None:
        init_uv = projected_uv(X_q_in_k, K, kf.W, kf.H)
    D_k = kf.descriptors(descriptors) if D_q is not None else None
    return match_pointmaps(kf.ray_image(), X_q_in_k, init_uv=init_uv, D_i=D_k, D_j=D_q, query_valid=query_valid,
                           config=matching)


def even_subset(idx: torch.Tensor, limit: int) -> torch.Tensor:
    """At most ``limit`` entries of ``idx``, evenly strided."""
    if idx.numel() <= limit:
        return idx
    return idx[torch.linspace(0, idx.numel() - 1, limit).round().to(torch.int64)]


@dataclass
class EdgeMeasurement:
    """A measured edge: the backend edge, the refined ``T_CaCb``, the match counts."""

    edge: PointmapEdge
    T_CaCb: Sim3
    num_valid: int
    num_inliers: int


def measure_edge(a: PointmapKeyframe, b: PointmapKeyframe, T_CaCb: np.ndarray, K, block: PointmapBlockConfig,
                 tracking: PointmapTrackingConfig, graph: PointmapGraphConfig, matching: MatchingConfig, descriptors: DescriptorConfig,
                 fixed_scale: bool, query_stride: int = 1) -> EdgeMeasurement | None:
    """The edge (a, b) from the canonical pointmaps and the guess ``T_CaCb`` (4x4 Sim(3)): b's points moved
    into a, matched, the relative pose refined (:func:`~.tracking.track_pose`), inlier matches kept
    (at most ``graph.max_edge_matches``). None (logged) with fewer than ``graph.min_edge_matches`` valid
    matches or inliers, or less than ``graph.min_edge_inlier_ratio`` of the matches inliers."""
    T0 = Sim3.from_matrix(torch.as_tensor(np.asarray(T_CaCb, np.float64)))
    query = _grid(b.H, b.W, query_stride)
    X_b = b.X[query]
    ok = (b.C[query] >= tracking.min_confidence) & torch.isfinite(X_b).all(-1)
    X_b_in_a = T0.act(X_b.to(torch.float64)).to(torch.float32)
    D_b = b.descriptors(descriptors)[query]
    m = match_frame(a, X_b_in_a, ok, D_b, None, K, matching, descriptors)
    n_valid = int(m.valid.sum())
    if n_valid < graph.min_edge_matches:
        logger.info("pointmap edge (%d, %d): %d valid matches (< %d); no edge", a.fid, b.fid, n_valid,
                    graph.min_edge_matches)
        return None
    sel = even_subset(m.valid.nonzero().squeeze(1), tracking.max_query_points)
    q, p = query[sel], m.index[sel]
    X_f = b.X[q].to(torch.float64)
    X_k = a.X[p].to(torch.float64)
    w = torch.sqrt(b.C[q].clamp(max=1.0) * a.C[p].clamp(max=1.0)).to(torch.float64)
    uv = m.uv[sel].to(torch.float64)
    Kt = torch.as_tensor(np.asarray(K, np.float64))
    tr: TrackResult = track_pose(T0, X_f, X_k, w, block, tracking, fixed_scale, uv, Kt)
    if tr.num_inliers < max(graph.min_edge_matches, graph.min_edge_inlier_ratio * len(sel)):
        logger.info("pointmap edge (%d, %d): %d inliers of %d matches (< %d or %.0f %%); no edge", a.fid, b.fid,
                    tr.num_inliers, len(sel), graph.min_edge_matches, 100 * graph.min_edge_inlier_ratio)
        return None
    keep = even_subset(tr.inlier.nonzero().squeeze(1), graph.max_edge_matches)
    edge = PointmapEdge(pose_key(a.fid), pose_key(b.fid), X_k[keep], X_f[keep], w[keep], uv[keep])
    return EdgeMeasurement(edge, tr.T_CkCf, n_valid, tr.num_inliers)


_GRIDS: dict[tuple[int, int, int], torch.Tensor] = {}


def _grid(H: int, W: int, stride: int) -> torch.Tensor:
    """Flat indices of every ``stride``-th pixel (both axes) of an ``H x W`` image (cached)."""
    key = (H, W, stride)
    idx = _GRIDS.get(key)
    if idx is None:
        v, u = torch.meshgrid(torch.arange(0, H, stride), torch.arange(0, W, stride), indexing="ij")
        idx = _GRIDS[key] = (v * W + u).reshape(-1)
    return idx


def query_grid(H: int, W: int, stride: int) -> torch.Tensor:
    """Flat indices of the query pixels of an ``H x W`` frame at ``stride`` (public name of the cache)."""
    return _grid(H, W, stride)
