"""A stored map that a run relocalises in while it goes on (``fgslam run --map``, metric sensors).

The run's keyframes are localised in the stored map one after the other as they are handed to the loop
service (:class:`MapLocalizer`, as :func:`~fgslam.localize.merge.merge_recording` does at the end of the
run). When the run loses its track, the lost frame is localised in the stored map too, and the transform
between the run's frame and the map's, fitted on the keyframes localised so far (their latest poses; the
consistent ones, :func:`~fgslam.localize.merge.fit_transform`), puts it in the run's frame: the anchor of
the new map, as a relocalisation in the run's own keyframe database would be. So a run that loses its
track relocalises against the loaded map too, before it starts a new map in a frame of its own.

The fit uses the keyframes of the run's first map only (every restart freezes it, a relocalised one
too): a map started after a lost track that was not relocalised is in a frame of its own until it
rejoins, and its keyframes would mix the two frames. Metric runs and maps only (RGB-D, stereo): the
transform is rigid.
"""

from __future__ import annotations

import logging
from typing import Callable, Optional

import numpy as np

from ..export.mapfile import StoredMap
from .localizer import LocalizeConfig, MapLocalizer
from .merge import Localised, fit_transform

logger = logging.getLogger(__name__)


class LoadedMapLink:
    """The run's link to a loaded stored map (module docstring).

    Args:
        stored: the loaded map (its camera checked against the run's before).
        config: its localisation settings (``merge``: the fit's gates).
    """

    def __init__(self, stored: StoredMap, config: LocalizeConfig | None = None):
        self.config = config or LocalizeConfig()
        self.localizer = MapLocalizer(stored, self.config)
        self._stored_position = {int(kf): i for i, kf in enumerate(stored.kf_ids)}
        self._localised: dict[int, tuple[np.ndarray, int]] = {}  # run keyframe id -> (T_MC, stored position)
        self.frozen = False  # the run started a second map: no more keyframes for the fit
        self.keyframes_tried = 0

    @property
    def localised(self) -> dict[int, np.ndarray]:
        """``T_MC`` (4x4, the map's frame) of each run keyframe localised in the map, by keyframe id."""
        return {k: T_MC for k, (T_MC, _) in self._localised.items()}

    def add_keyframe(self, kf_id: int, image: np.ndarray) -> bool:
        """Localise the run's keyframe ``kf_id`` (its image) in the stored map; True when it localised."""
        if self.frozen:
            return False
        self.keyframes_tried += 1
        res = self.localizer.localize(image)
        if res.T_WC is None:
            return False
        self._localised[int(kf_id)] = (np.asarray(res.T_WC, np.float64), self._stored_position[int(res.kf_id)])
        return True

    def map_reset(self) -> None:
        """The run starts a new map: the fit keeps the keyframes of the first one (module docstring)."""
        self.frozen = True
        self.localizer.last = self.localizer.prev = None

    def transform(self, pose_of: Callable[[int], Optional[np.ndarray]]) -> np.ndarray | None:
        """``S_MR`` (4x4, the run's frame to the map's) fitted on the localised keyframes at their poses
        ``pose_of(kf_id)`` (the run's latest ``T_WC``; None: no longer a keyframe), or None with too few
        consistent ones."""
        pairs: list[Localised] = []
        for k, (T_MC, i) in sorted(self._localised.items()):
            T_WC = pose_of(k)
            if T_WC is not None:
                pairs.append((k, T_MC, np.asarray(T_WC, np.float64), i))
        fit = fit_transform(pairs, self.config.merge, metric=True)
        return None if fit is None else fit[0]

    def relocalize(self, image: np.ndarray, pose_of: Callable[[int], Optional[np.ndarray]]) -> tuple[int, np.ndarray] | None:
        """``(stored keyframe id, T_WC in the run's frame)`` of a lost frame's ``image`` localised in the
        stored map, or None (not localised there, or the run's frame not yet tied to the map's);
        ``pose_of``: the run's latest keyframe poses (:meth:`transform`)."""
        S_MR = self.transform(pose_of)
        if S_MR is None:
            return None
        self.localizer.last = self.localizer.prev = None  # a lost frame: retrieval and verification
        res = self.localizer.localize(image)
        if res.T_WC is None:
            return None
        logger.info("relocalised in the loaded map (on the map's keyframe %d, %d inliers)", res.kf_id, res.inliers)
        return int(res.kf_id), np.linalg.inv(S_MR) @ np.asarray(res.T_WC, np.float64)
