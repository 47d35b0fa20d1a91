"""The dense frontend's map starts: the monocular initialisation over the first keyframes, and the map
restart after ``tracking.max_lost`` failed frames in a row (relocalised through the loop port when it can)."""

from __future__ import annotations

import logging
import time

import numpy as np

from ..records import AbsolutePose
from .ba import DenseBA
from .contributor import DenseLoopContributor
from .keyframes import DenseKeyframes
from .state import DenseState
from .tracking import DenseTracker

logger = logging.getLogger(__name__)


class DenseMapStarts:
    """Initialises and restarts the map of the shared ``state`` (its graph, loop port and motion state)
    with the ``keyframes`` (edges), the ``ba`` (optimisation, the backend's blocks), the ``tracker``
    (re-tracking) and the loop ``contributor`` (the finished map's hand-over)."""

    def __init__(self, state: DenseState, keyframes: DenseKeyframes, ba: DenseBA, tracker: DenseTracker,
                 contributor: DenseLoopContributor):
        self.state = state
        self.keyframes = keyframes
        self.ba = ba
        self.tracker = tracker
        self.contributor = contributor

    def initialize(self) -> None:
        """Monocular initialisation: with ``ba.init_neighbour_rounds``, rounds on the edges between
        keyframes at most ``graph.init_radius`` apart first; then every collected keyframe connected to
        those within reach and optimised (``ba.init_rounds``); then the frames tracked meanwhile
        re-tracked against the optimised maps."""
        st = self.state
        t0 = time.perf_counter()
        g = st.graph
        cfg = st.config.ba
        free = list(g.active)
        flow0 = st.times["flow"]
        if cfg.init_neighbour_rounds:  # DROID-SLAM: updates on the neighbourhood edges first
            edges = self.keyframes.connect_neighbourhood(st.config.graph.init_radius)
            for _ in range(cfg.init_neighbour_rounds):
                self.ba.measure(edges)
                self.ba.optimize(free, edges, cfg.init_iterations, init=True)
        self.keyframes.connect_all()
        edges = g.active_edges()
        for _ in range(cfg.init_rounds):
            self.ba.measure(edges)
            self.ba.optimize(free, edges, cfg.init_iterations, init=True)
        st.initialized = True
        st.times["ba"] += time.perf_counter() - t0 - (st.times["flow"] - flow0)
        logger.info("dense frontend: initialised on %d keyframes, %d edges", len(free), len(edges))
        self.tracker.retrack(st.init_frames)
        st.init_frames = {}

    def restart(self, fid: int, frame) -> str:
        """Start a new map: the current one is finalised (kept for outputs), the next keyframe starts at
        the relocalised pose when the loop service finds one, else at the last prediction."""
        st = self.state
        st.counts["map_restarts"] += 1
        self.contributor.feed(all_keyframes=True)
        T_WC = st.pose_of(fid)
        found = st.loops.relocalize(frame.image, st.K)
        if found is not None:
            T_WC = np.asarray(found[1], dtype=np.float64)
            st.records[fid] = AbsolutePose(T_WC)
        g = st.graph
        for kf in g.keyframes.values():
            kf.image = None
            kf.surface = None
            st.final[kf.fid] = kf
            st.source.remove_frame(kf.fid)
        self.ba.clear_blocks()
        st.set_calibration(st.calibration)  # an empty graph
        st.loops.map_reset()
        st.initialized = False
        st.lost = 0
        st.pending_origin = T_WC if T_WC is not None else np.eye(4)
        st.last_fid = None
        st.velocity = np.eye(4)
        return "map restarted" + (" (relocalised)" if found is not None else "")
