"""The contract between the SLAM runner and a frontend family (dense, patch, pointmap).

A frontend consumes :class:`fgslam.io.frame.Frame` objects one at a time, owns its measurement
source and its slice of the map, and reports per-frame status. The runner (``fgslam.slam``) is
frontend-agnostic: it iterates a dataset, calls :meth:`Frontend.process`, and at the end asks for
the poses of every input frame with :meth:`Frontend.trajectory`.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

#: How a frame's pose was obtained.
PoseSource = Literal["initializing", "tracked", "motion_model", "relocalized"]

SensorMode = Literal["mono", "stereo", "rgbd"]


@dataclass
class FrameStatus:
    """What :meth:`Frontend.process` reports for one frame.

    Attributes:
        index: the frame's ``Frame.index``.
        timestamp: seconds.
        T_WC: current camera-to-world estimate (4x4 float64; for monocular the scale is the map's),
            or None while the system is initialising and has no pose yet.
        pose_source: ``initializing`` (waiting for parallax), ``tracked`` (visual measurements),
            ``motion_model`` (tracking failed; pose predicted - counted as a failure),
            ``relocalized``.
        is_keyframe: whether the frame is currently kept as a keyframe.
        num_valid: number of valid measurements (patches / pixels / matches) used for this frame.
        events: human-readable notes (initialised, tracking lost, keyframe removed, ...).
    """

    index: int
    timestamp: float
    T_WC: np.ndarray | None
    pose_source: PoseSource
    is_keyframe: bool = False
    num_valid: int = 0
    events: list[str] = field(default_factory=list)


class Frontend(abc.ABC):
    """A frontend family. Constructed by the runner with its config section and the sensor mode."""

    #: registry name (``dense``, ``patch``, ``pointmap``)
    name: str = ""

    @abc.abstractmethod
    def process(self, frame) -> FrameStatus:
        """Consume one frame (in order) and return its status. Never raises on a tracking failure:
        a failure is reported as ``pose_source="motion_model"`` with an event."""

    @abc.abstractmethod
    def trajectory(self) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Final poses of every processed frame: ``(timestamps (N,), T_WC (N, 4, 4), pose_sources)``
        after the last optimisation (non-keyframes from their stored pose relative to a keyframe).
        Frames that never got a pose (initialisation never succeeded) are omitted."""

    @abc.abstractmethod
    def num_keyframes(self) -> int:
        """Keyframes currently in the map."""

    def finish(self) -> None:
        """Called once after the last frame (final global optimisation, flush background work)."""

    def stage_times(self) -> dict[str, float]:
        """Accumulated wall time in seconds per stage (e.g. ``flow``, ``ba``, ``bookkeeping``)."""
        return {}

    def keyframe_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Optional map points ``(X_W (M, 3) float, colour (M, 3) uint8)`` for PLY export."""
        return None

    def keyframe_depths(self) -> dict[int, tuple[float, np.ndarray, np.ndarray | None]] | None:
        """Optional dense depth per keyframe: kf id -> ``(timestamp, depth (H, W) float32 in the map's
        units at image resolution (0: none), confidence (H, W) in [0, 1] or None)``; the runner writes
        them as 16-bit PNGs with ``output.write_depth``."""
        return None

    def loop_summary(self) -> dict | None:
        """Optional loop-closure counts for ``summary.json`` (loops verified / accepted, corrections
        applied, relocalisations, ...); None when the frontend runs no loop closure."""
        return None
