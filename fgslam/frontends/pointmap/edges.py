"""The pointmap frontend's keyframe graph through the backend (step 6 of :mod:`.frontend`): the edges
between keyframes (tracking and loop edges), the family's one
:class:`~fgslam.factors.pointmap_block.PointmapBlock` over them, the window and final optimisations, and
the hand-over of new keyframes to the loop port."""

from __future__ import annotations

import logging
import time

import numpy as np

from ...backend.keys import pose_key
from ...core.errors import OptimizationError
from ...factors.pointmap_block import PointmapBlock, PointmapEdge
from .keyframes import PointmapKeyframe, measure_edge
from .state import PointmapState

logger = logging.getLogger(__name__)

#: numerical trouble of an optimisation: logged, the poses kept
_OPTIMIZATION_ERRORS = (OptimizationError, RuntimeError, np.linalg.LinAlgError)


class PointmapGraph:
    """The edges of the shared state's keyframes and their optimisation through its backend; ``owner``
    names the family's blocks there (``set_blocks(owner, ...)``, the depth blocks ``<owner>.depth``).

    Attributes:
        edges: every pointmap edge (tracking and loop edges), in insertion order.
        pairs: the (older, newer) keyframe pairs with an edge.
    """

    def __init__(self, state: PointmapState, owner: str):
        self.state = state
        self.owner = owner
        self.edges: list[PointmapEdge] = []
        self.pairs: set[tuple[int, int]] = set()
        self.depth_pairs: list[tuple[int, int]] = []  # keyframe pairs joined by depth alone (RGB-D depth alignment)
        self.depth_name = f"{owner}.depth"  # the owner of the depth-alignment blocks
        self._loops_seen = 0  # verified loops of the loop service already looked at

    def after_keyframe(self, kf: PointmapKeyframe, edge) -> None:
        """A new keyframe ``kf``: its edge ``(previous keyframe, PointmapEdge)`` (None: the first; a None
        PointmapEdge: joined by depth alone) added and the window optimised; the keyframe handed to the
        loop port (with every pose when loops run)."""
        st = self.state
        try:
            if edge is not None:
                prev, e = edge
                if e is None:
                    self.depth_pairs.append((prev, kf.fid))
                else:
                    self.edges.append(e)
                self.pairs.add((prev, kf.fid))
                self.optimize()
        finally:  # a keyframe whose optimisation failed is still the loop port's (its pose is the backend's)
            t0 = time.perf_counter()
            prev_ids = list(st.kfs)[-2:-1]
            st.loops.add_keyframe(kf.fid, prev_ids)
            if st.loops.enabled:
                st.loops.update_poses({k: st.keyframe_T_WC(k) for k in st.kfs})
            st.times["bookkeeping"] += time.perf_counter() - t0

    def _set_block(self) -> None:
        """The family's block over the edges whose keyframes are in the backend."""
        st = self.state
        edges = [e for e in self.edges if st.backend.has_key(e.key_i) and st.backend.has_key(e.key_j)]
        st.backend.set_blocks(self.owner, [PointmapBlock(edges, st.config.block, st.cam.K)] if edges else [])
        if st.depth.enabled:
            st.backend.set_blocks(self.depth_name, self.depth_blocks())

    def depth_blocks(self) -> list:
        """RGB-D depth alignment: depth blocks between the newest ``depth_align.window_pairs`` pairs of
        consecutive keyframes, and between every pair of keyframes joined by depth alone (their only link)."""
        st = self.state
        ids = list(st.kfs)
        blocks = st.depth.chain([(pose_key(f), st.kfs[f].surface) for f in ids])
        have = {b.keys for b in blocks}
        for a, b in self.depth_pairs:
            ka, kb = st.kfs.get(a), st.kfs.get(b)
            if ka is not None and kb is not None and ka.surface is not None and kb.surface is not None \
                    and (pose_key(a), pose_key(b)) not in have:
                blocks.append(st.depth.block(pose_key(a), pose_key(b), ka.surface, kb.surface))
        return blocks

    def optimize(self) -> None:
        """At most ``graph.iterations`` LM iterations over the newest ``graph.window`` keyframes (0: all)."""
        st = self.state
        t0 = time.perf_counter()
        self._set_block()
        ids = list(st.kfs)
        window = st.config.graph.window
        free = ids if window == 0 else ids[-window:]
        try:
            report = st.backend.optimize_window(free, st.config.graph.iterations)
            logger.debug("pointmap optimisation over %d keyframes: %s", len(free), report)
            self._write_back_rigid(free)
        except _OPTIMIZATION_ERRORS as exc:
            logger.warning("pointmap optimisation failed (%s); poses kept", exc)
        st.times["optimization"] += time.perf_counter() - t0

    def _write_back_rigid(self, free: list[int]) -> None:
        """A metric map's optimised keyframes written back rigid: their scale prior holds the Sim(3) scale at 1
        only to the solver's convergence, and a metric map has none to estimate (as the dense family's RGB-D)."""
        st = self.state
        if st.fixed_scale:
            st.backend.write_back_rigid(free)

    def final_optimize(self) -> None:
        """The last optimisation: ``graph.final_iterations`` over every keyframe (when there are two)."""
        st = self.state
        if st.config.graph.final_iterations > 0 and len(st.kfs) > 1:
            t0 = time.perf_counter()
            try:
                self._set_block()
                st.backend.optimize_window(list(st.kfs), st.config.graph.final_iterations)
                self._write_back_rigid(list(st.kfs))
            except _OPTIMIZATION_ERRORS as exc:
                logger.warning("pointmap final optimisation failed (%s); poses kept", exc)
            st.times["optimization"] += time.perf_counter() - t0

    def window_edges(self, kf: PointmapKeyframe, others: list[int]) -> int:
        """Edges from the keyframes ``others`` to the new keyframe ``kf`` measured from their canonical pointmaps
        (:func:`.keyframes.measure_edge`, started from the current poses), then the window optimised when any
        was added; returns how many (the monocular features' source: the scale tied over several keyframes)."""
        st = self.state
        cfg = st.config
        t0 = time.perf_counter()
        added = 0
        for a in others:
            if a not in st.kfs or (a, kf.fid) in self.pairs:
                continue
            T_CaCb = np.linalg.inv(st.keyframe_T_WC(a)) @ st.keyframe_T_WC(kf.fid)
            meas = measure_edge(st.kfs[a], kf, T_CaCb, st.cam.K, cfg.block, cfg.tracking, cfg.graph, cfg.matching,
                                cfg.source.descriptor, st.fixed_scale, cfg.query_stride)
            if meas is None:
                continue
            self.edges.append(meas.edge)
            self.pairs.add((a, kf.fid))
            added += 1
        st.times["matching"] += time.perf_counter() - t0
        if added:
            self.optimize()
        return added

    def loop_edges(self) -> None:
        """A pointmap edge for each loop the loop service accepted since the last call."""
        st = self.state
        if not st.loops.classical:
            return
        loops = st.loops.verified_loops()
        new = loops[self._loops_seen:]
        self._loops_seen = len(loops)
        added = False
        for rec in new:
            if rec.status != "accepted":
                continue
            a, b = int(rec.candidate_id), int(rec.query_id)
            if a not in st.kfs or b not in st.kfs or (a, b) in self.pairs:
                continue
            T_CaCb = np.linalg.inv(st.keyframe_T_WC(a)) @ st.keyframe_T_WC(b)
            cfg = st.config
            meas = measure_edge(st.kfs[a], st.kfs[b], T_CaCb, st.cam.K, cfg.block, cfg.tracking, cfg.graph,
                                cfg.matching, cfg.source.descriptor, st.fixed_scale, cfg.query_stride)
            if meas is None:
                continue
            self.edges.append(meas.edge)
            self.pairs.add((a, b))
            st.counts["loop_edges"] += 1
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
