"""The dense frontend's map starts: the monocular initialisation over the first keyframes, and the map
restart after ``tracking.max_lost`` failed frames in a row (relocalised through the loop port when it can)."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from ..records import AbsolutePose

if TYPE_CHECKING:
    from .frontend import DenseFrontend

logger = logging.getLogger(__name__)


class DenseMapStarts:
    """Initialises and restarts the map of ``frontend`` (its graph, BA, tracker, loop port and motion state)."""

    def __init__(self, frontend: "DenseFrontend"):
        self.fe = frontend

    def initialize(self) -> None:
        """Monocular initialisation: with ``ba.init_neighbour_rounds``, rounds on the edges between
        keyframes at most ``graph.init_radius`` apart first; then every collected keyframe connected to
        those within reach and optimised (``ba.init_rounds``); then the frames tracked meanwhile
        re-tracked against the optimised maps."""
        fe = self.fe
        t0 = time.perf_counter()
        g = fe.graph
        cfg = fe.config.ba
        free = list(g.active)
        flow0 = fe._times["flow"]
        if cfg.init_neighbour_rounds:  # DROID-SLAM: updates on the neighbourhood edges first
            edges = fe.keyframes.connect_neighbourhood(fe.config.graph.init_radius)
            for _ in range(cfg.init_neighbour_rounds):
                fe.ba.measure(edges)
                fe.ba.optimize(free, edges, cfg.init_iterations, init=True)
        fe.keyframes.connect_all()
        edges = g.active_edges()
        for _ in range(cfg.init_rounds):
            fe.ba.measure(edges)
            fe.ba.optimize(free, edges, cfg.init_iterations, init=True)
        fe._initialized = True
        fe._times["ba"] += time.perf_counter() - t0 - (fe._times["flow"] - flow0)
        logger.info("dense frontend: initialised on %d keyframes, %d edges", len(free), len(edges))
        fe.tracker.retrack(fe._init_frames)
        fe._init_frames = {}

    def restart(self, fid: int, frame) -> str:
        """Start a new map: the current one is finalised (kept for outputs), the next keyframe starts at
        the relocalised pose when the loop service finds one, else at the last prediction."""
        fe = self.fe
        fe._counts["map_restarts"] += 1
        fe.contributor.feed(all_keyframes=True)
        T_WC = fe._pose_of(fid)
        found = fe.loops.relocalize(frame.image, fe.K)
        if found is not None:
            T_WC = np.asarray(found[1], dtype=np.float64)
            fe._records[fid] = AbsolutePose(T_WC)
        g = fe.graph
        for kf in g.keyframes.values():
            kf.image = None
            kf.surface = None
            fe._final[kf.fid] = kf
            fe.source.remove_frame(kf.fid)
        fe.backend.set_blocks(fe.name, [])
        if fe.depth.enabled:
            fe.backend.set_blocks(fe.ba.depth_name, [])
        fe._set_calibration(fe.calibration)  # an empty graph
        fe.loops.map_reset()
        fe._initialized = False
        fe._lost = 0
        fe._pending_origin = T_WC if T_WC is not None else np.eye(4)
        fe._last_fid = None
        fe._velocity = np.eye(4)
        return "map restarted" + (" (relocalised)" if found is not None else "")
