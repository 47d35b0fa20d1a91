"""Rejoining a restarted map (patch frontend): after a lost track restarts the map without a relocalisation
(the restart frame itself unrecognisable: a covered lens, motion blur), the new map's tracked frames keep
trying to relocalise in the keyframe database, among the keyframes of the maps before the restart. Two
relocalisations of different frames that imply the same rigid transform between the new map and the old
(within ``tracking.rejoin_max_translation`` and ``tracking.rejoin_max_rotation_deg``) move every keyframe of
the new map into the old map's frame, as one correction (:class:`~fgslam.loop.records.PoseCorrection`,
older keyframes held) applied through the loop service (``LoopPort.move_map``: the contributor's hooks,
the closer's pose table; a loop solve or global BA computed before it is solved again or dropped).
Attempts run on frames that entered the graph (not on stationary frames, which repeat the keyframe's
view). A map that was not rejoined stays out of the reference: a later restart rejoins only the maps
before the first such map. Metric maps only (RGB-D, stereo): a monocular map restarts at a scale of its
own, which one relocalisation does not measure. Needs the classical loop closer's database
(``loop_closure.mode`` classical or both) or a loaded map (``fgslam run --map``: the lost frame's
relocalisation falls back to it, :mod:`fgslam.localize.live`); otherwise nothing is tried. Numerical trouble in an attempt
ends the attempts with a logged warning, never the run.
"""

from __future__ import annotations

import logging

import numpy as np

from ...contracts.contributor import PoseCorrection
from ...core.errors import FGSlamError
from ...eval.trajectory import rotation_angle
from ..base import LoopPort
from .state import PatchState

logger = logging.getLogger(__name__)


#: what an attempt may raise: the library's own errors, numerical ones (and OpenCV's, added where cv2 is imported)
_ATTEMPT_ERRORS = (FGSlamError, RuntimeError, ValueError, ArithmeticError, np.linalg.LinAlgError)


class MapRejoin:
    """The rejoin attempts of the map started at frame ``start`` (module docstring): :meth:`begin` at a
    restart, :meth:`step` after every tracked frame of the new map."""

    def __init__(self, state: PatchState, loops: LoopPort):
        self.state = state
        self.loops = loops
        self.start: int | None = None  # first frame of the map to rejoin; None: nothing to rejoin
        self.reference_end: int | None = None  # keyframes from this id on are in no reference frame (a map not rejoined)
        self.frames = 0  # tracked frames of the new map seen so far
        self.pending: tuple[int, np.ndarray] | None = None  # (frame, U) of the last relocalisation not yet confirmed
        self.rejoined = 0

    def begin(self, start: int) -> None:
        """A restart at frame ``start`` that was not relocalised: its map may rejoin the maps before it."""
        self._give_up()  # a map still waiting is left where it is
        cfg = self.state.config.tracking
        if cfg.rejoin_frames == 0 or not self.loops.relocalizes or self.state.sensor_mode == "mono":
            self.reference_end = start if self.reference_end is None else self.reference_end
            return
        self.start, self.frames, self.pending = start, 0, None

    def _give_up(self) -> None:
        """The map waiting to rejoin (if any) stays in a frame of its own, out of the reference."""
        if self.start is not None and self.reference_end is None:
            self.reference_end = self.start
        self.start, self.pending = None, None

    def cancel(self) -> None:
        """A restart that was relocalised: its map is in the old frame already."""
        self.start, self.pending = None, None

    def step(self, fid: int, frame) -> str | None:
        """After tracked frame ``fid`` of the new map: every ``rejoin_every`` frames of the graph a
        relocalisation among the older maps' keyframes; the event to report when the map was moved, else None."""
        st, cfg = self.state, self.state.config.tracking
        if self.start is None or not st.initialized or st.graph.frames[-1].fid != fid:
            return None  # nothing waiting, or a stationary frame (the keyframe's view again)
        self.frames += 1
        if self.frames > cfg.rejoin_frames:
            logger.info("map started at frame %d: not rejoined within %d frames", self.start, cfg.rejoin_frames)
            self._give_up()
            return None
        if (self.frames - 1) % cfg.rejoin_every:
            return None
        import cv2  # deferred: OpenCV (its error type)

        try:
            return self._attempt(fid, frame)
        except (*_ATTEMPT_ERRORS, cv2.error) as exc:
            logger.warning("frame %d: rejoining the map started at frame %d failed (%s); it stays in a frame of its own",
                           frame.index, self.start, exc)
            self._give_up()
            return None

    def _attempt(self, fid: int, frame) -> str | None:
        st, cfg = self.state, self.state.config.tracking
        before = self.start if self.reference_end is None else self.reference_end
        T_new = st.pose_of(fid)
        found = self.loops.relocalize(frame.image, st.K.numpy(), before=before)
        if found is None or T_new is None:
            return None
        kf_id, T_old = found
        U = np.asarray(T_old, dtype=np.float64) @ np.linalg.inv(T_new)  # new map's world -> old map's world
        previous, self.pending = self.pending, (fid, U)
        if previous is None:
            return None
        dU = np.linalg.inv(previous[1]) @ U
        moved, turned = float(np.linalg.norm(dU[:3, 3])), float(np.degrees(rotation_angle(dU[:3, :3])))
        if moved > cfg.rejoin_max_translation or turned > cfg.rejoin_max_rotation_deg:
            logger.info("frame %d relocalised on keyframe %d, %.3f m / %.1f deg from frame %d's: not rejoined yet",
                        frame.index, kf_id, moved, turned, previous[0])
            return None
        if not self._move(U):
            logger.warning("frame %d: the loop port cannot move the map; it stays in a frame of its own", frame.index)
            self._give_up()
            return None
        event = f"map rejoined: relocalised on keyframe {kf_id}, frames {previous[0]} and {fid} agree"
        logger.info("frame %d: %s (%.3f m, %.1f deg apart)", frame.index, event, moved, turned)
        self.start, self.pending = None, None
        self.rejoined += 1
        return event

    def _move(self, U: np.ndarray) -> bool:
        """Every keyframe of the new map moved by ``U`` (rigid), the older ones held; False: not applied."""
        st = self.state
        frames = [f for f in list(st.graph.frames) + list(st.final.values()) if f.fid >= self.start]
        T_old = {f.fid: f.T_WC for f in frames}
        T_new = {k: U @ T for k, T in T_old.items()}
        return self.loops.move_map(PoseCorrection.between(T_old, T_new, hold_older=True), T_new)
