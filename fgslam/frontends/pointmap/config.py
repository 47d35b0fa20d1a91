"""Typed configuration of the pointmap frontend (MASt3R-SLAM family): the ``pointmap:`` section of the
runner's ``SlamConfig``. Pixel quantities are in pixels of the working resolution (``image_width``);
point quantities in the pointmaps' units (metres for RGB-D and stereo, the pair's arbitrary unit for
the monocular two-view source)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from ...core.config import MAX_COUNT, MAX_FRAMES, MAX_IMAGE_SIDE, MAX_ITERATIONS, MAX_KEYFRAMES, MAX_LAMBDA, MAX_SCALAR, MAX_THREADS, MAX_WINDOW, check_ranges, ranged
from ...core.errors import ConfigError
from ...factors.pointmap_block import PointmapBlockConfig
from .. import KEYFRAME_SHARE, MemoryPart, MemorySizes
from ..depth_tracking import DepthTrackingConfig
from .features import FeaturePoseConfig
from .matching import MatchingConfig
from .source import PointmapSourceConfig


@dataclass
class PointmapTrackingConfig:
    """Frame-to-keyframe tracking (MASt3R-SLAM section 3.3): Gauss-Newton IRLS on the residuals of
    ``block.mode`` (ray + distance, or calibrated pixel + log depth), Huber, confidence weighting."""

    iterations: int = ranged(10, ge=1, le=MAX_ITERATIONS)  # Gauss-Newton iterations at most
    step_tolerance: float = ranged(1e-5, gt=0, le=MAX_SCALAR)  # stop when the largest tangent step component is below this
    damping: float = ranged(1e-6, gt=0, le=MAX_LAMBDA)  # initial Marquardt damping: this times the Hessian's diagonal is added to it
    lambda_factor: float = ranged(10.0, gt=1, le=MAX_SCALAR)  # damping raised by this after a step that raises the cost, lowered after one that lowers it
    lambda_max: float = ranged(1e6, gt=0, le=MAX_LAMBDA)  # no descent at this damping: converged
    # scale of the relative pose: free (Sim(3), the monocular two-view source's arbitrary scale per pair),
    # fixed (SE(3): metric RGB-D / stereo pointmaps), auto: fixed for metric sources, free otherwise
    scale: Literal["auto", "free", "fixed"] = "auto"
    inlier_threshold: float = ranged(5.0, gt=0, le=MAX_SCALAR)  # a match is an inlier when its ray (pixel) rows' whitened norm is below this
    # metric sources: X_f^k from the pose measured by PnP on the source's dense flow (else from the previous
    # frame's relative pose: projective matching alone then only refines it within the descriptor window)
    measure_pose: bool = True
    # start of projective matching: the previous frame's matches into the same keyframe (MASt3R-SLAM), or the
    # projection of the predicted query points (exact for the predicted pose; the start after a keyframe change)
    warm_start: Literal["previous", "projection"] = "previous"
    min_matches: int = ranged(200, ge=7, le=MAX_COUNT)  # fewer valid matches: tracking failed (relocalisation)
    min_valid_fraction: float = ranged(0.05, ge=0, le=1)  # valid matches / valid query points below this: failed
    max_query_points: int = ranged(5000, ge=100, le=MAX_COUNT)  # tracking uses at most this many valid matches (evenly strided)
    min_confidence: float = ranged(0.1, ge=0, le=1)  # query pixels below this pointmap confidence are not matched
    init_min_confident: float = ranged(0.2, ge=0, le=1)  # monocular start: fraction of confident pair pixels needed
    init_max_frames: int = ranged(30, ge=1, le=MAX_WINDOW)  # monocular start: after this many frames without one, start from a newer frame


@dataclass
class KeyframeConfig:
    """Keyframes (section 3.4) and pointmap fusion (eq. 9)."""

    new_fraction: float = ranged(0.333, ge=0, le=1)  # a new keyframe when valid matches / valid points fall below this
    max_gap: int = ranged(0, ge=0, le=MAX_FRAMES)  # also a new keyframe after this many tracked frames (0: no limit)
    fuse: bool = True  # canonical pointmap <- confidence-weighted running average (eq. 9) of the tracked frames
    max_confidence: float = ranged(50.0, gt=0, le=MAX_SCALAR)  # cap of the fused confidence sum (later frames keep a weight)
    keep_source_frames: int = ranged(2, ge=1, le=MAX_WINDOW)  # newest keyframes whose source caches (descriptors, flow) stay loaded


@dataclass
class PointmapGraphConfig:
    """Keyframe graph and global optimisation through the backend (section 3.5)."""

    iterations: int = ranged(10, ge=1, le=MAX_ITERATIONS)  # LM iterations per new keyframe (the backend stops early on convergence)
    window: int = ranged(0, ge=0, le=MAX_WINDOW)  # newest keyframes optimised per new keyframe (0: all: the global optimisation)
    max_edge_matches: int = ranged(3000, ge=10, le=MAX_COUNT)  # matches kept per edge (evenly strided); the block is 14x14 anyway
    min_edge_matches: int = ranged(100, ge=7, le=MAX_COUNT)  # an edge (loop or relocalisation) needs this many valid matches
    min_edge_inlier_ratio: float = ranged(0.5, ge=0, le=1)  # ... and this share of them inliers at the refined pose
    final_iterations: int = ranged(20, ge=0, le=MAX_ITERATIONS)  # global optimisation when the run ends (0: none)


@dataclass
class PointmapRelocalizationConfig:
    """Relocalisation when tracking fails (section 3.6)."""

    recent_keyframes: int = ranged(3, ge=0, le=MAX_KEYFRAMES)  # besides retrieval (loop service), try the newest this many keyframes
    min_valid_fraction: float = ranged(0.2, ge=0, le=1)  # a candidate keyframe is accepted with this valid-match fraction


@dataclass
class PointmapConfig:
    """The ``pointmap`` section: source, matching, tracking, keyframes, graph (see the module docstring)."""

    source: PointmapSourceConfig = field(default_factory=lambda: PointmapSourceConfig(kind="auto"))
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    block: PointmapBlockConfig = field(default_factory=PointmapBlockConfig)  # residual mode, sigmas, Huber (tracking too)
    image_width: int = ranged(320, ge=0, le=MAX_IMAGE_SIDE)  # frames are resized to this width (aspect kept; 0: as the dataset gives them)
    query_stride: int = ranged(2, ge=1, le=MAX_IMAGE_SIDE)  # every this many pixels of a frame (both axes) are matched (MASt3R-SLAM subsamples;
    # 2: matching 42 ms CPU per 320x240 pair against 118 ms for every pixel, tools/bench_pointmap.py)
    tracking: PointmapTrackingConfig = field(default_factory=PointmapTrackingConfig)
    keyframe: KeyframeConfig = field(default_factory=KeyframeConfig)
    graph: PointmapGraphConfig = field(default_factory=PointmapGraphConfig)
    relocalization: PointmapRelocalizationConfig = field(default_factory=PointmapRelocalizationConfig)
    # monocular source: the pose of every frame by corners, KLT and PnP against the keyframe's pointmap (issue 28)
    features: FeaturePoseConfig = field(default_factory=FeaturePoseConfig)
    # RGB-D: point-to-plane depth alignment in tracking and the keyframe graph (between the newest
    # window_pairs pairs of consecutive keyframes, and always between keyframes joined by depth alone)
    depth_align: DepthTrackingConfig = field(default_factory=lambda: DepthTrackingConfig(window_pairs=1))
    ply_stride: int = ranged(4, ge=1, le=MAX_IMAGE_SIDE)  # keyframe_points(): every this many pixels of each canonical pointmap
    ply_min_confidence: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # ... whose fused confidence reaches this
    threads: int = ranged(1, ge=0, le=MAX_THREADS)  # torch threads of the frontend (0: torch's setting)

    def validate(self) -> None:
        check_ranges(self, "pointmap")
        self.depth_align.validate()
        if self.keyframe.new_fraction < self.tracking.min_valid_fraction:
            raise ConfigError(f"pointmap.keyframe.new_fraction ({self.keyframe.new_fraction}) must be at least "
                              f"pointmap.tracking.min_valid_fraction ({self.tracking.min_valid_fraction})")

    def source_kind(self, sensor_mode: str) -> str:
        """The source kind for ``sensor_mode`` (``auto``: rgbd, stereo or mono from the sensor)."""
        return sensor_mode if self.source.kind == "auto" else self.source.kind


# ----------------------------------------------------------------------------------------- memory estimate

#: B per pointmap pixel of a keyframe: canonical float32 points (12 B), confidence (4 B), colour (3 B)
POINTMAP_KEYFRAME_BYTES_PER_PIXEL = 20
#: B per pointmap pixel of a frame whose source caches stay loaded: two 16-dimensional float32
#: descriptors with confidences, the flow / depth maps
POINTMAP_SOURCE_BYTES_PER_PIXEL = 160
#: B per pointmap pixel of the matching and tracking of one frame (per-pixel LM states, rays, indices)
POINTMAP_MATCHING_BYTES_PER_PIXEL = 200


def memory_parts(cfg: PointmapConfig, sizes: MemorySizes) -> list[MemoryPart]:
    """The pointmap family's parts of a run's peak-memory estimate (its registry entry's ``memory``,
    :mod:`fgslam.run.memory`): the keyframes' pointmaps (a share of the frames) and one frame's
    source caches, matching and tracking."""
    width, height, frames, size_keys = sizes.width, sizes.height, sizes.frames, sizes.size_keys
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
