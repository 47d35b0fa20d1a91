"""What tracking says of a frame (:class:`TrackResult`) and a map's keyframes (:class:`Keyframes`): plain
records of the public API (``fgslam.TrackResult``), shared by a run (:class:`fgslam.run.session.Slam`) and
localisation in a stored map (:class:`fgslam.localize.localizer.Localizer`).

Frames and units: ``T_WC`` is the 4x4 camera-to-world transform, metres (monocular runs: the map's own
scale); times are seconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass(frozen=True)
class TrackResult:
    """What :meth:`Slam.track` says of one frame.

    Attributes:
        index: the frame's index: ``Frame.index`` (its position in the dataset) for a loader's frame, the
            number of frames tracked before it for ``Slam.track``.
        t: the frame's time, seconds.
        T_WC: ``(4, 4)`` float64 camera-to-world pose, metres (monocular: the map's scale), or None
            while the system initialises.
        status: ``initializing``, ``tracked``, ``motion_model`` (tracking failed: a prediction),
            ``relocalized`` or ``imu`` (visual tracking failed, the IMU's prediction); in a stored map
            (:class:`~fgslam.localize.localizer.Localizer`): ``tracked``, ``relocalised`` or ``not_localised``.
        keyframe: whether the frame is kept as a keyframe (now; a later frame may remove it).
        num_valid: the valid measurements (patches, pixels, matches) the frame's pose used.
        reason: why there is no pose, or why the pose is a prediction (None when tracked).
        events: the frontend's notes on the frame (initialised, keyframe removed, ...).
        process_s: wall seconds the system spent on the frame.
        keyframe_id: localisation: the map keyframe the pose was verified against (None: none).
        position_std: localisation: the standard deviation of the camera position for 1 px of pixel noise,
            over the median depth of the points it used (scale-free conditioning; None: no pose).
        new_map: the run lost its track and started a new map at this frame: later poses are not tied to
            the earlier ones (``Slam.save_map`` keeps each map as a session of its own).
    """

    index: int
    t: float
    T_WC: Optional[np.ndarray]
    status: str
    keyframe: bool
    num_valid: int
    reason: Optional[str]
    events: tuple[str, ...] = ()
    process_s: float = 0.0
    keyframe_id: Optional[int] = None
    position_std: Optional[float] = None
    new_map: bool = False

    @property
    def tracked(self) -> bool:
        """A pose from the visual measurements (tracked or relocalised), not a prediction."""
        return self.T_WC is not None and self.status in ("tracked", "relocalized", "relocalised")


@dataclass(frozen=True)
class Keyframes:
    """The keyframes of a run: ``ids (K,)`` int64, ``t (K,)`` seconds, ``T_WC (K, 4, 4)`` camera-to-world."""

    ids: np.ndarray
    t: np.ndarray
    T_WC: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.shape[0])
