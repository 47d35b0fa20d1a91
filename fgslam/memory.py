"""Peak-memory estimate of a run, checked before any work (issue 21).

:func:`estimate_run_memory` models the memory a ``fgslam run`` needs from the sizes that set it: the
output image size (after resizing), the frontend's per-frame and per-keyframe data (patches, edges,
1/8-resolution dense maps, pointmaps) and the windows that bound how many of them are kept.
:func:`check_run_memory` refuses a run whose estimate exceeds ``max_memory_gib`` with a
:class:`~fgslam.errors.ConfigError` naming the keys that set the largest part, so that a typo such as
``dataset.resize_scale=4`` on 8K images stops at once instead of being killed by the kernel hours in.

The model is not exact; it is an order-of-magnitude-honest sum of the arrays each part keeps (bytes
per pixel, per edge, per keyframe: the constants below, each with what it counts), calibrated
against measured peak RSS: a patch run on KITTI (1241x376) peaks at about 0.95 GB whatever the
resize (the patch frontend tracks at ``patch.lk.auto_width``), almost all of it the interpreter with
torch, OpenCV and GTSAM loaded.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .errors import ConfigError

if TYPE_CHECKING:
    from .io.datasets import Dataset

logger = logging.getLogger(__name__)

GIB = 1024**3

#: B: the interpreter with numpy, torch, OpenCV and GTSAM imported (measured: 0.93 GB RSS)
RUNTIME_BYTES = 1 * GIB
#: B per output pixel and camera: the two float32 remap tables of the undistortion (map x, map y)
REMAP_BYTES_PER_PIXEL = 8
#: images of one frame alive at once: the raw image, its remapped output, the runner's frame and a
#: frontend's working copy
FRAMES_IN_FLIGHT = 4
#: B per raw pixel as read (colour, 8 bit)
RAW_BYTES_PER_PIXEL = 3
#: B per output pixel of a frame's streams: grey image, colour image, float32 depth, right grey image
GREY_BYTES, RGB_BYTES, DEPTH_BYTES, RIGHT_BYTES = 1, 3, 4, 1
#: pyramid overhead of an image pyramid (1 + 1/4 + 1/16 + ...)
PYRAMID_FACTOR = 4 / 3
#: B per pixel of a float32 image processing (corner score: gradients, structure tensor, response)
SCORE_BYTES_PER_PIXEL = 24

#: B per patch-graph edge: its bookkeeping rows (ids, uv, confidence, weights ~ 70 B) plus the
#: bundle adjustment's linearisation (float64 residuals and 2 x 13 Jacobian entries, ~ 300 B)
PATCH_EDGE_BYTES = 400
#: B per edge of the inactive-edge store (uv_src, uv, confidence, inverse depth, ids)
INACTIVE_EDGE_BYTES = 100
#: B per patch of a graph frame (centre, inverse depths, colour, per-patch state)
PATCH_BYTES = 64
#: B per pixel of a keyframe image kept as PNG for proximity loop edges (compressed grey)
PNG_BYTES_PER_PIXEL = 0.5

#: B per grid pixel of a dense keyframe: inverse depth, confidence, flow-distance and source maps
#: (float32, ~ 8 channels)
DENSE_KEYFRAME_BYTES_PER_CELL = 32
#: B per grid pixel of a dense edge: flow target, weights, residuals and the float32 Jacobian rows of
#: the dense bundle adjustment (2 rows x (6 + 6 + 1) entries + 4 targets/weights, float64), and the
#: induced field an active edge keeps for the local BA's re-measurement test (2 x float32)
DENSE_EDGE_BYTES_PER_CELL = 248
#: B per grid pixel of a learned (DROID) keyframe: feature and context maps (128 + 256 float32 channels)
DROID_KEYFRAME_BYTES_PER_CELL = 384 * 4
#: B per (grid pixel)^2 of one edge's all-pairs correlation volume (float32, all pyramid levels)
DROID_CORRELATION_BYTES = 4 * PYRAMID_FACTOR
#: B per image pixel of the dense optical flow (DIS) at ``dense.source.flow.image_scale``: two grey
#: pyramids, the float32 flow field and its backward check
DENSE_FLOW_BYTES_PER_PIXEL = 40

#: B per pointmap pixel of a keyframe: canonical float32 points (12 B), confidence (4 B), colour (3 B)
POINTMAP_KEYFRAME_BYTES_PER_PIXEL = 20
#: Share of the frames that become keyframes, for what grows with the keyframes (pointmap keyframes,
#: loop-closure descriptors): at most 8 % measured (pointmap 52 of 723 hand-held frames; patch on
#: KITTI and 7-Scenes 5-30 % but it keeps no per-keyframe image), 25 % for a margin. Assuming every
#: frame a keyframe refused honest long sequences (10,000 frames at 512 px over 16 GiB).
KEYFRAME_SHARE = 0.25
#: B per pointmap pixel of a frame whose source caches stay loaded: two 16-dimensional float32
#: descriptors with confidences, the flow / depth maps
POINTMAP_SOURCE_BYTES_PER_PIXEL = 160
#: B per pointmap pixel of the matching and tracking of one frame (per-pixel LM states, rays, indices)
POINTMAP_MATCHING_BYTES_PER_PIXEL = 200

#: B per ORB feature of a keyframe in the classical loop closer (descriptor, keypoint, BoW entries, 3-D point)
ORB_FEATURE_BYTES = 128


@dataclass
class MemoryPart:
    """One part of the estimate: bytes and the config keys (with their values) that set them."""

    name: str
    bytes: float
    keys: list[str] = field(default_factory=list)

    @property
    def gib(self) -> float:
        return self.bytes / GIB


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


def _fit_width(width: int, height: int, target: int) -> tuple[int, int]:
    """``width x height`` resized to at most ``target`` wide (aspect kept; 0: unchanged)."""
    if target <= 0 or target >= width:
        return width, height
    return target, max(1, round(height * target / width))


def estimate_run_memory(config, width: int, height: int, frames: int,
                        raw_size: tuple[int, int] | None = None) -> MemoryEstimate:
    """Peak memory of running ``config`` (a :class:`fgslam.runconfig.SlamConfig`: the runner imports this
    module, so it is not imported here) on ``frames`` frames of ``width x height`` output images
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
    family = config.family_section()
    if config.frontend == "patch" and family is not None:
        parts += _patch_parts(family, width, height, stereo, rgbd, config.loop_closure.mode, size_keys)
    elif config.frontend == "dense" and family is not None:
        parts += _dense_parts(family, width, height, size_keys)
    elif config.frontend == "pointmap" and family is not None:
        parts += _pointmap_parts(family, width, height, frames, size_keys)
    if config.loop_closure.mode in ("classical", "both"):
        n = config.loop_closure.bow.orb.n_features
        parts.append(MemoryPart("loop-closure keyframes", KEYFRAME_SHARE * frames * n * ORB_FEATURE_BYTES,
                                [f"loop_closure.bow.orb.n_features={n}"]))
    return MemoryEstimate(parts)


def _patch_parts(cfg, width: int, height: int, stereo: bool, rgbd: bool, loop_mode: str,
                 size_keys: list[str]) -> list[MemoryPart]:
    g, lk = cfg.graph, cfg.lk
    cams = 2 if stereo else 1
    if lk.scale > 0:
        lk_w, lk_h = max(1, round(width * lk.scale)), max(1, round(height * lk.scale))
    else:
        lk_w, lk_h = _fit_width(width, height, lk.auto_width)
    score_w, score_h = _fit_width(width, height, g.score_width)
    frames_kept = g.removal_window + cfg.tracking.init_max_frames
    per_frame = (float(lk_w) * lk_h * PYRAMID_FACTOR * cams + float(width) * height * DEPTH_BYTES * rgbd
                 + g.patches_per_frame * PATCH_BYTES)
    edges = float(g.patches_per_frame) * g.removal_window * g.patch_lifetime * cams
    parts = [
        MemoryPart("patch frames", frames_kept * per_frame + float(score_w) * score_h * SCORE_BYTES_PER_PIXEL,
                   [f"patch.graph.removal_window={g.removal_window}", f"patch.lk.auto_width={lk.auto_width}",
                    f"patch.lk.scale={lk.scale:g}", f"patch.graph.score_width={g.score_width}", *size_keys]),
        MemoryPart("patch graph edges", edges * PATCH_EDGE_BYTES,
                   [f"patch.graph.patches_per_frame={g.patches_per_frame}",
                    f"patch.graph.removal_window={g.removal_window}", f"patch.graph.patch_lifetime={g.patch_lifetime}"]),
        MemoryPart("patch inactive edges", float(g.max_inactive_edges) * INACTIVE_EDGE_BYTES,
                   [f"patch.graph.max_inactive_edges={g.max_inactive_edges}"]),
    ]
    if loop_mode in ("proximity", "both"):
        p = cfg.proximity
        parts.append(MemoryPart(
            "patch proximity loops",
            float(p.max_stored_keyframes) * lk_w * lk_h * PNG_BYTES_PER_PIXEL
            + float(min(p.ba.chunk_edges, g.max_inactive_edges + edges)) * PATCH_EDGE_BYTES,
            [f"patch.proximity.max_stored_keyframes={p.max_stored_keyframes}",
             f"patch.proximity.ba.chunk_edges={p.ba.chunk_edges}"]))
    return parts


def _dense_parts(cfg, width: int, height: int, size_keys: list[str]) -> list[MemoryPart]:
    src, graph, glob = cfg.source, cfg.graph, cfg.global_ba
    cells = float(math.ceil(width / src.stride)) * math.ceil(height / src.stride)
    learned = src.kind in ("droid", "learned")
    kf_bytes = cells * (DENSE_KEYFRAME_BYTES_PER_CELL + DROID_KEYFRAME_BYTES_PER_CELL * learned)
    active_edges = graph.active_keyframes * 2 * (graph.neighbours + graph.temporal_radius)
    global_edges = min(glob.max_edges, glob.max_keyframes * 2 * (graph.neighbours + glob.temporal_radius))
    scaled_px = float(width) * height * src.flow.image_scale**2
    grid_keys = [f"dense.source.stride={src.stride}", *size_keys]
    parts = [
        MemoryPart("dense keyframes",
                   (graph.active_keyframes + glob.max_keyframes) * (kf_bytes + scaled_px * GREY_BYTES),
                   [f"dense.graph.active_keyframes={graph.active_keyframes}",
                    f"dense.global_ba.max_keyframes={glob.max_keyframes}", *grid_keys]),
        MemoryPart("dense edges", max(active_edges, global_edges) * cells * DENSE_EDGE_BYTES_PER_CELL,
                   [f"dense.global_ba.max_edges={glob.max_edges}", f"dense.graph.neighbours={graph.neighbours}",
                    *grid_keys]),
        MemoryPart("dense flow", scaled_px * DENSE_FLOW_BYTES_PER_PIXEL,
                   [f"dense.source.flow.image_scale={src.flow.image_scale:g}", *size_keys]),
    ]
    if learned:
        chunk = src.droid.chunk_edges
        parts.append(MemoryPart("dense correlation volumes", chunk * cells * cells * DROID_CORRELATION_BYTES,
                                [f"dense.source.droid.chunk_edges={chunk}", *grid_keys]))
    return parts


def _pointmap_parts(cfg, width: int, height: int, frames: int, size_keys: list[str]) -> list[MemoryPart]:
    pw, ph = (width, height) if cfg.image_width <= 0 else (cfg.image_width, max(1, round(height * cfg.image_width / width)))
    ppx = float(pw) * ph
    keys = [f"pointmap.image_width={cfg.image_width}"] + (size_keys if cfg.image_width <= 0 else [])
    keep = cfg.keyframe.keep_source_frames
    return [
        MemoryPart(f"pointmap keyframes ({pw}x{ph}, {KEYFRAME_SHARE:.0%} of {frames} frames)",
                   KEYFRAME_SHARE * frames * ppx * POINTMAP_KEYFRAME_BYTES_PER_PIXEL, keys),
        MemoryPart("pointmap frames", ppx * ((keep + 1) * POINTMAP_SOURCE_BYTES_PER_PIXEL + POINTMAP_MATCHING_BYTES_PER_PIXEL),
                   [*keys, f"pointmap.keyframe.keep_source_frames={keep}"]),
    ]


def check_run_memory(config, dataset: Dataset) -> MemoryEstimate:
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
