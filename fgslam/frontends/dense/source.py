"""Measurement sources of the dense frontend: the learned slot and the factory; the interface and the
built-in dense flow are in :mod:`fgslam.frontends.flow` (shared with the pointmap family).

DROID-SLAM's update operator (section 3.2) takes, for every edge ``(i, j)`` of the frame graph, the
correspondence field that the current poses and depths induce (each pixel of ``i``'s 1/8-resolution
grid reprojected into ``j``: :func:`fgslam.factors.reprojection.reproject`) and emits a revision
``r_ij`` and a confidence ``w_ij``, so that ``p*_ij = p_ij + r_ij`` is the target of the dense
bundle adjustment (:mod:`fgslam.factors.dense`), and a per-pixel damping ``eta_i``. A
:class:`DenseSource` does exactly that: :meth:`DenseSource.revise` maps induced fields to
:class:`FlowRevision` s. Per-frame work (image pyramids, feature and context maps) is cached by
:meth:`DenseSource.add_frame` and dropped by :meth:`DenseSource.remove_frame`.

Sources:

- :class:`DenseFlowSource` (built-in, no weights): OpenCV's DIS optical flow on the images resized by
  ``image_scale``, started from the induced flow (warm start), pooled to the grid (block means);
  confidence per pixel and axis from the forward-backward consistency, the photometric error of the
  warped target image and the image gradient energy along each axis (the aperture problem: a uniform
  wall or an edge constrains the flow only across the edge).
- :class:`LearnedDroidSource` (``kind: droid``): DROID's learned update operator (:mod:`fgslam.nets`) from
  the ``droid.pth`` checkpoint, which is not shipped: without one it is a :class:`~fgslam.core.errors.ConfigError`
  naming ``dense.source.checkpoint`` and the built-in alternative; no download is ever attempted.

Grid convention: with stride ``s`` (8), grid pixel ``(x, y)`` covers image pixels ``s x .. s x + s - 1``
and sits at image coordinates ``u = s (x + 1/2) - 1/2`` (pixel centres at integers, as
``PinholeCamera.resized``); its intrinsics are :func:`~fgslam.frontends.flow.grid_intrinsics`. Fields are ``(h, w, 2)`` in grid
pixel coordinates, ``h = H // s``, ``w = W // s``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, Optional

import numpy as np

from ...core.config import MAX_IMAGE_SIDE, ranged
from ...core.errors import ConfigError
from ...nets.config import DroidNetConfig
from ..checkpoints import LearnedSlot, load_learned
from ..flow import DenseFlowConfig, DenseFlowSource, DenseSource, FlowRevision

logger = logging.getLogger(__name__)

__all__ = ["DenseSourceConfig", "LearnedDroidSource", "make_dense_source"]

@dataclass
class DenseSourceConfig:
    """Which dense measurement source, and its settings (YAML section ``dense.source``)."""

    kind: Literal["flow", "droid", "learned"] = "flow"  # built-in dense flow, or DROID's learned update operator (droid; learned: the same)
    checkpoint: Optional[str] = None  # learned: path of the DROID-SLAM weights (droid.pth)
    stride: int = ranged(8, ge=1, le=MAX_IMAGE_SIDE)  # image pixels per grid pixel (DROID: 8)
    flow: DenseFlowConfig = field(default_factory=DenseFlowConfig)
    droid: DroidNetConfig = field(default_factory=DroidNetConfig)  # kind droid: iterations, threads, device


class LearnedDroidSource(DenseSource):
    """DROID-SLAM's learned update operator (feature and context encoders, correlation pyramid, ConvGRU
    emitting revisions r_ij, confidences w_ij and the damping eta; :mod:`fgslam.nets.droid`) run from
    the ``droid.pth`` checkpoint (:mod:`fgslam.nets.sources`). The checkpoint is not shipped with
    fgslam: without ``dense.source.checkpoint`` it is a ConfigError, with a missing or foreign file a
    DataError, each naming the built-in ``dense.source.kind: flow``. ``fb_error`` is NaN (the network
    has no forward-backward check)."""

    name = "droid"
    colour = True  # the official network's input: colour (RGB, fgslam.nets.sources.network_image)

    def __init__(self, checkpoint: str | None, stride: int = 8, config=None):
        from ...nets.sources import DroidRunner  # deferred: the learned networks (fgslam.nets), only for kind droid

        self.stride = int(stride)
        slot = LearnedSlot("DROID-SLAM", "droid.pth", "dense.source.kind=droid", "dense.source.checkpoint",
                           "dense.source.kind=flow")
        self._runner = load_learned(slot, checkpoint, lambda path: DroidRunner(path, config, self.stride))

    def add_frame(self, frame_id: int, image: np.ndarray) -> None:
        self._runner.add_frame(frame_id, image)

    def remove_frame(self, frame_id: int) -> None:
        self._runner.remove_frame(frame_id)

    def revise(self, edges: Sequence[tuple[int, int]], uv_induced: np.ndarray) -> list[FlowRevision]:
        return [FlowRevision(target=t, weight=w, damping=eta, fb_error=np.full(eta.shape, np.nan))
                for t, w, eta in self._runner.revise(edges, uv_induced)]


def make_dense_source(config: DenseSourceConfig) -> DenseSource:
    """The dense measurement source selected by ``config.kind``."""
    if config.kind == "flow":
        return DenseFlowSource(config.flow, config.stride)
    if config.kind in ("droid", "learned"):
        return LearnedDroidSource(config.checkpoint, config.stride, config.droid)
    raise ConfigError(f"dense.source.kind: unknown source {config.kind!r} (expected flow or droid)")
