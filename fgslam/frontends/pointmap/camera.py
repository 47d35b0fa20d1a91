"""The pointmap frontend's working resolution: frames resized so that the width is at most
``image_width``, intrinsics scaled alike (also used by :mod:`.mix`)."""

from __future__ import annotations

import cv2
import numpy as np

from ...core.errors import ConfigError


class WorkingCamera:
    """The frames at the working resolution: ``scale`` so that the width is at most ``image_width``
    (never enlarged), ``K`` ``(4,)`` scaled with the pixel-centre convention, stereo ``baseline``."""

    def __init__(self, calibration, image_width: int, sensor_mode: str):
        W, H = int(calibration.width), int(calibration.height)
        scale = 1.0 if image_width <= 0 or W <= image_width else image_width / W
        self.W, self.H = int(round(W * scale)), int(round(H * scale))
        self.full = (W, H)
        sx, sy = self.W / W, self.H / H
        fx, fy, cx, cy = (float(k) for k in calibration.K)
        self.K = np.array([fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5])
        self.baseline = None
        if sensor_mode == "stereo":
            if calibration.right is None or calibration.T_CLCR is None:
                raise ConfigError("sensor mode stereo needs a calibration with a right camera and T_CLCR")
            self.baseline = float(np.linalg.norm(np.asarray(calibration.T_CLCR)[:3, 3]))

    def image(self, img: np.ndarray | None) -> np.ndarray | None:
        if img is None or (img.shape[1], img.shape[0]) == (self.W, self.H):
            return img
        return cv2.resize(img, (self.W, self.H), interpolation=cv2.INTER_AREA)

    def depth(self, depth: np.ndarray | None) -> np.ndarray | None:
        if depth is None or (depth.shape[1], depth.shape[0]) == (self.W, self.H):
            return depth
        return cv2.resize(np.asarray(depth, np.float32), (self.W, self.H), interpolation=cv2.INTER_NEAREST)
