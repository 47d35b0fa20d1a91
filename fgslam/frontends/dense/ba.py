"""The dense frontend's bundle adjustment through the backend: edges measured from the field the current
estimate induces, one :class:`~fgslam.factors.dense.DenseBlock` over them, the local BA of the newest
keyframes (step 3 of :mod:`.frontend`) and the global optimisation of the map (step 5)."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from ...backend.keys import pose_key
from ...factors.dense import DenseBlock, DenseEdge, DenseKeyframe
from ..records import rigid
from .graph import EdgeMeasurement, select_global_edges
from .weights import block_config, huber_weight, information

if TYPE_CHECKING:
    from .frontend import DenseFrontend

logger = logging.getLogger(__name__)


class DenseBA:
    """Measurement and optimisation of the keyframes of ``frontend`` (its graph, source, backend, counts
    and stage times)."""

    def __init__(self, frontend: "DenseFrontend"):
        self.fe = frontend
        self.depth_name = f"{frontend.name}.depth"  # the owner of the depth-alignment blocks (RGB-D)

    def measure(self, edges: list[tuple[int, int]], min_change: float = 0.0) -> None:
        """Measure ``edges`` from the fields the current estimate induces; stores their revisions
        (confidence times the Huber weight of the revision) and the sources' confidence maps.
        ``min_change`` (image px, > 0): an edge whose induced field moved less than this on average
        since its last measurement keeps that measurement (the flow would start where it started)."""
        if not edges:
            return
        fe = self.fe
        t0 = time.perf_counter()
        g = fe.graph
        induced, _ = g.induced(edges)
        if min_change > 0:
            moved = g.induced_change(edges, induced) * fe.stride >= min_change
            fe._counts["edges_kept"] += int((~moved).sum())
            edges = [e for e, m in zip(edges, moved) if m]
            induced = induced[moved]
        revs = fe.source.revise(edges, induced) if edges else []
        for (i, j), rev, ind in zip(edges, revs, induced):
            w = rev.weight * huber_weight(rev.target - ind, fe.config, fe.stride)
            # the induced field is kept only for the local BA's comparison (cleared when the edge leaves the active graph)
            g.edges[(i, j)] = EdgeMeasurement(rev.target, w, ind.astype(np.float32) if min_change > 0 else None)
        for i in {e[0] for e in edges}:
            kf = g.keyframes[i]
            kf.confidence = np.max([g.edges[e].weight.mean(-1) for e in g.edges if e[0] == i], axis=0)
        fe._times["flow"] += time.perf_counter() - t0

    def block(self, edges: list[tuple[int, int]]) -> DenseBlock:
        """One dense block over the measured ``edges`` (their sources' inverse depths eliminated)."""
        fe = self.fe
        g = fe.graph
        info = information(fe.config, fe.stride)
        sources = sorted({i for i, _ in edges}, key=list(g.keyframes).index)
        kfs = [DenseKeyframe(pose_key(i), g.keyframes[i].inv_depth, sensor_depth=g.keyframes[i].sensor_depth,
                             stereo=g.keyframes[i].stereo) for i in sources]
        dedges = [DenseEdge(pose_key(i), pose_key(j), g.edges[(i, j)].target, g.edges[(i, j)].weight * info)
                  for i, j in edges]
        return DenseBlock(kfs, dedges, fe.K_grid, block_config(fe.config, fe._reproj))

    def optimize(self, free: list[int], edges: list[tuple[int, int]], iterations: int, init: bool,
                 global_: bool = False) -> None:
        """One optimisation of the free keyframes with the dense block of ``edges`` through the backend."""
        fe = self.fe
        g = fe.graph
        block = self.block(edges)
        free_keys = {pose_key(f) for f in free}
        depth_blocks = self.depth_blocks(free_keys, global_)
        keys = set(block.keys).union(*(b.keys for b in depth_blocks))
        fixed = [k for k in keys if k not in free_keys]
        anchor = free[0] if (init or global_ or not fixed) else None
        pair = (free[0], free[-1]) if init and fe.sensor_mode == "mono" and len(free) >= 2 else None
        if global_ and fe.sensor_mode == "mono" and len(free) >= 2:
            pair = (free[0], free[1])
        fe.backend.set_gauge(anchor=anchor, scale_pair=pair)
        fe.backend.set_blocks(fe.name, [block])
        if fe.depth.enabled:
            fe.backend.set_blocks(self.depth_name, depth_blocks)
        fe.backend.optimize_window(free, iterations)
        fid_of = {pose_key(f): f for f in g.keyframes}
        for src in block.sources:
            g.keyframes[fid_of[src.keys[0]]].inv_depth = src.inverse_depth.numpy().copy()
        if fe.sensor_mode == "rgbd":  # sensor depths observe no Sim(3) scale: written back rigid (as patch)
            for f in free:
                fe.backend.set_pose(f, rigid(fe.backend.pose_matrix(f)))

    def depth_blocks(self, free_keys: set[int], global_: bool) -> list:
        """RGB-D depth alignment: the depth blocks between consecutive keyframes of the map (with their
        surfaces) at least one of which is free; the newest ``depth_align.window_pairs`` of them, every one
        in the global optimisation. Empty when depth alignment is off."""
        fe = self.fe
        if not fe.depth.enabled:
            return []
        g = fe.graph
        frames = [(pose_key(f), g.keyframes[f].surface) for f in g.order()]
        return fe.depth.chain(frames, free_keys, 0 if global_ else None)

    def local(self, new_fid: int, rounds: int | None = None) -> None:
        """Local BA after keyframe ``new_fid``: ``rounds`` (default ``ba.rounds``) of re-measuring the
        newest keyframes' edges and optimising the newest ``ba.window`` keyframes."""
        fe = self.fe
        t0 = time.perf_counter()
        g = fe.graph
        cfg = fe.config.ba
        free = g.active[-cfg.window:]
        free_set = set(free)
        edges = [e for e in g.active_edges() if e[0] in free_set or e[1] in free_set]
        newest = set(g.active[-cfg.remeasure:]) | {new_fid}
        fresh = [e for e in edges if e[0] in newest or e[1] in newest]
        flow0 = fe._times["flow"]
        for _ in range(cfg.rounds if rounds is None else rounds):
            self.measure(fresh, cfg.remeasure_min_change)
            self.optimize(free, edges, cfg.iterations, init=False)
        fe._times["ba"] += time.perf_counter() - t0 - (fe._times["flow"] - flow0)

    def global_ba(self) -> None:
        """Edges rebuilt from the N x N flow-distance matrix of the map's keyframes (those whose images
        are kept), measured, and every keyframe of the map optimised through the backend."""
        fe = self.fe
        t0 = time.perf_counter()
        flow0 = fe._times["flow"]
        g = fe.graph
        cfg = fe.config.global_ba
        fe._new_since_global = 0
        fids = [f for f in g.order() if g.keyframes[f].image is not None]
        n = len(fids)
        if n < 3:
            return
        pairs = [(a, b) for a in fids for b in fids if a != b]
        dist = np.full((n, n), np.inf)
        d = g.flow_distance(pairs, fe.config.graph.distance_stride)
        index = {f: k for k, f in enumerate(fids)}
        for (a, b), v in zip(pairs, d):
            dist[index[a], index[b]] = v
        edges = select_global_edges(fids, dist, cfg.temporal_radius, cfg.nms_radius, cfg.max_distance, cfg.max_edges)
        imaged = set(fids)
        kept = [e for e in g.edges if not (e[0] in imaged and e[1] in imaged)]  # edges of dropped images: as stored
        for e in edges:
            g.ensure_edge(e)
        free = g.order()
        for _ in range(cfg.rounds):
            self.measure(edges)
            self.optimize(free, edges + kept, cfg.iterations, init=False, global_=True)
        # the active graph's own edges stay; others built for this run are dropped again (memory)
        active = set(g.active)
        for e in [e for e in g.edges if e not in kept and not (e[0] in active and e[1] in active) and e not in edges]:
            del g.edges[e]
        fe._counts["global_runs"] += 1
        fe._times["global"] += time.perf_counter() - t0 - (fe._times["flow"] - flow0)
        logger.info("dense global optimisation: %d keyframes, %d edges, %.2f s", len(free), len(edges),
                    time.perf_counter() - t0)
