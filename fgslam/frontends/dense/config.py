"""Configuration of the dense frontend (DROID-SLAM family; YAML section ``dense``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

from ...core.config import MAX_COUNT, MAX_IMAGE_SIDE, MAX_ITERATIONS, MAX_KEYFRAMES, MAX_LAMBDA, MAX_SCALAR, MAX_THREADS, MAX_WINDOW, ranged
from ...core.errors import ConfigError
from ...factors.configs import DepthPriorConfig
from ..depth_tracking import DepthTrackingConfig
from .. import GREY_BYTES, PYRAMID_FACTOR, MemoryPart, MemorySizes
from ..flow import DenseFlowConfig
from .source import DenseSourceConfig


def _default_source() -> DenseSourceConfig:
    """The frontend's source defaults: the flow's aperture confidence at 1.5 grey levels per px (the
    source's own default, 3.0, starves faint tile lines: synthetic low-texture mono ATE 1.22 % -> 0.73 %
    of path, room-loop mono 0.18 % -> 0.17 %)."""
    return DenseSourceConfig(flow=DenseFlowConfig(aperture_gradient=1.5))


def _default_depth_align() -> DepthTrackingConfig:
    """Depth alignment off; when on, depth blocks between the consecutive keyframes of the whole local
    window (``ba.window`` free keyframes and the one before them: 4 pairs), so that a keyframe of a
    texture-free stretch is never free without a block that holds it."""
    return DepthTrackingConfig(window_pairs=4)


@dataclass
class DenseGraphConfig:
    """Frame graph: keyframe selection, edges, removal (DROID-SLAM section 3.4)."""

    motion_filter_flow: float = ranged(12.0, ge=0, le=MAX_SCALAR)  # image px: a frame becomes a keyframe when the mean flow from the newest keyframe exceeds this
    keyframe_min_confident: float = ranged(0.25, ge=0, le=1)  # a frame tracked by its image becomes a keyframe when its confident grid pixels are fewer than this share of its textured ones (tracking.texture_gradient), whatever its flow (0: off): on a forward drive the pixels of large flow lose confidence first, so the confident ones' mean flow stays under motion_filter_flow while the tracking's support fades and its pose stalls
    neighbours: int = ranged(3, ge=1, le=MAX_KEYFRAMES)  # a new keyframe is connected (both ways) to this many nearest keyframes by flow distance
    temporal_radius: int = ranged(2, ge=1, le=MAX_KEYFRAMES)  # ... and always to this many previous keyframes
    max_edge_distance: float = ranged(80.0, gt=0, le=MAX_SCALAR)  # image px: no edge between keyframes whose flow distance exceeds this
    active_keyframes: int = ranged(12, ge=3, le=MAX_WINDOW)  # keyframes in the active graph (older ones leave it, kept for the global optimisation)
    remove_threshold: float = ranged(6.0, ge=0, le=MAX_SCALAR)  # image px: the second newest keyframe is removed when its flow distance to the one before is below this (0: never)
    init_keyframes: int = ranged(6, ge=2, le=MAX_WINDOW)  # monocular: keyframes collected before the initialisation (stereo / RGB-D: 2)
    init_radius: int = ranged(3, ge=1, le=MAX_WINDOW)  # monocular initialisation with ba.init_neighbour_rounds: its first rounds use the edges between keyframes at most this many apart in order (DROID-SLAM: 3)
    distance_stride: int = ranged(2, ge=1, le=MAX_IMAGE_SIDE)  # grid pixels subsampled by this when computing flow distances


@dataclass
class DenseBAConfig:
    """Local dense bundle adjustment through the backend's window optimisation."""

    window: int = ranged(4, ge=1, le=MAX_WINDOW)  # newest keyframes with free poses (the rest of the active graph is held fixed)
    rounds: int = ranged(1, ge=1, le=MAX_ITERATIONS)  # measure/optimise rounds per new keyframe
    iterations: int = ranged(2, ge=1, le=MAX_ITERATIONS)  # LM iterations per round
    remeasure: int = ranged(2, ge=1, le=MAX_ITERATIONS)  # edges touching the newest this many keyframes are re-measured each round (the others keep their last measurement)
    kept_rounds: int = ranged(0, ge=0, le=MAX_ITERATIONS)  # more rounds after the keyframe-removal decision when the second newest keyframe is kept (DROID-SLAM: 2, its iters2; 0: none)
    remeasure_min_change: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # image px: an edge to re-measure whose induced field moved less than this (mean) since its last measurement keeps it (0: always re-measure; 7-Scenes RGB-D: 1.0 keeps about 40 % of them; 0-199 ATE 0.0224 -> 0.0225 m, 0-599 0.0334 -> 0.0331 m)
    init_rounds: int = ranged(5, ge=1, le=MAX_ITERATIONS)  # rounds of the initialisation
    init_iterations: int = ranged(4, ge=1, le=MAX_ITERATIONS)  # LM iterations per initialisation round
    init_neighbour_rounds: int = ranged(0, ge=0, le=MAX_ITERATIONS)  # monocular initialisation: rounds on the neighbourhood edges (graph.init_radius) before every pair within reach is connected for the init_rounds (DROID-SLAM: 8, then 8; 0: all pairs from the start)
    init_rounds_per_frame: int = ranged(0, ge=0, le=MAX_ITERATIONS)  # monocular initialisation: rounds run per frame from the frame that collects the last initial keyframe, so that no frame pays for all of them (0: all on that frame; KITTI 00 at 616x184: 1.0 s on that frame, 0.17 s a frame at 1); frames meanwhile are tracked as before it, and keyframes collected meanwhile join its next rounds
    pixel_sigma: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # image px: standard deviation of a fully confident flow measurement
    damping: float = ranged(1e-4, ge=0, le=MAX_LAMBDA)  # DROID's per-pixel damping eta added to each inverse depth's information (built-in source)
    min_depth: float = ranged(0.05, gt=0, le=MAX_SCALAR)  # smallest valid depth in a target camera (map units)
    huber: float = ranged(2.0, ge=0, le=MAX_SCALAR)  # image px: Huber threshold on the residual after a round (0: off)
    depth_prior: DepthPriorConfig = field(default_factory=DepthPriorConfig)  # RGB-D inverse-depth prior (sigma, noise model)
    depth_edge: float = ranged(0.1, ge=0, le=MAX_SCALAR)  # RGB-D: sensor depths in grid blocks whose relative depth spread exceeds this are dropped (edges, misregistration; 0: off)
    stereo_weight: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # weight of the left-right rows relative to a flow edge


@dataclass
class DenseTrackingConfig:
    """Per-frame motion-only tracking against the newest keyframe (motion filter, non-keyframe poses)."""

    iterations: int = ranged(6, ge=1, le=MAX_ITERATIONS)  # LM iterations of the motion-only optimisation
    step_tolerance: Optional[float] = ranged(None, ge=0, le=MAX_SCALAR)  # the motion-only LM stops when the largest tangent step component (rad, world units) falls below this (null: map.step_tolerance)
    rounds: int = ranged(1, ge=1, le=MAX_ITERATIONS)  # flow measurement rounds (each re-started from the pose just found)
    motion_damping: float = ranged(0.8, ge=0, le=1)  # constant-velocity prediction damping (1: undamped)
    min_confident: float = ranged(0.03, ge=0, le=1)  # a frame whose share of confident grid pixels is below this is a tracking failure
    min_textured: float = ranged(0.03, ge=0, le=1)  # a frame whose share of textured grid blocks is below this is a tracking failure (blank, blurred, covered)
    texture_gradient: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # grey levels per px: a grid block is textured when its RMS gradient exceeds this
    confident_weight: float = ranged(0.2, ge=0, le=1)  # a grid pixel is confident when its flow confidence exceeds this
    max_lost: int = ranged(10, ge=1, le=MAX_KEYFRAMES)  # consecutive failures before the map is restarted (relocalised when the loop closer or a loaded map can)
    retrack_per_frame: int = ranged(0, ge=0, le=MAX_KEYFRAMES)  # monocular: the frames tracked before the initialisation are re-tracked against its maps at most this many per frame, newest first (0: all on the frame that ends the initialisation; KITTI 00: 15 frames, 0.2 s); the rest on the frames after it, before a map restart and at the end of the run
    rejoin_frames: int = ranged(150, ge=0, le=MAX_KEYFRAMES)  # metric maps with the classical loop closer or a loaded map (--map): a map restarted without a relocalisation tries this many of its tracked frames to relocalise among the keyframes before it, and two agreeing relocalisations move it into the old map's frame (frontends/rejoin.py; 0: off)
    rejoin_every: int = ranged(5, ge=1, le=MAX_KEYFRAMES)  # ... one attempt every this many tracked frames
    rejoin_max_translation: float = ranged(0.05, ge=0, le=MAX_SCALAR)  # ... the two relocalisations' transforms (new map -> old map) agree within this (m) ...
    rejoin_max_rotation_deg: float = ranged(2.0, ge=0, le=180)  # ... and this rotation (degrees)


@dataclass
class DenseGlobalConfig:
    """Global optimisation (DROID-SLAM's backend) through the backend: edges rebuilt from the
    keyframes' flow-distance matrix (temporal first, then by distance, Chebyshev NMS)."""

    every: int = ranged(0, ge=0, le=MAX_KEYFRAMES)  # run after every this many new keyframes (0: only at the end)
    background: bool = True  # the periodic ones in the loop service's worker, applied at its safe point (false: synchronously, stalling tracking)
    delay_frames_per_keyframe: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # a background one is applied this many frames per keyframe of its snapshot after its start (at least loop_closure.global_ba_delay_frames), so that tracking need not wait for it
    final: bool = True  # run once at the end of the sequence (synchronously)
    iterations: int = ranged(4, ge=1, le=MAX_ITERATIONS)  # LM iterations per measure/optimise round
    rounds: int = ranged(1, ge=1, le=MAX_ITERATIONS)  # measure/optimise rounds
    temporal_radius: int = ranged(2, ge=1, le=MAX_KEYFRAMES)  # edges between keyframes this close in order always
    nms_radius: int = ranged(1, ge=0, le=MAX_KEYFRAMES)  # Chebyshev non-maximum suppression of the proximity edges (keyframe indices)
    max_distance: float = ranged(60.0, gt=0, le=MAX_SCALAR)  # image px: proximity edges only below this flow distance
    max_edges: int = ranged(2000, ge=1, le=MAX_COUNT)  # memory bound: edges of one global optimisation
    max_keyframes: int = ranged(400, ge=2, le=MAX_KEYFRAMES)  # memory bound: keyframes whose images are kept for re-measurement (older ones keep their last edges)


@dataclass
class DenseProximityConfig:
    """Proximity loops of the dense family (on with ``loop_closure.mode`` proximity or both).

    Each keyframe that settles (all but the newest two: only the second newest can still be removed)
    is a query: older keyframes of the map with images, at least ``min_gap`` keyframes back, whose
    current camera centre is within ``radius`` median query depths and whose optical axis within
    ``max_angle_deg``, and whose flow distance to the query (both ways) is below ``max_flow_px``, are
    candidates; the nearest by flow gets long-range edges (its and its ``old_neighbours``' maps into
    the query's and its ``new_neighbours``' and back) measured by the dense source from the field the
    estimate induces, verified by their confident share; a global optimisation then runs with them in
    the loop service's worker (``global_ba`` settings), undone unless ``min_ba_inlier_ratio`` of them
    keep a weight (an edge keeps it when ``min_edge_inliers`` of its pixels end within ``outlier_px``).
    """

    min_gap: int = ranged(20, ge=1, le=MAX_KEYFRAMES)  # keyframes between a query and a candidate at least
    radius: float = ranged(0.5, gt=0, le=MAX_SCALAR)  # candidate camera centres at most this many median query depths away
    max_angle_deg: float = ranged(30.0, gt=0, le=180)  # angle between the optical axes at most
    max_flow_px: float = ranged(80.0, gt=0, le=MAX_SCALAR)  # image px: flow distance between candidate and query at most
    old_neighbours: int = ranged(1, ge=0, le=MAX_KEYFRAMES)  # keyframes on each side of the candidate that also get loop edges
    new_neighbours: int = ranged(1, ge=0, le=MAX_KEYFRAMES)  # keyframes on each side of the query that also get loop edges
    min_confident: float = ranged(0.3, ge=0, le=1)  # share of a loop edge's grid pixels that must be confident (flow weight above confident_weight)
    confident_weight: float = ranged(0.2, ge=0, le=1)  # a loop edge's pixel is confident when its mean weight exceeds this
    min_loop_edges: int = ranged(2, ge=1, le=MAX_COUNT)  # verified loop edges needed
    outlier_px: float = ranged(4.0, gt=0, le=MAX_SCALAR)  # image px: a loop edge's pixel is an inlier after the global optimisation when its residual is below this
    min_edge_inliers: float = ranged(0.5, ge=0, le=1)  # a loop edge keeps its weight when this share of its pixels are inliers
    min_ba_inlier_ratio: float = ranged(0.6, ge=0, le=1)  # share of the loop edges that must keep a weight after the global optimisation (else undone)
    cooldown: int = ranged(10, ge=0, le=MAX_KEYFRAMES)  # keyframes after an accepted proximity loop during which no other is searched


@dataclass
class DenseConfig:
    """The ``dense`` section of a run config: the DROID-SLAM family (fgslam/frontends/dense/frontend.py)."""

    source: DenseSourceConfig = field(default_factory=_default_source)
    graph: DenseGraphConfig = field(default_factory=DenseGraphConfig)
    ba: DenseBAConfig = field(default_factory=DenseBAConfig)
    tracking: DenseTrackingConfig = field(default_factory=DenseTrackingConfig)
    global_ba: DenseGlobalConfig = field(default_factory=DenseGlobalConfig)
    proximity: DenseProximityConfig = field(default_factory=DenseProximityConfig)  # proximity loops (loop_closure.mode proximity or both)
    depth_align: DepthTrackingConfig = field(default_factory=_default_depth_align)  # RGB-D: point-to-plane depth alignment in tracking and the window
    point_confidence: float = ranged(0.5, ge=0, le=1)  # keyframe_points / depth PNG: grid pixels with confidence below this are left out
    threads: int = ranged(1, ge=0, le=MAX_THREADS)  # torch threads of the frontend (0: torch's default)

    def wants_colour(self) -> bool:
        """The DROID source takes the colour image (the official network's input); the flow source grey."""
        return self.source.kind in ("droid", "learned")

    def validate(self) -> None:
        self.depth_align.validate()
        if self.ba.window >= self.graph.active_keyframes:
            raise ConfigError(f"dense.ba.window ({self.ba.window}) must be smaller than dense.graph.active_keyframes "
                              f"({self.graph.active_keyframes}): some active keyframes hold the window's gauge")


# ----------------------------------------------------------------------------------------- memory estimate

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


def memory_parts(cfg: DenseConfig, sizes: MemorySizes) -> list[MemoryPart]:
    """The dense family's parts of a run's peak-memory estimate (its registry entry's ``memory``,
    :mod:`fgslam.run.memory`): the active and global keyframes' grids, the edges of the larger of the
    local and global bundle adjustments, the optical flow, and for the learned source its
    correlation volumes."""
    width, height, size_keys = sizes.width, sizes.height, sizes.size_keys
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
