"""The contributor contract: what shared services (loop closure, relocalisation) need from a frontend.

A frontend family that feeds the backend implements :class:`Contributor`; the loop-closure service
(:class:`fgslam.services.loops.LoopService`) talks to it only through these methods, so the
patch, dense and pointmap families (or two of them on one graph) share one service.

- :meth:`Contributor.keyframe_image`: the keyframe's grey image, intrinsics and (RGB-D) depth, for
  retrieval (BoW), verification and relocalisation; None once the frontend no longer keeps it.
- :meth:`Contributor.keyframe_pose`: its current ``T_WC`` (4x4 Sim(3)) or None.
- :meth:`Contributor.apply_correction`: apply a :class:`PoseCorrection` (a Sim(3) update per keyframe;
  keyframes it does not list take the update of the nearest listed id) to the frontend's own poses,
  structure (with ``fold_scale`` the scale goes into the structure: patch inverse depths ``d <- d / s``)
  and non-keyframe pose records. Called only at the frontend's safe point (:meth:`LoopService.poll`).
- :meth:`Contributor.long_range_edges`: proximity loops: measured and verified long-range
  observations between the neighbourhoods of two keyframes (None: none, or the family has none).

Families with proximity loops also implement :class:`ProximityContributor` (candidate search and the
global bundle adjustment's hand-over: a snapshot problem solved in the background and its result) and
name their gates (:class:`ProximityGates`, the family's proximity config).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Protocol, runtime_checkable

import numpy as np

from ..loop.records import PoseCorrection

__all__ = ["Contributor", "GlobalBAJob", "KeyframeImage", "PoseCorrection", "ProximityCandidate", "ProximityContributor",
           "ProximityGates", "SolvedGlobalBA", "apply_global_ba_result"]


@dataclass(frozen=True)
class KeyframeImage:
    """What retrieval and verification see of a keyframe."""

    image: np.ndarray  # (H, W) grey uint8
    K: np.ndarray  # (4,) fx, fy, cx, cy of the undistorted pinhole image
    timestamp: float
    depth: Optional[np.ndarray] = None  # (H, W) metres (RGB-D), None otherwise


class SolvedGlobalBA(Protocol):
    """What the service reads of a solved global BA (:attr:`GlobalBAJob.solve`'s result, e.g.
    :class:`fgslam.backend.global_ba.GlobalBAResult`, the dense family's ``DenseGlobalResult``); the
    contributor's own result type carries more."""

    T_WC: np.ndarray  # (F, 4, 4) the problem's keyframe poses
    robust: np.ndarray  # (N,) per edge: 0 where the edge lost its weight


class ProximityCandidate(Protocol):
    """A proximity candidate as the service sees it: keyframe ``fid`` and its flow to the query (px)."""

    fid: int
    flow: float


@dataclass
class GlobalBAJob:
    """A contributor's snapshot for one global bundle adjustment, solved by the service (possibly in
    a background thread, so nothing in it may alias the contributor's live state).

    ``solve()`` returns a result with ``T_WC`` (F, 4, 4) and ``robust`` (N,) (0: the edge lost its
    weight), e.g. :func:`fgslam.backend.global_ba.global_bundle_adjustment` bound to its
    problem. ``kf_ids[i]`` is the keyframe of problem frame i, ``T_WC`` their poses at the snapshot;
    ``is_loop`` marks the problem's loop edges (the gate ``min_ba_inlier_ratio`` acts on them);
    ``context`` is the contributor's own data for :meth:`ProximityContributor.apply_global_ba`.
    ``in_process``: ``solve`` is picklable and needs nothing of the contributor's process (a module-level
    function bound to its data), so the service may run it in a worker process. ``delay_frames``: the
    safe points after its start at which its result is applied, when more than the service's
    ``global_ba_delay_frames`` (a contributor whose global BAs grow with its map asks for more, from
    the snapshot's size, so that tracking does not wait for it there)."""

    solve: Callable[[], SolvedGlobalBA]
    kf_ids: np.ndarray
    T_WC: np.ndarray
    is_loop: np.ndarray
    loop_edges: Optional[dict] = None
    context: object = None  # the contributor's own, opaque to the service
    in_process: bool = False
    delay_frames: int = 0


class ProximityGates(Protocol):
    """The proximity settings the loop service uses (the family's proximity config, e.g.
    ``patch.proximity``; a frontend's ``proximity_gates``)."""

    min_gap: int  # keyframes settled between a candidate and the query at least
    cooldown: int  # keyframes after an accepted loop before the next query
    min_ba_inlier_ratio: float  # share of the loop edges that must keep a weight after the global BA


@runtime_checkable
class Contributor(Protocol):
    """A frontend as the shared services see it (module docstring)."""

    name: str

    def keyframe_image(self, kf_id: int) -> Optional[KeyframeImage]: ...

    def keyframe_pose(self, kf_id: int) -> Optional[np.ndarray]: ...

    def apply_correction(self, correction: PoseCorrection) -> None: ...

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> Optional[dict]: ...


@runtime_checkable
class ProximityContributor(Contributor, Protocol):
    """A contributor with proximity loops and a global bundle adjustment (patch and dense families)."""

    def proximity_candidate(self, query_kf_id: int, candidate_kf_ids: list[int]) -> Optional[ProximityCandidate]:
        """The best candidate among older keyframes (an object with ``fid`` and ``flow``) or None."""
        ...

    def global_ba_job(self, loop_edges: Optional[dict]) -> Optional[GlobalBAJob]:
        """Snapshot of the current map with every stored edge and ``loop_edges`` (None: no map)."""
        ...

    def apply_global_ba(self, job: GlobalBAJob, result: SolvedGlobalBA, keep_loop: np.ndarray) -> None:
        """Hand-over of an accepted result, before the pose correction is applied: structure of the
        keyframes unchanged since the snapshot, loop edges ``keep_loop`` (bool over the job's loop
        edges) into the contributor's store."""
        ...


def apply_global_ba_result(contributor: ProximityContributor, job: GlobalBAJob, result: SolvedGlobalBA, keep: np.ndarray,
                           seconds: float = 0.0) -> None:
    """Apply an accepted global BA: ``contributor.apply_global_ba``, then the correction
    ``U_k = T_new_k T_snapshot_k^-1`` of every snapshot keyframe on its current pose (the proximity
    service's hand-over, and the synchronous path of a contributor that runs a job at once, e.g. the
    dense family's final one)."""
    ids = [int(k) for k in job.kf_ids]
    corr = PoseCorrection.between(dict(zip(ids, job.T_WC)), dict(zip(ids, result.T_WC)), seconds, hold_older=True)
    contributor.apply_global_ba(job, result, keep)
    contributor.apply_correction(corr)
