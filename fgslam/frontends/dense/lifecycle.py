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

_NEIGHBOURHOOD, _ALL_PAIRS = "neighbourhood", "all pairs"  # the initialisation's phases
_VELOCITY_FRAMES = 2  # when the initialisation ends, at least the newest two frames are re-tracked (the velocity's)


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
        self._rounds: list[str] = []  # the begun initialisation's rounds left (phases)
        self._phase: str | None = None  # the phase of the last round run
        self._edges: list[tuple[int, int]] = []  # that phase's edges

    @property
    def pending(self) -> bool:
        """The monocular initialisation has begun and has rounds left (``ba.init_rounds_per_frame``)."""
        return bool(self._rounds)

    def initialize(self) -> bool:
        """Monocular initialisation over the collected keyframes: with ``ba.init_neighbour_rounds``, rounds
        on the edges between keyframes at most ``graph.init_radius`` apart first; then every collected
        keyframe connected to those within reach and optimised (``ba.init_rounds``); then the frames
        tracked meanwhile re-tracked against the optimised maps. ``ba.init_rounds_per_frame`` of the rounds
        run now, the rest in :meth:`advance` on the next frames. True when the map is initialised."""
        cfg = self.state.config.ba
        self._rounds = [_NEIGHBOURHOOD] * cfg.init_neighbour_rounds + [_ALL_PAIRS] * cfg.init_rounds
        self._phase = None
        return self.advance()

    def advance(self, all_left: bool = False) -> bool:
        """The next ``ba.init_rounds_per_frame`` rounds of the begun initialisation (0 or ``all_left``: all
        left); after the last one the map is initialised and the frames tracked before it re-tracked
        (:meth:`retrack_pending`). True when the map is initialised."""
        st = self.state
        t0 = time.perf_counter()
        g = st.graph
        cfg = st.config.ba
        free = list(g.active)  # with the keyframes collected since the initialisation began
        flow0 = st.times["flow"]
        budget = len(self._rounds) if all_left else (cfg.init_rounds_per_frame or len(self._rounds))
        try:
            while self._rounds and budget:
                phase = self._rounds.pop(0)
                budget -= 1
                if phase == _NEIGHBOURHOOD:  # DROID-SLAM: updates on the neighbourhood edges first
                    self._edges = self.keyframes.connect_neighbourhood(st.config.graph.init_radius)
                else:
                    if phase != self._phase:  # every pair within reach connected once (keyframes collected
                        self.keyframes.connect_all()  # later join with their usual edges)
                    self._edges = g.active_edges()
                self._phase = phase
                self.ba.measure(self._edges)
                self.ba.optimize(free, self._edges, cfg.init_iterations, init=True)
        except BaseException:  # a failed round abandons the initialisation: the next keyframe starts it again
            self._rounds = []
            raise
        finally:
            st.times["ba"] += time.perf_counter() - t0 - (st.times["flow"] - flow0)
        if self._rounds:
            return False
        st.initialized = True
        logger.info("dense frontend: initialised on %d keyframes, %d edges", len(free), len(self._edges))
        self.retrack_pending(at_least=_VELOCITY_FRAMES)
        return True

    def retrack_pending(self, all_left: bool = False, at_least: int = 0) -> None:
        """Re-track the frames tracked before the initialisation against its maps: at most
        ``tracking.retrack_per_frame`` of them (but ``at_least``), newest first (0 or ``all_left``: all,
        in order); the rest stay pending."""
        st = self.state
        cap = st.config.tracking.retrack_per_frame
        if cap:
            cap = max(cap, at_least)
        if all_left or not cap or cap >= len(st.init_frames):
            frames, st.init_frames = st.init_frames, {}
        else:
            newest = list(st.init_frames)[-cap:][::-1]
            frames = {fid: st.init_frames.pop(fid) for fid in newest}
        self.tracker.retrack(frames)

    def restart(self, fid: int, frame, before: int | None = None) -> tuple[str, bool]:
        """Start a new map: the current one is finalised (kept for outputs), the next keyframe starts at
        the relocalised pose when the loop service finds one (``before``: among keyframes with a smaller id,
        the reference maps'), else at the last prediction. Returns the event and whether the lost frame was
        relocalised."""
        st = self.state
        st.counts["map_restarts"] += 1
        if st.initialized:  # frames still waiting for their re-tracking get it before the map is finalised
            self.retrack_pending(all_left=True)
        st.init_frames = {}  # (a map never initialised: its frames keep their poses)
        self.contributor.feed(all_keyframes=True)
        T_WC = st.pose_of(fid)
        found = st.loops.relocalize(frame.image, st.K, before)
        if found is not None:
            T_WC = np.asarray(found[1], dtype=np.float64)
            st.records[fid] = AbsolutePose(T_WC)
        self._rounds = []  # an initialisation under way is abandoned with its map
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
        return "map restarted" + (" (relocalised)" if found is not None else ""), found is not None
