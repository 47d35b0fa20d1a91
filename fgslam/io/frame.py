"""The one frame type every dataset loader yields.

Conventions
-----------
- ``timestamp``: float64 seconds (EuRoC nanoseconds / 1e9; KITTI ``times.txt``; 7-Scenes and
  TartanAir, which store no times, ``index / nominal rate``).
- ``image``: grey ``uint8`` ``(H, W)``: what SLAM frontends consume. ``rgb``: the colour image
  ``(H, W, 3)`` ``uint8`` in **RGB** order (not OpenCV's BGR) for colour sources, else None. Loaded
  only when the run needs colour (PLY colours, a learned measurement source: ``dataset_config_for``).
- ``image_right``: grey ``uint8`` ``(H, W)`` of the (rectified) right camera, or None; ``rgb_right``:
  its colour image (RGB) when ``rgb`` is loaded, else None.
- ``depth``: float32 ``(H, W)`` z-depth in **metres** in the output left camera frame;
  **0.0 marks an invalid pixel** (no NaN, no inf, no negative value ever leaves a loader).
- ``imu``: the IMU samples with ``t_prev < t <= timestamp`` where ``t_prev`` is the timestamp of
  the previous frame of the dataset (after start/stride); the first frame gets an empty block.
  None when the source has no IMU.
- All images are undistorted / rectified / resized / cropped according to the dataset config;
  ``calibration`` describes them (distortion ``none``).
- ``T_WC_gt``: ``(4, 4)`` float64 ground-truth camera-to-world pose of the output left camera, or
  None when the frame has no ground truth (never extrapolated).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.errors import DataError
from .calibration import Calibration


@dataclass(frozen=True)
class ImuSamples:
    """IMU measurements in the IMU (body) frame.

    Attributes:
        timestamps: ``(M,)`` float64 seconds, increasing.
        gyro: ``(M, 3)`` float64 angular velocity, rad/s.
        accel: ``(M, 3)`` float64 specific force, m/s^2.
    """

    timestamps: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])


@dataclass
class Frame:
    """One time instant of a sequence (see the module docstring for every convention).

    Attributes:
        index: position of the frame in the dataset (0 .. len-1, after start/end/stride).
        source_index: index of the frame in the raw sequence.
        timestamp: seconds.
        image: grey uint8 ``(H, W)``.
        calibration: calibration of ``image`` (and ``image_right``).
        rgb: RGB uint8 ``(H, W, 3)`` or None.
        image_right: grey uint8 ``(H, W)`` or None.
        rgb_right: RGB uint8 ``(H, W, 3)`` of the right camera or None.
        depth: float32 metres ``(H, W)``, 0 = invalid, or None.
        imu: IMU samples since the previous frame, or None.
        T_WC_gt: ground-truth camera-to-world ``(4, 4)`` or None.
        path: the file the left image was read from (None for video frames).
    """

    index: int
    source_index: int
    timestamp: float
    image: np.ndarray
    calibration: Calibration
    rgb: Optional[np.ndarray] = None
    image_right: Optional[np.ndarray] = None
    depth: Optional[np.ndarray] = None
    imu: Optional[ImuSamples] = None
    T_WC_gt: Optional[np.ndarray] = None
    path: Optional[Path] = None
    rgb_right: Optional[np.ndarray] = None

    def colour_or_grey(self, right: bool = False) -> Optional[np.ndarray]:
        """The colour image (RGB) of the left (or right) camera when the frame carries one, else its grey
        image: what a learned measurement source is fed (a grey dataset's image stands for all three
        channels, as ``cv2.imread`` repeats a grey file's channel)."""
        colour = self.rgb_right if right else self.rgb
        if colour is not None:
            return colour
        return self.image_right if right else self.image

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])


class FrameReadError(DataError):
    """One frame could not be read (unreadable/corrupt file); iteration skips and counts it."""


class FrameSizeError(FrameReadError):
    """One frame (or its right image or depth map) is not of the calibration's size; iteration skips
    and counts it as a frame of the wrong size (not as unreadable)."""
