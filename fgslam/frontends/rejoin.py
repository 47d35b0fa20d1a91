"""Rejoining a restarted map (patch and dense frontends): after a lost track restarts the map without a
relocalisation (the restart frame itself unrecognisable: a covered lens, motion blur), the new map's
tracked frames keep trying to relocalise through the loop port, among the keyframes of the maps before
the restart (the classical closer's database) or in a loaded map (``fgslam run --map``,
:mod:`fgslam.localize.live`). Two relocalisations of different frames that imply the same rigid
transform between the new map and the old (within ``rejoin_max_translation`` and
``rejoin_max_rotation_deg``) move every keyframe of the new map into the old map's frame, as one
correction (:class:`~fgslam.loop.records.PoseCorrection`, older keyframes held) applied through the
loop service (``LoopPort.move_map``: the contributor's hooks, the closer's pose table; a loop solve or
global BA computed before it is solved again or dropped).

The family calls :meth:`MapRejoin.step` after each frame of the new map that shows a view of its own
(the patch family: frames that entered the graph, not stationary ones; the dense family: every tracked
frame), and only once that map is initialised. A map that was not rejoined stays out of the reference:
a later restart rejoins only the maps before the first such map. Metric maps only (RGB-D, stereo): a
monocular map restarts at a scale of its own, which one relocalisation does not measure. Numerical
trouble in an attempt ends the attempts with a logged warning, never the run.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..contracts.contributor import PoseCorrection
from ..core.errors import FGSlamError
from ..eval.trajectory import rotation_angle
from .base import LoopPort

logger = logging.getLogger(__name__)


#: what an attempt may raise: the library's own errors, numerical ones (and OpenCV's, added where cv2 is imported)
_ATTEMPT_ERRORS = (FGSlamError, RuntimeError, ValueError, ArithmeticError, np.linalg.LinAlgError)


@dataclass(frozen=True)
class RejoinSettings:
    """The family's ``tracking.rejoin_*`` keys (module docstring)."""

    frames: int  # tracked frames of the new map that may try (0: off)
    every: int  # one attempt every this many of them
    max_translation: float  # the two relocalisations' transforms agree within this (map units: m) ...
    max_rotation_deg: float  # ... and this rotation

    @classmethod
    def of(cls, tracking) -> "RejoinSettings":
        """From a family's tracking config (its ``rejoin_frames``, ``rejoin_every``, ``rejoin_max_*``)."""
        return cls(int(tracking.rejoin_frames), int(tracking.rejoin_every), float(tracking.rejoin_max_translation),
                   float(tracking.rejoin_max_rotation_deg))


class MapRejoin:
    """The rejoin attempts of the map started at frame ``start`` (module docstring): :meth:`begin` at a
    restart, :meth:`step` after every tracked frame of the new map.

    Args:
        settings: the family's rejoin keys.
        loops: the loop port (relocalisation, ``move_map``).
        metric: the family's maps have a metric scale (monocular maps never try).
        keyframe_poses: ``T_WC`` by id of every keyframe (the current map's and the finalised ones).
    """

    def __init__(self, settings: RejoinSettings, loops: LoopPort, metric: bool,
                 keyframe_poses: Callable[[], dict[int, np.ndarray]]):
        self.settings = settings
        self.loops = loops
        self.metric = metric
        self.keyframe_poses = keyframe_poses
        self.start: int | None = None  # first frame of the map to rejoin; None: nothing to rejoin
        self.reference_end: int | None = None  # keyframes from this id on are in no reference frame (a map not rejoined)
        self.frames = 0  # tracked frames of the new map seen so far
        self.pending: tuple[int, np.ndarray] | None = None  # (frame, U) of the last relocalisation not yet confirmed
        self.rejoined = 0

    @property
    def waiting(self) -> bool:
        """A restarted map waits to rejoin."""
        return self.start is not None

    @property
    def reference_before(self) -> int | None:
        """Keyframes below this id are in the reference frame (None: all): what a relocalisation may land on."""
        return self.reference_end if self.reference_end is not None else self.start

    def restarted(self, start: int, relocalised: bool) -> None:
        """The family restarted its map at frame ``start`` (the first id its new map can hold): relocalised
        (the new map is in the reference frame: :meth:`cancel`) or not (:meth:`begin`)."""
        if relocalised:
            self.cancel()
        else:
            self.begin(start)

    def begin(self, start: int) -> None:
        """A restart at frame ``start`` that was not relocalised: its map may rejoin the maps before it."""
        self._give_up()  # a map still waiting is left where it is
        if self.settings.frames == 0 or not self.loops.relocalizes or not self.metric:
            self.reference_end = start if self.reference_end is None else self.reference_end
            return
        self.start, self.frames, self.pending = start, 0, None

    def _give_up(self) -> None:
        """The map waiting to rejoin (if any) stays in a frame of its own, out of the reference."""
        if self.start is not None and self.reference_end is None:
            self.reference_end = self.start
        self.start, self.pending = None, None

    def cancel(self) -> None:
        """A restart that was relocalised: its map is in the old frame already (a map still waiting to rejoin
        stays out of the reference)."""
        self._give_up()

    def step(self, fid: int, frame, K: np.ndarray, pose_of: Callable[[int], np.ndarray | None]) -> str | None:
        """After tracked frame ``fid`` of the new map (``frame``: its input, ``K`` its camera, ``pose_of`` the
        family's frame poses in the new map): every ``every`` frames a relocalisation among the older maps'
        keyframes; the event to report when the map was moved, else None."""
        if self.start is None:
            return None
        cfg = self.settings
        self.frames += 1
        if self.frames > cfg.frames:
            logger.info("map started at frame %d: not rejoined within %d frames", self.start, cfg.frames)
            self._give_up()
            return None
        if (self.frames - 1) % cfg.every:
            return None
        import cv2  # deferred: OpenCV (its error type)

        try:
            return self._attempt(fid, frame, K, pose_of)
        except (*_ATTEMPT_ERRORS, cv2.error) as exc:
            logger.warning("frame %d: rejoining the map started at frame %d failed (%s); it stays in a frame of its own",
                           frame.index, self.start, exc)
            self._give_up()
            return None

    def _attempt(self, fid: int, frame, K: np.ndarray, pose_of: Callable[[int], np.ndarray | None]) -> str | None:
        cfg = self.settings
        found = self.loops.relocalize(frame.image, K, before=self.reference_before)
        T_new = None if found is None else pose_of(fid)
        if found is None or T_new is None:
            return None
        kf_id, T_old = found
        U = np.asarray(T_old, dtype=np.float64) @ np.linalg.inv(T_new)  # new map's world -> old map's world
        previous, self.pending = self.pending, (fid, U)
        if previous is None:
            return None
        dU = np.linalg.inv(previous[1]) @ U
        moved, turned = float(np.linalg.norm(dU[:3, 3])), float(np.degrees(rotation_angle(dU[:3, :3])))
        if moved > cfg.max_translation or turned > cfg.max_rotation_deg:
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
        T_old = {k: T for k, T in self.keyframe_poses().items() if k >= self.start}
        T_new = {k: U @ T for k, T in T_old.items()}
        return self.loops.move_map(PoseCorrection.between(T_old, T_new, hold_older=True), T_new)
