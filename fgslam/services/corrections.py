"""Correction hooks between the run's services and a contributor: :class:`ObservedContributor`, a
contributor whose map corrections pass through the IMU service's hooks on their way in."""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from ..contracts.contributor import Contributor, GlobalBAJob, KeyframeImage, PoseCorrection

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

    def proximity_candidate(self, query_kf_id: int, candidate_kf_ids: list[int]) -> object:
        return self._contributor.proximity_candidate(query_kf_id, candidate_kf_ids)

    def global_ba_job(self, loop_edges: Optional[dict]) -> Optional[GlobalBAJob]:
        return self._contributor.global_ba_job(loop_edges)

    def apply_global_ba(self, job: GlobalBAJob, result: object, keep_loop: np.ndarray) -> None:
        self._contributor.apply_global_ba(job, result, keep_loop)

    def apply_correction(self, correction: PoseCorrection) -> None:
        if self._adapt is not None:
            correction = self._adapt(correction)
        self._contributor.apply_correction(correction)
        for listener in self._listeners:
            listener(correction)
