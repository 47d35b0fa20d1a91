"""The dense frontend's frame graph: keyframes (inverse-depth maps on the 1/8 grid), edges and their
last measured correspondence fields, flow distances and the global edge selection.

Poses live in the backend (Sim(3) ``T_WC`` per keyframe id); this module holds the rest and the
geometry the frontend asks for: the field a pair of keyframes induces (:meth:`FrameGraph.induced`),
flow distances between keyframes (:meth:`FrameGraph.flow_distance`) and DROID-SLAM's global edge
selection from the N x N distance matrix (:func:`select_global_edges`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import torch

from ...factors.dense import DenseStereo
from ...factors.reprojection import ReprojectionConfig, reproject
from ...core.lie import sim3_matrix_components


@dataclass
class DenseKeyframeState:
    """One keyframe of the dense map (its pose is the backend's)."""

    fid: int  # frame id (the backend's keyframe id)
    index: int  # the input frame's index
    timestamp: float
    image: Optional[np.ndarray]  # grey (H, W) uint8 while kept (loop closure, re-measurement); None once dropped
    inv_depth: np.ndarray  # (h, w) float64 grid inverse depths (metric in the keyframe's camera)
    colour: np.ndarray  # (h, w, 3) uint8 block means (points export)
    sensor_depth: Optional[np.ndarray] = None  # (h, w) metres (RGB-D; NaN: no reading), grid blocks
    depth_image: Optional[np.ndarray] = None  # (H, W) sensor depth for loop verification (RGB-D)
    stereo: Optional[DenseStereo] = None  # left-right rows (stereo)
    confidence: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (h, w) best outgoing edge confidence
    surface: Optional[object] = None  # the depth's DepthSurface (RGB-D depth alignment; None once the image is dropped)


@dataclass
class EdgeMeasurement:
    """Last measured correspondence field of edge (i, j): ``target`` (h, w, 2) grid px of j, ``weight``
    (h, w, 2) in [0, 1] (confidence times robust weight); ``induced`` (h, w, 2) float32 the field the
    estimate induced when it was measured (NaN: invalid; None: unmeasured, or the edge left the
    active graph), from which the local BA tells whether a re-measurement can change anything."""

    target: np.ndarray
    weight: np.ndarray
    induced: Optional[np.ndarray] = None


class FrameGraph:
    """Keyframes of the current map in order, the active ones, and the measured edges."""

    def __init__(self, K_grid: np.ndarray, shape: tuple[int, int], stride: int, reprojection: ReprojectionConfig,
                 pose: Callable[[int], np.ndarray]):
        self.K = torch.as_tensor(np.asarray(K_grid, dtype=np.float64))
        self.shape = shape  # (h, w)
        self.stride = int(stride)
        self.reprojection = reprojection
        self.pose = pose  # fid -> 4x4 Sim(3) T_WC (the backend's)
        self.keyframes: dict[int, DenseKeyframeState] = {}  # current map, in order
        self.active: list[int] = []  # fids of the active graph, in order
        self.edges: dict[tuple[int, int], EdgeMeasurement] = {}  # every measured edge of the current map
        h, w = shape
        y, x = np.mgrid[0:h, 0:w]
        self.grid = np.stack([x, y], -1).astype(np.float64)  # (h, w, 2)
        self._grid_t = torch.as_tensor(self.grid.reshape(-1, 2))

    # ------------------------------------------------------------------ keyframes and edges
    def add(self, kf: DenseKeyframeState) -> None:
        self.keyframes[kf.fid] = kf
        self.active.append(kf.fid)

    def remove(self, fid: int) -> None:
        self.keyframes.pop(fid, None)
        if fid in self.active:
            self.active.remove(fid)
        for e in [e for e in self.edges if fid in e]:
            del self.edges[e]

    def ensure_edge(self, edge: tuple[int, int]) -> None:
        """Add ``edge`` unmeasured (NaN targets, zero weights) unless the graph has it."""
        self.edges.setdefault(edge, EdgeMeasurement(np.full(self.shape + (2,), np.nan), np.zeros(self.shape + (2,))))

    def active_edges(self) -> list[tuple[int, int]]:
        act = set(self.active)
        return [e for e in self.edges if e[0] in act and e[1] in act]

    def order(self) -> list[int]:
        return list(self.keyframes)

    # ------------------------------------------------------------------ geometry
    def induced(self, edges: list[tuple[int, int]], stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """``(E, h', w', 2)`` grid pixels of each edge's source reprojected into its target (NaN where
        invalid: behind the camera) and the same grid's ``(h', w', 2)`` source pixels, on every
        ``stride``-th grid pixel."""
        h, w = self.shape
        grid = self.grid[::stride, ::stride]
        hs, ws = grid.shape[:2]
        if not edges:
            return np.zeros((0, hs, ws, 2)), grid
        uv = torch.as_tensor(grid.reshape(-1, 2))
        d = torch.as_tensor(np.stack([self.keyframes[i].inv_depth[::stride, ::stride].reshape(-1) for i, _ in edges]))
        Ti = np.stack([self.pose(i) for i, _ in edges])
        Tj = np.stack([self.pose(j) for _, j in edges])
        Ri, ti, si = sim3_matrix_components(Ti)
        Rj, tj, sj = sim3_matrix_components(Tj)
        out, ok = reproject(uv[None].expand(len(edges), -1, 2), d, (Ri[:, None], ti[:, None], si[:, None]),
                            (Rj[:, None], tj[:, None], sj[:, None]), self.K, config=self.reprojection)
        out = out.numpy().reshape(len(edges), hs, ws, 2).copy()
        out[~ok.numpy().reshape(len(edges), hs, ws)] = np.nan
        return out, grid

    def flow_distance(self, edges: list[tuple[int, int]], stride: int, chunk: int = 256) -> np.ndarray:
        """Mean induced flow (image px) of each edge over its source's pixels that land inside the
        target's image; ``inf`` when fewer than half of them do."""
        h, w = self.shape
        out = np.full(len(edges), np.inf)
        for a in range(0, len(edges), chunk):
            part = edges[a:a + chunk]
            uv, grid = self.induced(part, stride)
            inside = (np.isfinite(uv).all(-1) & (uv[..., 0] >= -0.5) & (uv[..., 0] <= w - 0.5)
                      & (uv[..., 1] >= -0.5) & (uv[..., 1] <= h - 0.5))
            flow = np.linalg.norm(np.where(inside[..., None], uv - grid, 0.0), axis=-1)
            n_in = inside.reshape(len(part), -1).sum(1)
            mean = flow.reshape(len(part), -1).sum(1) / np.maximum(n_in, 1) * self.stride
            out[a:a + len(part)] = np.where(n_in >= 0.5 * inside[0].size, mean, np.inf)
        return out

    def induced_change(self, edges: list[tuple[int, int]], induced: np.ndarray) -> np.ndarray:
        """Mean change (grid px) of each edge's induced field ``induced`` (E, h, w, 2) since its last
        measurement, over the pixels valid in both; ``inf`` for an edge without a stored field or
        without a pixel valid in both."""
        out = np.full(len(edges), np.inf)
        for n, e in enumerate(edges):
            m = self.edges.get(e)
            if m is None or m.induced is None:
                continue
            d = np.linalg.norm(induced[n] - m.induced, axis=-1)
            ok = np.isfinite(d)
            if ok.any():
                out[n] = float(d[ok].mean())
        return out

    def distance(self, i: int, j: int, stride: int) -> float:
        """Bidirectional flow distance between keyframes i and j (image px)."""
        d = self.flow_distance([(i, j), (j, i)], stride)
        return float(0.5 * (d[0] + d[1]))


def select_global_edges(fids: list[int], distance: np.ndarray, temporal_radius: int, nms_radius: int,
                        max_distance: float, max_edges: int) -> list[tuple[int, int]]:
    """DROID-SLAM's global edge selection over keyframes ``fids`` (in order) from their N x N flow
    distances (``distance[a, b]``, image px, symmetric or not): every pair at most ``temporal_radius``
    apart in order first; then pairs by increasing distance below ``max_distance``, each suppressing
    the pairs within ``nms_radius`` of it in both indices (Chebyshev); both directions of every chosen
    pair, at most ``max_edges`` edges in all."""
    n = len(fids)
    chosen: list[tuple[int, int]] = []
    taken = np.zeros((n, n), dtype=bool)  # suppressed or chosen (index pairs a < b)

    def take(a: int, b: int) -> bool:
        if len(chosen) + 2 > max_edges:
            return False
        chosen.extend([(fids[a], fids[b]), (fids[b], fids[a])])
        lo_a, hi_a = max(0, a - nms_radius), min(n, a + nms_radius + 1)
        lo_b, hi_b = max(0, b - nms_radius), min(n, b + nms_radius + 1)
        taken[lo_a:hi_a, lo_b:hi_b] = True
        taken[lo_b:hi_b, lo_a:hi_a] = True
        return True

    for r in range(1, temporal_radius + 1):
        for a in range(n - r):
            if len(chosen) + 2 > max_edges:
                return chosen
            chosen.extend([(fids[a], fids[a + r]), (fids[a + r], fids[a])])
    # the temporal band suppresses its own neighbourhood
    for a in range(n):
        lo, hi = max(0, a - temporal_radius - nms_radius), min(n, a + temporal_radius + nms_radius + 1)
        taken[a, lo:hi] = True
    sym = 0.5 * (distance + distance.T)
    iu, ju = np.triu_indices(n, k=1)
    d = sym[iu, ju]
    order = np.argsort(d, kind="stable")
    for k in order:
        if not d[k] < max_distance:
            break
        a, b = int(iu[k]), int(ju[k])
        if taken[a, b]:
            continue
        if not take(a, b):
            break
    return chosen
