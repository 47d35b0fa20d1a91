"""The pointmap frontend's keyframe graph through the backend (step 6 of :mod:`.frontend`): the edges
between keyframes (tracking and loop edges), the family's one
:class:`~fgslam.factors.pointmap_block.PointmapBlock` over them, the window and final optimisations, and
the hand-over of new keyframes to the loop port."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from ...errors import OptimizationError
from ...factors.pointmap_block import PointmapBlock, PointmapEdge
from .keyframes import PointmapKeyframe, measure_edge

if TYPE_CHECKING:
    from .frontend import PointmapFrontend

logger = logging.getLogger(__name__)

#: numerical trouble of an optimisation: logged, the poses kept
_OPTIMIZATION_ERRORS = (OptimizationError, RuntimeError, np.linalg.LinAlgError)


class PointmapGraph:
    """The edges of the keyframes of ``frontend`` and their optimisation through its backend.

    Attributes:
        edges: every pointmap edge (tracking and loop edges), in insertion order.
        pairs: the (older, newer) keyframe pairs with an edge.
    """

    def __init__(self, frontend: "PointmapFrontend"):
        self.fe = frontend
        self.edges: list[PointmapEdge] = []
        self.pairs: set[tuple[int, int]] = set()
        self.depth_pairs: list[tuple[int, int]] = []  # keyframe pairs joined by depth alone (RGB-D depth alignment)
        self.depth_name = f"{frontend.name}.depth"  # the owner of the depth-alignment blocks
        self._loops_seen = 0  # verified loops of the loop service already looked at

    def after_keyframe(self, kf: PointmapKeyframe, edge) -> None:
        """A new keyframe ``kf``: its edge ``(previous keyframe, PointmapEdge)`` (None: the first; a None
        PointmapEdge: joined by depth alone) added and the window optimised; the keyframe handed to the
        loop port (with every pose when loops run)."""
        fe = self.fe
        if edge is not None:
            prev, e = edge
            if e is None:
                self.depth_pairs.append((prev, kf.fid))
            else:
                self.edges.append(e)
            self.pairs.add((prev, kf.fid))
            self.optimize()
        t0 = time.perf_counter()
        prev_ids = list(fe._kfs)[-2:-1]
        fe.loops.add_keyframe(kf.fid, prev_ids)
        if fe.loops.enabled:
            fe.loops.update_poses({k: fe._keyframe_T_WC(k) for k in fe._kfs})
        fe._times["bookkeeping"] += time.perf_counter() - t0

    def _set_block(self) -> None:
        """The family's block over the edges whose keyframes are in the backend."""
        fe = self.fe
        edges = [e for e in self.edges if fe.backend.has_key(e.key_i) and fe.backend.has_key(e.key_j)]
        fe.backend.set_blocks(fe.name, [PointmapBlock(edges, fe.config.block, fe.cam.K)] if edges else [])
        if fe.depth.enabled:
            fe.backend.set_blocks(self.depth_name, self.depth_blocks())

    def depth_blocks(self) -> list:
        """RGB-D depth alignment: depth blocks between the newest ``depth_align.window_pairs`` pairs of
        consecutive keyframes, and between every pair of keyframes joined by depth alone (their only link)."""
        fe = self.fe
        key = fe.backend_key
        ids = list(fe._kfs)
        blocks = fe.depth.chain([(key(f), fe._kfs[f].surface) for f in ids])
        have = {b.keys for b in blocks}
        for a, b in self.depth_pairs:
            ka, kb = fe._kfs.get(a), fe._kfs.get(b)
            if ka is not None and kb is not None and ka.surface is not None and kb.surface is not None \
                    and (key(a), key(b)) not in have:
                blocks.append(fe.depth.block(key(a), key(b), ka.surface, kb.surface))
        return blocks

    def optimize(self) -> None:
        """At most ``graph.iterations`` LM iterations over the newest ``graph.window`` keyframes (0: all)."""
        fe = self.fe
        t0 = time.perf_counter()
        self._set_block()
        ids = list(fe._kfs)
        window = fe.config.graph.window
        free = ids if window == 0 else ids[-window:]
        try:
            report = fe.backend.optimize_window(free, fe.config.graph.iterations)
            logger.debug("pointmap optimisation over %d keyframes: %s", len(free), report)
        except _OPTIMIZATION_ERRORS as exc:
            logger.warning("pointmap optimisation failed (%s); poses kept", exc)
        fe._times["optimization"] += time.perf_counter() - t0

    def final_optimize(self) -> None:
        """The last optimisation: ``graph.final_iterations`` over every keyframe (when there are two)."""
        fe = self.fe
        if fe.config.graph.final_iterations > 0 and len(fe._kfs) > 1:
            t0 = time.perf_counter()
            try:
                self._set_block()
                fe.backend.optimize_window(list(fe._kfs), fe.config.graph.final_iterations)
            except _OPTIMIZATION_ERRORS as exc:
                logger.warning("pointmap final optimisation failed (%s); poses kept", exc)
            fe._times["optimization"] += time.perf_counter() - t0

    def window_edges(self, kf: PointmapKeyframe, others: list[int]) -> int:
        """Edges from the keyframes ``others`` to the new keyframe ``kf`` measured from their canonical pointmaps
        (:func:`.keyframes.measure_edge`, started from the current poses), then the window optimised when any
        was added; returns how many (the monocular features' source: the scale tied over several keyframes)."""
        fe = self.fe
        cfg = fe.config
        t0 = time.perf_counter()
        added = 0
        for a in others:
            if a not in fe._kfs or (a, kf.fid) in self.pairs:
                continue
            T_CaCb = np.linalg.inv(fe._keyframe_T_WC(a)) @ fe._keyframe_T_WC(kf.fid)
            meas = measure_edge(fe._kfs[a], kf, T_CaCb, fe.cam.K, cfg.block, cfg.tracking, cfg.graph, cfg.matching,
                                cfg.source.descriptor, fe.fixed_scale, cfg.query_stride)
            if meas is None:
                continue
            self.edges.append(meas.edge)
            self.pairs.add((a, kf.fid))
            added += 1
        fe._times["matching"] += time.perf_counter() - t0
        if added:
            self.optimize()
        return added

    def loop_edges(self) -> None:
        """A pointmap edge for each loop the loop service accepted since the last call."""
        fe = self.fe
        if not fe.loops.classical:
            return
        loops = fe.loops.verified_loops()
        new = loops[self._loops_seen:]
        self._loops_seen = len(loops)
        added = False
        for rec in new:
            if rec.status != "accepted":
                continue
            a, b = int(rec.candidate_id), int(rec.query_id)
            if a not in fe._kfs or b not in fe._kfs or (a, b) in self.pairs:
                continue
            T_CaCb = np.linalg.inv(fe._keyframe_T_WC(a)) @ fe._keyframe_T_WC(b)
            cfg = fe.config
            meas = measure_edge(fe._kfs[a], fe._kfs[b], T_CaCb, fe.cam.K, cfg.block, cfg.tracking, cfg.graph,
                                cfg.matching, cfg.source.descriptor, fe.fixed_scale, cfg.query_stride)
            if meas is None:
                continue
            self.edges.append(meas.edge)
            self.pairs.add((a, b))
            fe._counts["loop_edges"] += 1
            logger.info("pointmap loop edge %d <-> %d: %d inliers", a, b, meas.num_inliers)
            added = True
        if added:
            self.optimize()

    def scale_keyframe(self, key: int, s: float) -> None:
        """The edges' snapshot points of the keyframe with backend ``key`` multiplied by ``s`` (its
        canonical pointmap was)."""
        for e in self.edges:
            if e.key_i == key:
                e.X_i_in_i = e.X_i_in_i * s
            if e.key_j == key:
                e.X_j_in_j = e.X_j_in_j * s
