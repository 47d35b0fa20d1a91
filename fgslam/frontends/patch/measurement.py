"""The patch frontend's measurement interface: :class:`MeasurementSource` and its :class:`Measurement`.

Below both implementations (:mod:`.lk`, the learned slot in :mod:`.source`) and the factory that
picks one (:func:`fgslam.frontends.patch.source.make_source`); see :mod:`.source` for the contract.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np


@dataclass
class Measurement:
    """``uv`` (n, 2) float64 target pixels, ``confidence`` (n,) in [0, 1] (0: rejected),
    ``fb_error`` (n,) forward-backward error in pixels (0 where the source has none)."""

    uv: np.ndarray
    confidence: np.ndarray
    fb_error: np.ndarray


class MeasurementSource(abc.ABC):
    """Where edge measurements come from (built-in Lucas-Kanade or a learned update operator)."""

    name: str = ""
    colour: bool = False  # True: prepare gets the colour image (RGB, Frame.colour_or_grey) instead of the grey one

    @abc.abstractmethod
    def prepare(self, image: np.ndarray):
        """Per-frame features of a grey uint8 image (H, W) (pyramids, feature maps...); a source with
        ``colour`` gets the RGB image (H, W, 3) when the frame has one."""

    @abc.abstractmethod
    def measure(self, src, tgt, uv_src: np.ndarray, uv_pred: np.ndarray) -> Measurement:
        """Measure n patches of the frame with features ``src`` in the frame with features ``tgt``.

        ``uv_src`` (n, 2) patch centres in the source image, ``uv_pred`` (n, 2) their current
        reprojection in the target image (the starting point).
        """

    def pack(self, features):
        """A compact copy of per-frame features kept for long-range (loop) edges; default: as is."""
        return features

    def unpack(self, packed):
        """Features back from :meth:`pack`."""
        return packed

    def measure_batch(self, requests: list) -> list[Measurement]:
        """Measure ``[(src, tgt, uv_src, uv_pred), ...]`` (one frame's edges, grouped by frame
        pair); sources override this to share work between requests."""
        return [self.measure(*request) for request in requests]
