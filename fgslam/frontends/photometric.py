"""Photometric models of the images the built-in measurement sources track (``patch.lk.photometric``,
``dense.source.flow.photometric``): ``raw`` assumes brightness constancy; ``gain`` undoes a gain per
image: each image is scaled so that its median grey level is the first image's. A real camera's
auto-exposure and a stereo pair's unequal gains scale an image, which cancels here, so tracking and
flow hold through them (issue 38: a road render with auto-exposure, ``driving_stereo`` 0.347 ->
0.041 m). The median, not the mean and contrast, sets the gain: it moves least when the view's content
changes, and a steady camera's images are left nearly as they are (the sources' thresholds in grey
levels, such as Lucas-Kanade's ``min_eigen``, keep their meaning)."""

from __future__ import annotations

from typing import Literal

import numpy as np

#: the photometric models a source config accepts
PhotometricModel = Literal["raw", "gain"]


class BrightnessModel:
    """``model`` applied to a source's images, in the order it prepares them: ``raw`` returns them
    unchanged; ``gain`` scales each so that its median plus ``floor`` grey levels is the first image's
    (the floor keeps a nearly black image from being amplified into noise), clipped to 8 bits."""

    def __init__(self, model: str, floor: float):
        self.model = model
        self.floor = float(floor)
        self.reference: float | None = None  # median plus floor of the first image

    def __call__(self, image: np.ndarray) -> np.ndarray:
        if self.model != "gain":
            return image
        f = image.astype(np.float32)
        level = float(np.median(f)) + self.floor
        if self.reference is None:
            self.reference = level
        return np.clip(np.rint(f * (self.reference / level)), 0, 255).astype(np.uint8)
