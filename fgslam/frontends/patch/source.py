"""Measurement sources of the patch frontend: the learned DPVO slot and the factory (the interface
is :mod:`.measurement`).

A source turns an edge (i, k, j) of the patch graph, given the patch centre ``uv_src`` in frame i
and its current reprojection ``uv_pred`` in frame j, into a target ``uv`` (the BA observation;
``uv - uv_pred`` is DPVO's residual update Delta_ikj) and a confidence in [0, 1] (DPVO's weight
w_ikj; 0 marks a rejected measurement). Sources cache per-frame work in the object returned by
:meth:`MeasurementSource.prepare`, which the frontend keeps only for frames inside the patch lifetime.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ...core.errors import ConfigError
from ...nets.sources import DpvoRunner
from ..checkpoints import LearnedSlot, load_learned
from .lk import LKSource
from .measurement import Measurement, MeasurementSource

if TYPE_CHECKING:
    from .config import PatchConfig


class LearnedDPVOSource(MeasurementSource):
    """DPVO's learned update operator (patch correlation + recurrent update emitting Delta_ikj and
    w_ikj; :mod:`fgslam.nets.dpvo`) run from the ``dpvo.pth`` checkpoint (:mod:`fgslam.nets.sources`).
    The checkpoint is not shipped with fgslam; without it construction fails with a ConfigError /
    DataError naming the file and ``source: lk``. The confidence is the smaller of the two per-axis
    weights; ``fb_error`` is 0 (no forward-backward check). Long-range (loop) edges keep only the image
    (:meth:`pack`) and recompute the maps."""

    name = "dpvo"
    colour = True  # the official network's input: colour (BGR, fgslam.nets.sources.network_image)

    def __init__(self, checkpoint: str | None, config=None):
        slot = LearnedSlot("DPVO", "dpvo.pth", "patch.source=dpvo", "patch.checkpoint", "patch.source=lk")
        self._runner = load_learned(slot, checkpoint, lambda path: DpvoRunner(path, config))

    def prepare(self, image: np.ndarray):
        return self._runner.prepare(image)

    def pack(self, features):
        return self._runner.pack(features)

    def unpack(self, packed):
        return self._runner.unpack(packed)

    def measure(self, src, tgt, uv_src: np.ndarray, uv_pred: np.ndarray) -> Measurement:
        return self.measure_batch([(src, tgt, uv_src, uv_pred)])[0]

    def measure_batch(self, requests: list) -> list[Measurement]:
        return [Measurement(uv=uv, confidence=conf, fb_error=np.zeros(len(conf)))
                for uv, conf in self._runner.measure_batch(requests)]


def make_source(config: "PatchConfig") -> MeasurementSource:
    """The measurement source selected by ``config.source`` (``lk``, or ``dpvo`` = ``learned``)."""
    if config.source == "lk":
        return LKSource(config.lk, config.graph.patch_size * config.graph.patch_stride)
    if config.source in ("dpvo", "learned"):
        return LearnedDPVOSource(config.checkpoint, config.dpvo)
    raise ConfigError(f"patch.source: unknown source {config.source!r} (expected lk or dpvo)")
