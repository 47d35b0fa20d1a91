"""Typed configuration of the patch frontend (DPVO / DPV-SLAM family).

``PatchConfig`` is the root; it is the ``patch:`` section of the runner's ``SlamConfig`` and loads
on its own with ``fgslam.config.load_config(PatchConfig, path, overrides)``. Pixel quantities are
in pixels of the frames as the dataset delivers them (after resizing); windows are counted in
frames of the patch graph (kept frames, DPVO's buffer positions).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Optional

from ...config import ranged
from ...errors import ConfigError


@dataclass
class GraphConfig:
    """Patch graph (DPV-SLAM section 3.1)."""

    patches_per_frame: int = 96  # K random p x p patches per frame, one inverse depth each
    patch_size: int = 3  # p: samples per patch side
    patch_stride: int = 7  # pixels between patch samples: the tracked footprint is p * stride pixels
    selection: Literal["corners", "random"] = "corners"  # corners: strongest min-eigenvalue pixels spread over a grid; random: uniform (DPVO)
    selection_grid: list[int] = field(default_factory=lambda: [8, 4])  # cells across x, down y; each cell yields the same share of patches
    candidate_block: int = 8  # corners: one candidate (local maximum) per block of this many pixels square
    score_width: int = 640  # corners: response computed on the image resized to at most this width (0: full resolution)
    border: int = 12  # patch centres keep this many pixels from the image border
    seed: int = 0  # random generator seed of patch selection
    patch_lifetime: int = 5  # a patch gets edges to frames at most this many graph frames away
    removal_window: int = 10  # edges whose source frame is this many graph frames old become inactive
    optimization_window: int = 6  # latest graph frames whose poses are optimised (older ones fixed)
    max_inactive_edges: int = 500_000  # bound of the inactive-edge store kept for global optimisation (oldest dropped)

    def validate(self) -> None:
        if self.patches_per_frame < 8:
            raise ConfigError(f"patch.graph.patches_per_frame must be >= 8, got {self.patches_per_frame}")
        if self.patch_size < 1 or self.patch_stride < 1:
            raise ConfigError("patch.graph.patch_size and patch_stride must be >= 1")
        if self.patch_lifetime < 1 or self.optimization_window < 2:
            raise ConfigError("patch.graph.patch_lifetime must be >= 1 and optimization_window >= 2")
        if self.removal_window <= self.patch_lifetime:
            raise ConfigError(
                f"patch.graph.removal_window ({self.removal_window}) must exceed patch_lifetime ({self.patch_lifetime})"
            )
        if len(self.selection_grid) != 2 or min(self.selection_grid) < 1:
            raise ConfigError(f"patch.graph.selection_grid must be two positive ints, got {self.selection_grid}")


@dataclass
class LKConfig:
    """Built-in pyramidal Lucas-Kanade measurement source (``source: lk``)."""

    scale: float = 0.0  # LK runs on images resized by this factor; 0: automatic, the largest factor <= 1 giving width <= auto_width
    auto_width: int = 640  # image width (px) the automatic scale aims at
    levels: int = 3  # pyramid levels above the LK resolution
    iterations: int = 20  # LK iterations per level
    epsilon: float = 0.02  # LK stops when the update is below this many pixels
    min_eigen: float = 1e-4  # cv2 minEigThreshold: windows with less texture are rejected
    fb_threshold: float = 1.0  # forward-backward error (px) above which a track is rejected
    fb_sigma: float = 0.5  # forward-backward error (px) at which the confidence halves
    error_sigma: float = 12.0  # mean absolute intensity error (grey levels) at which the confidence halves
    min_confidence: float = 0.05  # tracks below this confidence are rejected


@dataclass
class BAConfig:
    """Local bundle adjustment over the optimisation window."""

    iterations: int = 1  # Levenberg-Marquardt iterations per update round while tracking
    init_iterations: int = 15  # iterations per update round at initialisation
    rounds: int = 2  # update rounds per frame: measure (re-track bad edges), then optimise
    init_rounds: int = 3  # update rounds at initialisation
    refine_steps: int = 0  # per-patch depth Gauss-Newton steps before/after each BA (LM updates depths jointly anyway)
    pixel_sigma: float = 1.0  # standard deviation (px) of a full-confidence measurement
    huber_delta: float = 2.0  # Huber threshold on the whitened residual (sigma units)
    outlier_threshold: float = 6.0  # edges with a residual above this (px) after BA get zero weight
    retrack_threshold: float = 2.0  # new edges with a residual above this (px) are re-tracked from the new reprojection
    min_depth: float = 0.05  # smallest valid depth in a target camera (map units; stereo/RGB-D: metres)
    depth_prior_sigma: float = 0.05  # RGB-D: sensor-depth noise, relative (depth_noise: relative) or in 1/m of inverse depth (inverse)
    depth_min: float = 0.1  # RGB-D: sensor depths at or below this (m) are invalid
    depth_max: float = 10.0  # RGB-D: sensor depths above this (m) are invalid
    depth_window: int = 2  # RGB-D: half-size (px) of the window whose median is the patch's sensor depth
    depth_max_spread: float = 0.1  # RGB-D: (max - min) / median depth in that window above which it is a discontinuity (no prior)
    stereo_init_steps: int = 5  # stereo: per-patch depth Gauss-Newton steps on the first frame's right-image edges
    stereo_cross_edges: bool = False  # stereo: also edges into the right images of other frames (else own right image only)
    threads: int = 1  # torch threads during BA (small dense work: 1 is fastest)
    lambda_factor: float = 1000.0  # LM damping multiplier after a rejected step (the pose Hessian dwarfs damping below ~1e4: x10 retries the same step)
    depth_model: Literal["prior", "observation"] = "prior"  # RGB-D: prior on each patch's inverse depth in its source frame (DROID-SLAM), or sensor depth as a measurement of every observation, source and targets (ORB-SLAM3 RGB-D: virtual right-camera pixel u - f b / z)
    depth_noise: Literal["relative", "inverse"] = "relative"  # RGB-D: relative: sigma_d = depth_prior_sigma * d (sigma_z grows with z); inverse: sigma_d = depth_prior_sigma in 1/m (sigma_z grows with z^2, Kinect)
    depth_virtual_baseline: float = ranged(0.08, gt=0)  # RGB-D observation model: baseline (m) of the virtual right camera (sets the pixel scale of the depth rows)


@dataclass
class TrackingConfig:
    """Initialisation, motion model, keyframes, failure handling."""

    init_min_parallax: float = 6.0  # mono: median rotation-compensated flow (px) needed to initialise
    init_min_tracks: int = 30  # mono: tracks of the reference patches needed to keep waiting on one reference
    init_min_frames: int = 3  # mono: frames (reference included) collected before initialising
    init_max_frames: int = 8  # mono: frames kept in the initialisation window (older ones subsampled)
    init_ransac_threshold: float = 1.0  # mono: essential-matrix RANSAC threshold (px)
    init_min_inlier_ratio: float = 0.6  # mono: essential-matrix inlier share needed to initialise
    motion_damping: float = 0.5  # damped constant velocity: predicted step = damping * last step (DPVO 0.5)
    keyframe_index: int = 3  # frame this many graph frames before the newest is tested for removal
    keyframe_threshold: float = 20.0  # mean flow (px) between its neighbours below which it is removed
    min_valid_edges: int = 24  # fewer valid measurements into a new frame is a tracking failure
    max_motion_model_frames: int = 30  # consecutive failures after which the map re-initialises


@dataclass
class GlobalBAConfig:
    """Tunables of :func:`global_bundle_adjustment`."""

    iterations: int = 10  # Levenberg-Marquardt iterations per robust round
    robust_rounds: int = 2  # rounds, each re-weighting the edges from the previous one's residuals
    huber_first_round: bool = True  # round 1 Huber-weighted from the initial residuals (no outlier cut); else plain least squares
    huber_delta: float = 2.0  # Huber threshold on the whitened residual (later rounds)
    outlier_threshold: float = 6.0  # edges above this many pixels after a round get zero weight
    lambda_initial: float = 1e-4  # Marquardt damping: H + lambda diag(H)
    lambda_factor: float = 10.0  # damping multiplier on rejection / divisor on acceptance
    lambda_max: float = 1e4  # rejected steps pushing lambda above this end the round (at a minimum)
    relative_tolerance: float = 1e-6  # stop a round when the relative cost decrease falls below this
    min_structure: float = 1e-6  # inverse depths are clamped to at least this
    min_information: float = 1e-12  # patches with less information are not updated
    chunk_edges: int = 200_000  # edges linearised per batch (bounds memory: about 300 bytes per edge)
    threads: int = 0  # torch threads; 0: every core (large batched work, unlike the local BA; tracking waits for it)

    def validate(self) -> None:
        if self.threads < 0:
            raise ConfigError(f"patch.proximity.ba.threads must be >= 0 (0: every core), got {self.threads}")
        if self.iterations < 1 or self.robust_rounds < 1 or self.chunk_edges < 1:
            raise ConfigError("patch.proximity.ba: iterations, robust_rounds and chunk_edges must be >= 1")
        if not self.lambda_factor > 1 or not self.lambda_initial > 0:
            raise ConfigError("patch.proximity.ba: lambda_factor must be > 1 and lambda_initial > 0")


@dataclass
class ProximityConfig:
    """Proximity loop closure (DPV-SLAM section 3.2; on with ``loop_closure.mode`` proximity or both).

    Each keyframe that settles (can no longer be removed) is a query: older keyframes at least
    ``min_gap`` keyframes back whose current pose is within ``radius`` (in units of the query's median
    patch depth, so it holds at any monocular scale) and ``max_angle_deg`` of viewing direction, and
    whose patches reproject into the query with a mean displacement below ``max_flow_px`` (the flow
    check), are candidates; the best one gets long-range edges (its and its neighbours' patches into
    the query's neighbourhood and back), measured by the source, verified by a fundamental-matrix
    RANSAC, then a global bundle adjustment runs over every active, inactive and loop edge.
    """

    min_gap: int = 30  # keyframes between a query and a candidate at least
    radius: float = 0.5  # candidate camera centres at most this many median query depths away
    max_angle_deg: float = 30.0  # angle between the optical axes at most
    max_flow_px: float = 60.0  # mean reprojected displacement of the candidate's patches in the query at most
    min_overlap: float = 0.5  # share of the candidate's patches that reproject into the query image at least
    old_neighbours: int = 1  # keyframes on each side of the candidate whose patches also get loop edges
    new_neighbours: int = 1  # graph frames on each side of the query that also get loop edges
    ransac_threshold_px: float = 1.5  # fundamental-matrix RANSAC threshold on the loop measurements
    min_loop_edges: int = 60  # verified loop measurements needed
    min_inlier_ratio: float = 0.5  # share of valid loop measurements that must be RANSAC inliers
    min_ba_inlier_ratio: float = 0.6  # share of loop edges with non-zero weight after the global BA (else undone)
    cooldown: int = 10  # keyframes after an accepted proximity loop during which no other is searched
    max_stored_keyframes: int = 5000  # keyframe images kept (PNG in memory) for loop edges; oldest dropped
    ba: GlobalBAConfig = field(default_factory=GlobalBAConfig)

    def validate(self) -> None:
        if self.min_gap < 1 or self.min_loop_edges < 8 or self.cooldown < 0 or self.max_stored_keyframes < 1:
            raise ConfigError("patch.proximity: min_gap >= 1, min_loop_edges >= 8, cooldown >= 0, max_stored_keyframes >= 1")
        if not (self.radius > 0 and self.max_flow_px > 0 and 0 < self.max_angle_deg <= 180):
            raise ConfigError("patch.proximity: radius and max_flow_px must be > 0, max_angle_deg in (0, 180]")
        for name in ("min_overlap", "min_inlier_ratio", "min_ba_inlier_ratio"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"patch.proximity.{name} must be in [0, 1], got {getattr(self, name)}")
        if self.old_neighbours < 0 or self.new_neighbours < 0 or not self.ransac_threshold_px > 0:
            raise ConfigError("patch.proximity: neighbours must be >= 0 and ransac_threshold_px > 0")
        self.ba.validate()


@dataclass
class PatchConfig:
    """Root configuration of :class:`fgslam.frontends.patch.PatchFrontend`."""

    source: Literal["lk", "learned"] = "lk"  # measurement source: built-in Lucas-Kanade or the DPVO network
    checkpoint: Optional[str] = None  # learned source: path of the DPVO checkpoint (dpvo.pth)
    threads: int = 1  # torch threads of the frontend (flow/bookkeeping)
    graph: GraphConfig = field(default_factory=GraphConfig)
    lk: LKConfig = field(default_factory=LKConfig)
    ba: BAConfig = field(default_factory=BAConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    proximity: ProximityConfig = field(default_factory=ProximityConfig)

    def validate(self) -> None:
        """Raise ConfigError naming the first inconsistent field."""
        self.graph.validate()
        self.proximity.validate()
        if self.source not in ("lk", "learned"):
            raise ConfigError(f"patch.source must be 'lk' or 'learned', got {self.source!r}")
        if self.ba.iterations < 1 or self.ba.rounds < 1 or self.ba.init_iterations < 1 or self.ba.init_rounds < 1:
            raise ConfigError("patch.ba iterations/rounds must be >= 1")
        if self.ba.depth_model not in ("prior", "observation") or self.ba.depth_noise not in ("relative", "inverse"):
            raise ConfigError(f"patch.ba.depth_model must be prior|observation and depth_noise relative|inverse, "
                              f"got {self.ba.depth_model!r}, {self.ba.depth_noise!r}")
        if self.ba.lambda_factor <= 1.0:
            raise ConfigError(f"patch.ba.lambda_factor must be > 1, got {self.ba.lambda_factor}")
        if not 0.0 <= self.tracking.motion_damping <= 1.0:
            raise ConfigError(f"patch.tracking.motion_damping must be in [0, 1], got {self.tracking.motion_damping}")
        if not 2 <= self.tracking.init_min_frames <= self.tracking.init_max_frames:
            raise ConfigError("patch.tracking needs 2 <= init_min_frames <= init_max_frames")
        if not 1 <= self.tracking.keyframe_index < self.graph.optimization_window:
            raise ConfigError("patch.tracking.keyframe_index must be in [1, optimization_window)")
