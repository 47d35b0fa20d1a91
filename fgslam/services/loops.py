"""Loop closure as a shared service: classical loops (retrieval, verification, Sim(3) pose graph),
relocalisation, and proximity loops closed by a global bundle adjustment (DPV-SLAM sections 3.3 and
3.2), beside tracking, for any frontend that implements the contributor contract
(:mod:`fgslam.contracts.contributor`).

The run's system (:class:`fgslam.run.system.SlamSystem`) holds one :class:`LoopService`, runs
:meth:`LoopService.poll`, :meth:`LoopService.wait` and :meth:`LoopService.finish`, and connects it to
the frontend as its loop port (:class:`fgslam.frontends.base.LoopPort`), through which the frontend
calls the rest at fixed points of its frame loop:

- :meth:`LoopService.poll` at the *safe point* (before a frame is tracked, no optimisation running):
  the classical closer's newest correction and a finished global BA are applied there, through
  ``contributor.apply_correction`` (and, for the global BA, ``contributor.apply_global_ba`` first);
- :meth:`LoopService.add_keyframe` for each keyframe whose pose is final or about to be (the service
  fetches its image with ``contributor.keyframe_image``; ids must increase), then
  :meth:`LoopService.update_poses` with its latest keyframe poses;
- :meth:`LoopService.keyframe_settled` for each keyframe that can no longer be removed and
  :meth:`LoopService.search` with the newest of them (proximity loops);
- :meth:`LoopService.start_global_ba` for a periodic global BA of the contributor's map in the
  background (the dense family's; the system connects a service with loop closure off for it);
- :meth:`LoopService.relocalize` when the track is lost, :meth:`LoopService.map_reset` when the
  frontend starts a new map, :meth:`LoopService.finish` at the end.

A loaded map (``fgslam run --map``, metric sensors: a :class:`MapLink`,
:class:`fgslam.localize.live.LoadedMapLink`) gets the keyframes too, and a lost frame that the closer's
database does not relocalise (or every lost frame, with loop closure off) is relocalised in it.

Classical (``mode`` classical or both): :class:`fgslam.loop.closure.LoopCloser` in its worker thread;
a correction is a :class:`~fgslam.contracts.contributor.PoseCorrection` (metric maps: SE(3)).

Proximity (``mode`` proximity or both): :class:`fgslam.services.proximity.ProximityLoops` searches
loops among the settled keyframes and closes each by a global bundle adjustment in the background,
applied at a fixed safe point after its start (``global_ba_delay_frames``; the classical closer's
corrections likewise arrive ``correction_delay_frames`` polls after their keyframe).

:meth:`LoopService.finish` waits for a running global BA and applies it, then stops the closer and
applies its last correction.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from typing import Optional, Protocol

import numpy as np

from ..loop.closure import LoopCloser
from ..loop.records import LoopClosureConfig, PoseCorrection
from ..contracts.contributor import Contributor, ProximityGates
from .proximity import ProximityLoops

logger = logging.getLogger(__name__)


class MapLink(Protocol):
    """A loaded map the run relocalises in (:class:`fgslam.localize.live.LoadedMapLink`)."""

    def add_keyframe(self, kf_id: int, image: np.ndarray) -> bool: ...  # localise a run keyframe in the map

    def map_reset(self) -> None: ...  # the run starts a new map

    def relocalize(self, image: np.ndarray, pose_of: Callable[[int], Optional[np.ndarray]]
                   ) -> tuple[int, np.ndarray] | None: ...  # (its keyframe, T_WC in the run's frame) from the run's keyframe poses


class LoopService:
    """Loop closure beside one contributor (see the module docstring).

    Args:
        contributor: the frontend (:class:`~fgslam.contracts.contributor.Contributor`; for proximity
            loops a :class:`~fgslam.contracts.contributor.ProximityContributor`).
        config: ``loop_closure`` (None: off).
        metric: the map has a metric scale (stereo / RGB-D): classical corrections are SE(3).
        proximity: the family's proximity gates (needed when ``config.proximity``).
        link: a loaded map to relocalise in as well (None: none; module docstring).
    """

    def __init__(self, contributor: Contributor, config: LoopClosureConfig | None = None, metric: bool = False,
                 proximity: ProximityGates | None = None, link: MapLink | None = None):
        self.contributor = contributor
        self.config = config if config is not None else LoopClosureConfig()
        self.config.validate()
        self.closer = LoopCloser(self.config, metric=metric) if self.config.classical else None
        self.proximity = proximity if self.config.proximity else None
        self.link = link
        self._times: dict[str, float] = {}
        if self.closer is not None or link is not None:
            self._times["loop"] = 0.0
            self._counts = {"corrections_applied": 0, "keyframes_added": 0, "relocalization_attempts": 0,
                            "relocalized": 0, "relocalized_in_loaded_map": 0}
        self._last_added = -1  # newest keyframe id handed to the closer
        # proximity loops and every global BA (its run_global_ba also without proximity loops)
        self.proximity_closer = ProximityLoops(contributor, self.config, self.proximity, self.closer)

    # ------------------------------------------------------------------ state
    @property
    def enabled(self) -> bool:
        return self.closer is not None or self.proximity is not None

    @property
    def classical(self) -> bool:
        """Whether the classical closer (retrieval, verification, relocalisation) runs."""
        return self.closer is not None

    @property
    def relocalizes(self) -> bool:
        """Whether a lost frame can be relocalised (the classical closer's database, or a loaded map): the
        service then takes keyframes (:meth:`add_keyframe`)."""
        return self.closer is not None or self.link is not None

    def verified_loops(self) -> list:
        """The classical closer's verified loops so far (oldest first; empty without the closer)."""
        return [] if self.closer is None else self.closer.loops

    def accepted_pairs(self) -> list[tuple[int, int]]:
        """``(query id, candidate id)`` of every accepted loop, classical then proximity."""
        pairs = [(r.query_id, r.candidate_id) for r in self.verified_loops() if r.status == "accepted"]
        if self.proximity is not None:
            pairs += [(q, c) for q, c, status in self.proximity_loops if status == "accepted"]
        return pairs

    @property
    def proximity_loops(self) -> list[tuple[int, int, str]]:
        """``(query id, candidate id, status)`` of every proximity loop verified so far."""
        return self.proximity_closer.loops

    @property
    def proximity_counts(self) -> dict:
        """Proximity counts: queries, candidates, verified, accepted, undone, global BA runs and seconds."""
        return self.proximity_closer.counts

    @property
    def busy(self) -> bool:
        """Whether a global BA is running (or waits to be applied)."""
        return self.proximity_closer.busy

    def stage_times(self) -> dict[str, float]:
        """Seconds spent in the caller's thread: ``loop`` (classical), ``proximity``."""
        times = dict(self._times)
        if self.proximity is not None:
            times["proximity"] = self.proximity_closer.seconds
        return times

    # ------------------------------------------------------------------ safe point
    def poll(self) -> None:
        """One safe point: apply the closer's correction due now and the global BA due now (waiting
        for either when it is not ready: results arrive at fixed safe points, module docstring)."""
        if self.closer is not None:
            t0 = time.perf_counter()
            self._apply_correction(self.closer.poll())
            self._times["loop"] += time.perf_counter() - t0
        self.proximity_closer.poll()

    def _apply_correction(self, corr: PoseCorrection | None) -> None:
        if corr is None:
            return
        self.contributor.apply_correction(corr)
        self._counts["corrections_applied"] += 1
        logger.info("loop correction applied (%d loops accepted, %d keyframes in the pose graph)",
                    corr.n_accepted, len(corr.T_update))

    def map_reset(self) -> None:
        """The contributor starts a new map: a running global BA of the old one is dropped."""
        self.proximity_closer.map_reset()
        if self.link is not None:
            self.link.map_reset()

    def move_map(self, correction: PoseCorrection, T_WC_by_id: dict) -> bool:
        """A correction the contributor's frontend measured itself (a restarted map rejoining the map before
        it): applied through the contributor (and its hooks: the IMU's states turn with the poses), the moved
        keyframes' poses ``T_WC_by_id`` into the closer's table; a loop solve made on the poses before it is
        solved again, and a running global BA is dropped. True: applied."""
        self.contributor.apply_correction(correction)
        if self.closer is not None:
            self.closer.moved(T_WC_by_id)
        self.proximity_closer.map_reset()
        return True

    # ------------------------------------------------------------------ classical
    def add_keyframe(self, kf_id: int, neighbours: Sequence[int] = ()) -> bool:
        """Hand keyframe ``kf_id`` (pose final or about to be) to the closer and the loaded map, once; False
        when it was handed already or the contributor has no image of it."""
        if not self.relocalizes or kf_id <= self._last_added:
            return False
        t0 = time.perf_counter()
        kf = self.contributor.keyframe_image(kf_id)
        T_WC = self.contributor.keyframe_pose(kf_id)
        added = kf is not None and T_WC is not None
        if added:
            if self.closer is not None:
                self.closer.add_keyframe(kf_id, kf.timestamp, kf.image, kf.K, T_WC, neighbours=neighbours)
            if self.link is not None:
                self.link.add_keyframe(kf_id, kf.image)
            self._last_added = kf_id
            self._counts["keyframes_added"] += 1
        self._times["loop"] += time.perf_counter() - t0
        return added

    def update_poses(self, T_WC_by_id: dict) -> None:
        """The contributor's latest keyframe poses (the closer's pose table)."""
        if self.closer is not None:
            t0 = time.perf_counter()
            self.closer.update_poses(T_WC_by_id)
            self._times["loop"] += time.perf_counter() - t0

    def relocalize(self, image: np.ndarray, K: np.ndarray, before: int | None = None) -> tuple[int, np.ndarray] | None:
        """``(kf_id, T_WC)`` of a lost frame's image on the keyframe database (``before``: only keyframes with
        a smaller id, e.g. those of the maps before a restart), else in the loaded map (``kf_id``: its keyframe;
        ``T_WC`` in the run's frame), or None."""
        if not self.relocalizes:
            return None
        t0 = time.perf_counter()
        self._counts["relocalization_attempts"] += 1
        found = None if self.closer is None else self.closer.relocalize(image, K, before)
        if found is None and self.link is not None:
            found = self.link.relocalize(image, self.contributor.keyframe_pose)  # the latest poses, corrections included
            self._counts["relocalized_in_loaded_map"] += int(found is not None)
        self._times["loop"] += time.perf_counter() - t0
        if found is not None:
            self._counts["relocalized"] += 1
        return found

    # ------------------------------------------------------------------ proximity (ProximityLoops)
    def keyframe_settled(self, kf_id: int) -> None:
        """Keyframe ``kf_id`` can no longer be removed (ids increase): a future candidate."""
        self.proximity_closer.keyframe_settled(kf_id)

    def search(self, query: int) -> None:
        """Search a proximity loop for settled keyframe ``query`` and start its global BA."""
        self.proximity_closer.search(query)

    #: a contributor may hand its periodic global BAs to :meth:`start_global_ba` (the no-op loop port cannot)
    runs_global_ba = True

    def prepare_global_ba(self) -> None:
        """The contributor will hand global BAs: the worker process starts now (once), ahead of the first."""
        self.proximity_closer.prepare()

    def start_global_ba(self) -> bool:
        """A global BA of the contributor's map without loop edges in the background, applied at the
        safe point ``global_ba_delay_frames`` polls from now; False when one runs already (or no map)."""
        return self.proximity_closer.start_global_ba()

    def wait(self) -> None:
        """Wait for a running global BA and apply it (reruns included)."""
        self.proximity_closer.wait()

    # ------------------------------------------------------------------ end
    def finish(self) -> None:
        """Wait for a running global BA and apply it; stop the closer and apply its last correction
        (the caller hands its remaining keyframes first)."""
        self.proximity_closer.finish()
        if self.closer is not None:
            t0 = time.perf_counter()
            self.closer.close()
            self._apply_correction(self.closer.poll())
            self._times["loop"] += time.perf_counter() - t0

    def cancel(self) -> None:
        """Stop at once (an interrupted or failed run): a running global BA is dropped and its worker
        process ended, the closer's worker stops after its current job; nothing more is applied."""
        self.proximity_closer.cancel()
        if self.closer is not None:
            self.closer.cancel()

    def summary(self, index: dict[int, int] | None = None) -> dict | None:
        """Loop-closure counts for the run summary (None when off); ``index`` maps keyframe ids to the
        input frame indices reported in ``loop_frames`` (-1: unknown)."""
        if not self.enabled and self.link is None:
            return None
        index = index or {}
        out: dict = {"mode": self.config.mode}
        if self.closer is None and self.link is not None:
            out.update(self._counts)
        if self.closer is not None:
            loops = self.closer.loops
            out.update({**self._counts,
                        "verifications": len(self.closer.verifications), "verified_loops": len(loops),
                        "accepted_loops": sum(rec.status == "accepted" for rec in loops),
                        "loop_frames": [[index.get(rec.query_id, -1), index.get(rec.candidate_id, -1), rec.status]
                                        for rec in loops],
                        "closer_s": self.closer.stage_times(), "closer_counts": self.closer.counts})
        if self.proximity is not None:
            out["proximity"] = self.proximity_closer.summary(index)
        return out
