"""How the run's services move the map: the corrections they build (:func:`uniform_correction`,
:func:`pose_graph_correction`), their route to the contributors that take them
(:func:`route_correction`, :func:`takes_corrections`; the run's route is the backend's
``contributors``, :meth:`fgslam.backend.graph.Backend.set_contributors`) and
:class:`ObservedContributor`, a contributor whose map corrections pass through the IMU service's hooks
on their way in."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Callable, Optional, TypeGuard

import numpy as np

from ..contracts.contributor import (Contributor, GlobalBAJob, KeyframeImage, PoseCorrection, ProximityCandidate,
                                     SolvedGlobalBA)

if TYPE_CHECKING:  # the backend pulls torch and gtsam: annotations only (a run's config checks the plugins without them)
    from ..backend.graph import Backend, CorrectionTarget

CorrectionHook = Callable[[PoseCorrection], PoseCorrection]
CorrectionListener = Callable[[PoseCorrection], None]


class ObservedContributor:
    """A contributor whose map corrections pass through the run's correction hooks (the IMU service:
    :meth:`fgslam.services.imu.ImuService.adapt_correction` and ``on_correction``): ``adapt``
    (``correction -> correction``) may rewrite a correction before the contributor applies it (a
    monocular-inertial map whose scale is fixed takes loop corrections as SE(3)); each listener
    sees the correction the contributor applied, right after it (the IMU velocities follow the poses).
    Every other member of the contributor contract (:mod:`fgslam.contracts.contributor`, proximity
    members included when the contributor has them) goes to the contributor unchanged."""

    def __init__(self, contributor: Contributor, adapt: Optional[CorrectionHook] = None,
                 listeners: tuple[CorrectionListener, ...] = ()) -> None:
        self._contributor = contributor
        self._adapt = adapt
        self._listeners = tuple(listeners)

    @property
    def wrapped(self) -> Contributor:
        """The contributor itself."""
        return self._contributor

    @property
    def name(self) -> str:
        return self._contributor.name

    def keyframe_image(self, kf_id: int) -> Optional[KeyframeImage]:
        return self._contributor.keyframe_image(kf_id)

    def keyframe_pose(self, kf_id: int) -> Optional[np.ndarray]:
        return self._contributor.keyframe_pose(kf_id)

    def long_range_edges(self, query_kf_id: int, candidate_kf_id: int) -> Optional[dict]:
        return self._contributor.long_range_edges(query_kf_id, candidate_kf_id)

    def proximity_candidate(self, query_kf_id: int, candidate_kf_ids: list[int]) -> Optional[ProximityCandidate]:
        return self._contributor.proximity_candidate(query_kf_id, candidate_kf_ids)

    def global_ba_job(self, loop_edges: Optional[dict]) -> Optional[GlobalBAJob]:
        return self._contributor.global_ba_job(loop_edges)

    def apply_global_ba(self, job: GlobalBAJob, result: SolvedGlobalBA, keep_loop: np.ndarray) -> None:
        self._contributor.apply_global_ba(job, result, keep_loop)

    def apply_correction(self, correction: PoseCorrection) -> None:
        if self._adapt is not None:
            correction = self._adapt(correction)
        self._contributor.apply_correction(correction)
        for listener in self._listeners:
            listener(correction)


def takes_corrections(candidate: object) -> TypeGuard[CorrectionTarget]:
    """Whether ``candidate`` (the run's frontend or its contributor) takes map corrections: it has
    ``apply_correction`` (a frontend without the contributor contract has not)."""
    return callable(getattr(candidate, "apply_correction", None))


def route_correction(backend: Backend, correction: PoseCorrection, targets: Sequence[CorrectionTarget]) -> None:
    """Move the map by ``correction``: each of ``targets`` applies it (moves its keyframes, folds the
    scale into its structure); without targets every keyframe pose of ``backend`` is set
    (:meth:`~fgslam.backend.graph.Backend.move_keyframes`)."""
    if targets:
        for target in targets:
            target.apply_correction(correction)
        return
    backend.move_keyframes(correction)


def uniform_correction(backend: Backend, U: np.ndarray, fold_scale: bool) -> PoseCorrection:
    """The correction moving every keyframe of ``backend`` by the same Sim(3) ``U`` (4x4
    ``[[s R, t], [0, 1]]``), its scale folded into the structure with ``fold_scale`` (a contributor
    takes it)."""
    s = float(np.cbrt(np.linalg.det(U[:3, :3])))
    ids = list(backend.keyframe_ids)
    return PoseCorrection(T_update={k: U for k in ids}, scale={k: s for k in ids},
                          T_WC_new={k: U @ backend.pose_matrix(k) for k in ids}, loops=[], fold_scale=fold_scale,
                          n_accepted=0, solve_time_s=0.0)


def pose_graph_correction(backend: Backend, T_WC_new: Mapping[int, np.ndarray], fold_scale: bool,
                          solve_time_s: float = 0.0) -> PoseCorrection:
    """The correction taking each keyframe of ``T_WC_new`` from its current pose in ``backend`` there,
    the scale change folded into the structure with ``fold_scale``."""
    return PoseCorrection.between({k: backend.pose_matrix(k) for k in T_WC_new}, dict(T_WC_new), solve_time_s,
                                  fold_scale=fold_scale)
