"""Peak-memory estimate of a run, checked before any work (issue 21).

:func:`estimate_run_memory` models the memory a ``fgslam run`` needs from the sizes that set it: the
output image size (after resizing), the frontend's per-frame and per-keyframe data (patches, edges,
1/8-resolution dense maps, pointmaps) and the windows that bound how many of them are kept. The
frontend's parts come from its family's registry entry (:meth:`fgslam.frontends.FrontendFamily.memory_parts`,
next to each family's config), so a family is one registry entry here too.
:func:`check_run_memory` refuses a run whose estimate exceeds ``max_memory_gib`` with a
:class:`~fgslam.core.errors.ConfigError` naming the keys that set the largest part, so that a typo such as
``dataset.resize_scale=4`` on 8K images stops at once instead of being killed by the kernel hours in.

The model is not exact; it is an order-of-magnitude-honest sum of the arrays each part keeps (bytes
per pixel, per edge, per keyframe: the constants below and the families', each with what it counts), calibrated
against measured peak RSS: a patch run on KITTI (1241x376) peaks at about 0.95 GB whatever the
resize (the patch frontend tracks at ``patch.lk.auto_width``), almost all of it the interpreter with
torch, OpenCV and GTSAM loaded.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from ..core.errors import ConfigError
from ..frontends import DEPTH_BYTES, GIB, GREY_BYTES, KEYFRAME_SHARE, MemoryPart, MemorySizes, frontend_family
from ..io.datasets import Dataset
from .config import SlamConfig

logger = logging.getLogger(__name__)

#: B: the interpreter with numpy, torch, OpenCV and GTSAM imported (measured: 0.93 GB RSS)
RUNTIME_BYTES = 1 * GIB
#: B per output pixel and camera: the two float32 remap tables of the undistortion (map x, map y)
REMAP_BYTES_PER_PIXEL = 8
#: images of one frame alive at once: the raw image, its remapped output, the runner's frame and a
#: frontend's working copy, and the two frames the reader holds ahead (fgslam.io.live.ReadAhead)
FRAMES_IN_FLIGHT = 6
#: B per raw pixel as read (colour, 8 bit)
RAW_BYTES_PER_PIXEL = 3
#: B per output pixel of a frame's colour image and of its right grey image (grey and depth:
#: :data:`fgslam.frontends.GREY_BYTES`, :data:`~fgslam.frontends.DEPTH_BYTES`)
RGB_BYTES, RIGHT_BYTES = 3, 1

#: B per ORB feature of a keyframe in the classical loop closer (descriptor, keypoint, BoW entries, 3-D point)
ORB_FEATURE_BYTES = 128


@dataclass
class MemoryEstimate:
    """Estimated peak memory of a run, by part."""

    parts: list[MemoryPart]

    @property
    def total_bytes(self) -> float:
        return float(sum(p.bytes for p in self.parts))

    @property
    def total_gib(self) -> float:
        return self.total_bytes / GIB

    def largest(self) -> MemoryPart:
        return max(self.parts, key=lambda p: p.bytes)

    def text(self) -> str:
        return ", ".join(f"{p.name} {p.gib:.2f}" for p in sorted(self.parts, key=lambda p: -p.bytes))


def estimate_run_memory(config: SlamConfig, width: int, height: int, frames: int,
                        raw_size: tuple[int, int] | None = None) -> MemoryEstimate:
    """Peak memory of running ``config`` on ``frames`` frames of ``width x height`` output images
    (after resizing and cropping; ``raw_size``: the images as read, default the output size).

    A pure function of the config and the sizes: no dataset, no allocation."""
    raw_w, raw_h = raw_size if raw_size is not None else (width, height)
    px = float(width) * float(height)
    ds = config.dataset
    size_keys = ds.resize_keys()
    stereo, rgbd = config.sensor == "stereo", config.sensor == "rgbd"
    cams = 2 if stereo else 1
    frame_px_bytes = (GREY_BYTES + RGB_BYTES * (ds.load_rgb and config.needs_colour()) * cams
                      + DEPTH_BYTES * rgbd + RIGHT_BYTES * stereo)
    parts = [
        MemoryPart("runtime", RUNTIME_BYTES),
        MemoryPart(f"images ({width}x{height})",
                   px * REMAP_BYTES_PER_PIXEL * cams
                   + FRAMES_IN_FLIGHT * (px * frame_px_bytes + float(raw_w) * raw_h * RAW_BYTES_PER_PIXEL * cams),
                   size_keys),
    ]
    sizes = MemorySizes(width, height, frames, stereo, rgbd, config.loop_closure.mode, size_keys)
    parts += frontend_family(config.frontend).memory_parts(config.family_section(), sizes)
    if config.loop_closure.mode in ("classical", "both"):
        n = config.loop_closure.bow.orb.n_features
        parts.append(MemoryPart("loop-closure keyframes", KEYFRAME_SHARE * frames * n * ORB_FEATURE_BYTES,
                                [f"loop_closure.bow.orb.n_features={n}"]))
    return MemoryEstimate(parts)


def check_run_memory(config: SlamConfig, dataset: Dataset) -> MemoryEstimate:
    """:func:`estimate_run_memory` of the run config ``config`` for ``dataset`` (its output image size, raw image size and frame
    count, all known once it is open), refused with a ConfigError naming the keys of the largest
    part when it exceeds ``max_memory_gib``; returns the estimate otherwise."""
    calib, raw = dataset.calibration, dataset.raw_calibration
    estimate = estimate_run_memory(config, int(calib.width), int(calib.height), len(dataset),
                                   None if raw is None else (int(raw.width), int(raw.height)))
    logger.debug("estimated peak memory %.2f GiB (%s)", estimate.total_gib, estimate.text())
    if estimate.total_gib > config.max_memory_gib:
        big = estimate.largest()
        keys = ", ".join(big.keys) if big.keys else "the run's sizes"
        raise ConfigError(
            f"estimated peak memory {estimate.total_gib:.1f} GiB exceeds max_memory_gib={config.max_memory_gib:g} "
            f"(largest part: {big.name} {big.gib:.1f} GiB, set by {keys}); lower those keys or raise "
            f"max_memory_gib (parts in GiB: {estimate.text()})")
    return estimate
