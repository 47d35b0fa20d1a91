"""Typed configuration of the pointmap frontend (MASt3R-SLAM family): the ``pointmap:`` section of the
runner's ``SlamConfig``. Pixel quantities are in pixels of the working resolution (``image_width``);
point quantities in the pointmaps' units (metres for RGB-D and stereo, the pair's arbitrary unit for
the monocular two-view source)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Optional

from ...core.config import (MAX_COUNT, MAX_FRAMES, MAX_IMAGE_SIDE, MAX_ITERATIONS, MAX_KEYFRAMES, MAX_LAMBDA, MAX_PERCENT,
                            MAX_SCALAR, MAX_THREADS, MAX_WINDOW, check_ranges, ranged)
from ...core.errors import ConfigError
from ...factors.configs import PointmapBlockConfig
from .. import KEYFRAME_SHARE, MemoryPart, MemorySizes
from ..depth_tracking import DepthTrackingConfig
from ..flow import DenseFlowConfig


# ----------------------------------------------------------------------------------------- the parts' configs
# (each re-exported by the module that uses it, where it is explained: this module imports neither torch nor
# OpenCV, so that a run's config loads without them)


PATCH_SIDE = 4  # the patch descriptor: samples per side of its grid (PATCH_SIDE ** 2 dimensions)


@dataclass
class DescriptorConfig:
    """Which dense descriptor, and its scales (:mod:`fgslam.frontends.pointmap.descriptors`)."""

    kind: Literal["patch", "gradient"] = "patch"  # normalised local patch, or gradient-orientation histograms
    sigma: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # px: Gaussian smoothing before sampling (gradient: of the orientation channels)
    step: int = ranged(2, ge=1, le=MAX_IMAGE_SIDE)  # px: spacing of the samples (patch: 4x4 grid; gradient: 2x2 cells)
    texture: float = ranged(4.0, gt=0, le=MAX_SCALAR)  # grey levels: contrast at which the confidence Q is 1/2


@dataclass
class FeaturePoseConfig:
    """Monocular per-frame pose by corners, KLT and PnP against the keyframe's pointmap (YAML ``pointmap.features``)."""

    # features: the pose of every monocular frame by this module; two_view: the dense two-view pair per frame
    # (essential matrix on the dense flow, PnP on the flow for frames without parallax), the issue-13 source
    mode: Literal["features", "two_view"] = "features"
    max_corners: int = ranged(500, ge=8, le=MAX_COUNT)  # corners detected per keyframe (Shi-Tomasi)
    corner_quality: float = ranged(0.01, gt=0, le=1)  # cv2 qualityLevel: corners weaker than this times the best are dropped
    corner_min_distance: int = ranged(7, ge=1, le=MAX_IMAGE_SIDE)  # px between corners
    min_point_confidence: float = ranged(0.1, ge=0, le=MAX_SCALAR)  # a corner needs this canonical-pointmap confidence
    lk_window: int = ranged(21, ge=3, le=MAX_IMAGE_SIDE)  # px: KLT window side
    lk_levels: int = ranged(3, ge=0, le=10)  # KLT pyramid levels
    lk_iterations: int = ranged(20, ge=1, le=MAX_ITERATIONS)  # KLT iterations per level
    lk_epsilon: float = ranged(0.03, gt=0, le=MAX_SCALAR)  # px: KLT stops below this update
    fb_threshold: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # px: forward-backward error above which a track is dropped
    ransac_threshold: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # px: PnP RANSAC reprojection threshold
    ransac_iterations: int = ranged(100, ge=1, le=MAX_ITERATIONS)  # PnP RANSAC iterations
    ransac_confidence: float = ranged(0.999, gt=0, lt=1)  # PnP RANSAC success probability
    min_inliers: int = ranged(20, ge=6, le=MAX_COUNT)  # fewer PnP inliers: no pose (relocalisation / failure)
    min_inlier_ratio: float = ranged(0.5, ge=0, le=1)  # a smaller inlier share of the surviving tracks: no pose
    new_keyframe_fraction: float = ranged(0.5, ge=0, le=1)  # a new keyframe when the inliers fall below this share of the keyframe's corners
    new_keyframe_inliers: int = ranged(80, ge=6, le=MAX_COUNT)  # ... or when they fall below this many (a keyframe born with fewer: the share rule alone)
    # the new keyframe's pose refined by projective matching and the tracking solve on its pointmap: Sim(3),
    # SE(3) (the scale stays the corners' PnP scale, carried by the map) or off (the corners' pose and edge;
    # the default: 7-Scenes 0-599 0.150 m against 0.176 m with se3, room-loop 1.02 % against 1.12 %)
    keyframe_refine: Literal["sim3", "se3", "off"] = "off"
    extra_edges: int = ranged(0, ge=0, le=MAX_COUNT)  # a new keyframe also gets measured edges to this many keyframes before the previous one
    # each measured frame's corners triangulated with its pose and fused (eq. 9) into the keyframe's pointmap.
    # Off by default: the corners' points then follow the poses measured from them (a loop of gain near one
    # over short baselines), which made the run chaotic: 7-Scenes 0-599 ATE 0.18-0.42 m across 1-ppm focal
    # changes and CPU kernels (max/min 2.3), off 0.230-0.251 m (1.09; tools/bench_stability.py)
    fuse_corners: bool = False
    carried_confidence: float = ranged(1.0, ge=0, le=1)  # confidence factor of the previous keyframe's points carried into a new keyframe


@dataclass
class MatchingConfig:
    """Iterative projective matching and descriptor refinement (defaults: MASt3R-SLAM's where it has one)."""

    max_iterations: int = ranged(10, ge=1, le=MAX_ITERATIONS)  # LM iterations per pixel (paper: 10)
    lambda_initial: float = ranged(1e-3, gt=0, le=MAX_LAMBDA)  # per-pixel Marquardt damping at the start
    lambda_factor: float = ranged(10.0, gt=1, le=MAX_SCALAR)  # damping divided by this after a good step, multiplied after a bad one
    step_tolerance: float = ranged(1e-3, ge=0, le=MAX_SCALAR)  # px: a pixel whose step is below this has converged
    max_distance: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # matched points further apart than this times the query's norm are invalid
    max_ray_error: float = ranged(0.02, gt=0, le=MAX_SCALAR)  # final unit-ray error (~rad) above this: invalid (ray left the image)
    refine_radius: int = ranged(1, ge=0, le=MAX_IMAGE_SIDE)  # px: descriptor search window radius around the LM solution (0: no refinement)
    refine_dilations: list[int] = ranged(default_factory=lambda: [4, 2, 1], ge=1, le=MAX_IMAGE_SIDE)  # window spacings, coarse to fine
    # (radius 1 at spacings 4, 2, 1 reaches 7 px with 27 candidates: measured in tools/bench_pointmap.py)
    threads: int = ranged(1, ge=0, le=MAX_THREADS)  # torch intra-op threads while matching (0: torch's setting); 1: measured
    # 10x faster than 2 threads on the loaded 2-core machine (tools/bench_pointmap.py)


@dataclass
class RelativePoseConfig:
    """Relative pose of two views from the dense flow's confident correspondences (PnP or essential matrix)."""

    flow: DenseFlowConfig = field(default_factory=lambda: DenseFlowConfig(warm_start=False, image_scale=1.0))  # DIS on the full-resolution pair
    min_flow_confidence: float = ranged(0.1, ge=0, le=1)  # correspondences below this flow confidence are not used
    sample_stride: int = ranged(4, ge=1, le=MAX_IMAGE_SIDE)  # px: one correspondence per stride x stride cell feeds RANSAC
    ransac_threshold: float = ranged(0.5, gt=0, le=MAX_SCALAR)  # px: RANSAC inlier threshold (PnP reprojection / essential matrix)
    ransac_confidence: float = ranged(0.999, gt=0, lt=1)  # RANSAC success probability
    ransac_iterations: int = ranged(200, ge=1, le=MAX_ITERATIONS)  # PnP RANSAC iterations
    min_inliers: int = ranged(30, ge=6, le=MAX_COUNT)  # fewer RANSAC inliers: no pose (the pair gets zero confidence)
    min_inlier_ratio: float = ranged(0.3, ge=0, le=1)  # a smaller inlier fraction of the samples: no pose (no overlap)
    min_overlap: float = ranged(0.1, ge=0, le=1)  # fewer pixels with a confident flow (either way): no overlap, no pose


@dataclass
class StereoMatchConfig:
    """OpenCV semi-global block matching on the rectified pair (StereoSGBM)."""

    num_disparities: int = ranged(64, ge=16, le=MAX_IMAGE_SIDE)  # disparity search range (px; rounded up to a multiple of 16)
    block_size: int = ranged(5, ge=1, le=MAX_IMAGE_SIDE)  # matched block size (odd px)
    uniqueness: int = ranged(10, ge=0, le=MAX_PERCENT)  # % margin of the best cost over the second best
    disp12_max_diff: int = ranged(1, ge=-1, le=MAX_IMAGE_SIDE)  # px: left-right consistency check (-1: off)
    speckle_window: int = ranged(100, ge=0, le=MAX_IMAGE_SIDE)  # px: speckle filter region size (0: off)
    speckle_range: int = ranged(2, ge=0, le=MAX_IMAGE_SIDE)  # disparity variation inside a speckle region
    min_disparity: float = ranged(0.5, gt=0, le=MAX_SCALAR)  # px: smaller disparities (very far points) are invalid


@dataclass
class TriangulationConfig:
    """Monocular two-view reconstruction (essential matrix + triangulation)."""

    angle_sigma_deg: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # confidence 1 - exp(-(angle / sigma)^2) of the triangulation angle
    median_depth: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # the pair's arbitrary scale: median depth of X_i^i set to this
    max_depth_ratio: float = ranged(50.0, gt=1, le=MAX_SCALAR)  # points deeper than this times the median depth are invalid


@dataclass
class PointmapSourceConfig:
    """Which pointmap source, and its settings (YAML section ``pointmap.source``)."""

    kind: Literal["auto", "rgbd", "stereo", "mono", "mast3r"] = "rgbd"  # sensor depth, stereo SGBM, two-view
    # triangulation, MASt3R; auto (the pointmap frontend's default): the run's sensor mode picks rgbd, stereo or mono
    checkpoint: Optional[str] = None  # mast3r: path of the MASt3R checkpoint
    min_depth: float = ranged(1e-3, ge=0, le=MAX_SCALAR)  # metric sources: depths at or below this are invalid (m)
    descriptor: DescriptorConfig = field(default_factory=DescriptorConfig)
    pose: RelativePoseConfig = field(default_factory=RelativePoseConfig)
    stereo: StereoMatchConfig = field(default_factory=StereoMatchConfig)
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)


# ----------------------------------------------------------------------------------------- the family's


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
