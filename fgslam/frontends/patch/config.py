"""Typed configuration of the patch frontend (DPVO / DPV-SLAM family).

``PatchConfig`` is the root; it is the ``patch:`` section of the runner's ``SlamConfig`` and loads
on its own with ``fgslam.core.config.load_config(PatchConfig, path, overrides)``. Pixel quantities are
in pixels of the frames as the dataset delivers them (after resizing); windows are counted in
frames of the patch graph (kept frames, DPVO's buffer positions).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Optional

from ...core.config import MAX_COUNT, MAX_IMAGE_SIDE, MAX_ITERATIONS, MAX_KEYFRAMES, MAX_PATCHES_PER_FRAME, MAX_SCALAR, MAX_SEED, MAX_THREADS, MAX_WINDOW, check_ranges, ranged
from ...backend.config import GlobalBAConfig
from ...core.errors import ConfigError
from ...factors.configs import DepthPriorConfig
from ...nets.config import DpvoNetConfig
from ..depth_tracking import DepthTrackingConfig
from ..photometric import PhotometricModel
from .. import DEPTH_BYTES, PYRAMID_FACTOR, MemoryPart, MemorySizes


@dataclass
class PatchGraphConfig:
    """Patch graph (DPV-SLAM section 3.1)."""

    patches_per_frame: int = ranged(96, ge=8, le=MAX_PATCHES_PER_FRAME)  # K random p x p patches per frame, one inverse depth each
    patch_size: int = ranged(3, ge=1, le=MAX_IMAGE_SIDE)  # p: samples per patch side
    patch_stride: int = ranged(7, ge=1, le=MAX_IMAGE_SIDE)  # pixels between patch samples: the tracked footprint is p * stride pixels
    selection: Literal["corners", "random"] = "corners"  # corners: strongest min-eigenvalue pixels spread over a grid; random: uniform (DPVO)
    selection_grid: list[int] = ranged(default_factory=lambda: [8, 4], ge=1, le=MAX_IMAGE_SIDE)  # cells across x, down y; each cell yields the same share of patches
    candidate_block: int = ranged(8, ge=1, le=MAX_IMAGE_SIDE)  # corners: one candidate (local maximum) per block of this many pixels square
    score_width: int = ranged(640, ge=0, le=MAX_IMAGE_SIDE)  # corners: response computed on the image resized to at most this width (0: full resolution)
    border: int = ranged(12, ge=0, le=MAX_IMAGE_SIDE)  # patch centres keep this many pixels from the image border
    seed: int = ranged(0, ge=0, le=MAX_SEED)  # random generator seed of patch selection
    patch_lifetime: int = ranged(5, ge=1, le=MAX_WINDOW)  # a patch gets edges to frames at most this many graph frames away
    removal_window: int = ranged(10, ge=2, le=MAX_WINDOW)  # edges whose source frame is this many graph frames old become inactive
    optimization_window: int = ranged(6, ge=2, le=MAX_WINDOW)  # latest graph frames whose poses are optimised (older ones fixed)
    max_inactive_edges: int = ranged(500_000, ge=0, le=MAX_COUNT)  # bound of the inactive-edge store kept for global optimisation (oldest dropped)

    def validate(self) -> None:
        if self.removal_window <= self.patch_lifetime:
            raise ConfigError(
                f"patch.graph.removal_window ({self.removal_window}) must exceed patch_lifetime ({self.patch_lifetime})"
            )
        if len(self.selection_grid) != 2:
            raise ConfigError(f"patch.graph.selection_grid must be two positive ints, got {self.selection_grid}")

    def effective_border(self) -> int:
        """Pixels patch centres keep from the image border: ``border``, or half the patch footprint
        (``patch_size * patch_stride``) when that is larger."""
        return max(self.border, (self.patch_size * self.patch_stride) // 2 + 1)

    def check_image(self, width: int, height: int) -> None:
        """Raise ConfigError when the border leaves no room for patch centres in a ``width x height``
        image (called when the frontend gets its calibration, before the first frame)."""
        border = self.effective_border()
        if 2 * border >= min(width, height):
            footprint = (f" (patch_size * patch_stride = {self.patch_size * self.patch_stride} px needs {border})"
                         if border > self.border else "")
            raise ConfigError(
                f"patch.graph.border={self.border}{footprint} leaves no room for patch centres in the "
                f"{width}x{height} images: the border must be at most {(min(width, height) - 1) // 2} px"
            )


@dataclass
class LKConfig:
    """Built-in pyramidal Lucas-Kanade measurement source (``source: lk``)."""

    scale: float = ranged(0.0, ge=0, le=1)  # LK runs on images resized by this factor; 0: automatic, the largest factor <= 1 giving width <= auto_width
    auto_width: int = ranged(640, ge=16, le=MAX_IMAGE_SIDE)  # image width (px) the automatic scale aims at
    levels: int = ranged(3, ge=0, le=10)  # pyramid levels above the LK resolution
    iterations: int = ranged(20, ge=1, le=MAX_ITERATIONS)  # LK iterations per level
    epsilon: float = ranged(0.02, gt=0, le=MAX_SCALAR)  # LK stops when the update is below this many pixels
    min_eigen: float = ranged(1e-4, ge=0, le=MAX_SCALAR)  # cv2 minEigThreshold: windows with less texture are rejected
    fb_threshold: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # forward-backward error (px) above which a track is rejected
    fb_sigma: float = ranged(0.5, gt=0, le=MAX_SCALAR)  # forward-backward error (px) at which the confidence halves
    error_sigma: float = ranged(12.0, gt=0, le=MAX_SCALAR)  # mean absolute intensity error (grey levels) at which the confidence halves
    min_confidence: float = ranged(0.05, ge=0, le=1)  # tracks below this confidence are rejected
    photometric: PhotometricModel = "raw"  # raw (brightness constancy) | gain (undo a gain per image, auto-exposure: fgslam/frontends/photometric.py)
    photometric_floor: float = ranged(4.0, gt=0, le=255)  # gain: added to each image's median (grey levels), so a nearly black image is not amplified


@dataclass
class BAConfig:
    """Local bundle adjustment over the optimisation window."""

    iterations: int = ranged(1, ge=1, le=MAX_ITERATIONS)  # Levenberg-Marquardt iterations per update round while tracking
    init_iterations: int = ranged(15, ge=1, le=MAX_ITERATIONS)  # iterations per update round at initialisation
    rounds: int = ranged(2, ge=1, le=MAX_ITERATIONS)  # update rounds per frame: measure (re-track bad edges), then optimise
    init_rounds: int = ranged(3, ge=1, le=MAX_ITERATIONS)  # update rounds at initialisation
    pixel_sigma: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # standard deviation (px) of a full-confidence measurement
    huber_delta: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # Huber threshold on the whitened residual (sigma units)
    outlier_threshold: float = ranged(6.0, gt=0, le=MAX_SCALAR)  # edges with a residual above this (px) after BA get zero weight
    retrack_threshold: float = ranged(2.0, ge=0, le=MAX_SCALAR)  # new edges with a residual above this (px) are re-tracked from the new reprojection
    min_depth: float = ranged(0.05, gt=0, le=MAX_SCALAR)  # smallest valid depth in a target camera (map units; stereo/RGB-D: metres)
    depth_prior_sigma: float = ranged(0.05, gt=0, le=MAX_SCALAR)  # RGB-D: sensor-depth noise, relative (depth_noise: relative) or in 1/m of inverse depth (inverse)
    depth_min: float = ranged(0.1, ge=0, le=MAX_SCALAR)  # RGB-D: sensor depths at or below this (m) are invalid
    depth_max: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # RGB-D: sensor depths above this (m) are invalid
    depth_window: int = ranged(2, ge=0, le=MAX_IMAGE_SIDE)  # RGB-D: half-size (px) of the window whose median is the patch's sensor depth
    depth_max_spread: float = ranged(0.1, ge=0, le=MAX_SCALAR)  # RGB-D: (max - min) / median depth in that window above which it is a discontinuity (no prior)
    stereo_init_steps: int = ranged(5, ge=0, le=MAX_ITERATIONS)  # stereo: per-patch depth Gauss-Newton steps on the first frame's right-image edges
    stereo_init_inv_depth: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # stereo: inverse depth (1/m) the first frame's patches start from, so Lucas-Kanade searches the right image from disparity f * baseline * this (1 m suits an 11 cm baseline; driving's 0.54 m baseline needs the far field, 0.05: from 1 m the search starts 200+ px off and no patch is measured)
    stereo_cross_edges: bool = False  # stereo: also edges into the right images of other frames (else own right image only)
    threads: int = ranged(1, ge=0, le=MAX_THREADS)  # torch threads during BA (small dense work: 1 is fastest)
    depth_model: Literal["prior", "observation"] = "prior"  # RGB-D: prior on each patch's inverse depth in its source frame (DROID-SLAM), or sensor depth as a measurement of every observation, source and targets (ORB-SLAM3 RGB-D: virtual right-camera pixel u - f b / z)
    depth_noise: Literal["relative", "inverse"] = "relative"  # RGB-D (local and global BA): relative: sigma_d = depth_prior_sigma * d (sigma_z grows with z); inverse: sigma_d = depth_prior_sigma in 1/m (sigma_z grows with z^2, Kinect)
    depth_virtual_baseline: float = ranged(0.08, gt=0, le=MAX_SCALAR)  # RGB-D observation model: baseline (m) of the virtual right camera (sets the pixel scale of the depth rows)
    remeasure: Literal["new", "window"] = "new"  # new: a frame's rounds measure its new edges (later rounds re-track the bad ones); window: every round re-measures every active edge of the patch graph (DPVO: each update runs the operator on all edges, carrying each edge's recurrent state)
    measured_huber: bool = False  # a fresh measurement enters the next BA Huber-weighted by its distance from the reprojection it was measured from (else at full weight until that BA's residuals weigh it)

    def depth_noise_model(self) -> DepthPriorConfig:
        """RGB-D: the sensor inverse-depth noise model (``depth_prior_sigma``, ``depth_noise``) of the
        local and the global bundle adjustment (:mod:`fgslam.factors.depth`)."""
        return DepthPriorConfig(sigma=self.depth_prior_sigma, noise=self.depth_noise)


@dataclass
class PatchTrackingConfig:
    """Initialisation, motion model, keyframes, failure handling."""

    init_min_parallax: float = ranged(6.0, ge=0, le=MAX_SCALAR)  # mono: median rotation-compensated flow (px) needed to initialise
    init_min_tracks: int = ranged(30, ge=5, le=MAX_COUNT)  # mono: tracks of the reference patches needed to keep waiting on one reference
    init_min_frames: int = ranged(3, ge=2, le=MAX_WINDOW)  # mono: frames (reference included) collected before initialising
    init_max_frames: int = ranged(8, ge=2, le=MAX_WINDOW)  # mono: frames kept in the initialisation window (older ones subsampled)
    init_ransac_threshold: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # mono: essential-matrix RANSAC threshold (px)
    init_min_inlier_ratio: float = ranged(0.6, ge=0, le=1)  # mono: essential-matrix inlier share needed to initialise
    motion_damping: float = ranged(0.5, ge=0, le=1)  # damped constant velocity: predicted step = damping * last step (DPVO 0.5)
    keyframe_index: int = ranged(3, ge=1, le=MAX_WINDOW)  # frame this many graph frames before the newest is tested for removal
    keyframe_threshold: float = ranged(20.0, ge=0, le=MAX_SCALAR)  # mean flow (px) between its neighbours below which it is removed
    keyframe_flow: str = "raw"  # raw: the keyframe test's mean flow is the full reprojection flow (DPVO); translation: the rotation-compensated flow (each patch reprojected at its depth minus at infinity), so that pure rotation does not keep every frame as a keyframe (rotation-dominant hand-held motion)
    min_valid_edges: int = ranged(24, ge=3, le=MAX_COUNT)  # fewer valid measurements into a new frame is a tracking failure
    max_motion_model_frames: int = ranged(30, ge=1, le=MAX_KEYFRAMES)  # consecutive failures after which the map re-initialises
    rejoin_frames: int = ranged(150, ge=0, le=MAX_KEYFRAMES)  # metric maps with the classical loop closer or a loaded map (--map): a map re-initialised without a relocalisation tries this many of its tracked frames to relocalise among the keyframes before it, and two agreeing relocalisations move it into the old map's frame (frontends/rejoin.py; 0: off)
    rejoin_every: int = ranged(5, ge=1, le=MAX_KEYFRAMES)  # ... one attempt every this many tracked frames
    rejoin_max_translation: float = ranged(0.05, ge=0, le=MAX_SCALAR)  # ... the two relocalisations' transforms (new map -> old map) agree within this (m) ...
    rejoin_max_rotation_deg: float = ranged(2.0, ge=0, le=180)  # ... and this rotation (degrees)
    motion_filter_flow: float = ranged(1.0, ge=0, le=MAX_SCALAR)  # median flow (px) of the newest keyframe's patches into a new frame below which the frame is stationary: not added to the graph, posed from that keyframe (0: off)
    min_inlier_ratio: float = ranged(0.5, ge=0, le=1)  # share of a new frame's measurements that must be BA inliers; fewer: motion its own reprojections contradict, a tracking failure
    max_motion_contradiction: float = ranged(1.5, gt=0, le=2)  # a new frame whose tracked motion departs from the expected (undamped constant-velocity) motion by more than this many times the larger of the two motions (newest keyframe's patches reprojected: 0 as expected, 1 for a start or stop, 2 for a full reversal) ...
    min_contradiction_px: float = ranged(20.0, ge=0, le=MAX_IMAGE_SIDE)  # ... and by more than this median distance (px) is implausible motion, a tracking failure (7-Scenes hand-held reversals: at most 12 px; alternating KITTI / 7-Scenes frames: 29-83 px)
    median_of_measured: bool = False  # mono: new patches get the median inverse depth of the previous frame's patches that have a BA-inlier measurement (else of all of them: the unmeasured ones keep their initial value, which then stays the median)
    min_measured_patches: int = ranged(8, ge=1, le=MAX_COUNT)  # median_of_measured: fewer measured patches than this: the median of all of them


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

    min_gap: int = ranged(30, ge=1, le=MAX_KEYFRAMES)  # keyframes between a query and a candidate at least
    radius: float = ranged(0.5, gt=0, le=MAX_SCALAR)  # candidate camera centres at most this many median query depths away
    max_angle_deg: float = ranged(30.0, gt=0, le=180)  # angle between the optical axes at most
    max_flow_px: float = ranged(60.0, gt=0, le=MAX_SCALAR)  # mean reprojected displacement of the candidate's patches in the query at most
    min_overlap: float = ranged(0.5, ge=0, le=1)  # share of the candidate's patches that reproject into the query image at least
    old_neighbours: int = ranged(1, ge=0, le=MAX_KEYFRAMES)  # keyframes on each side of the candidate whose patches also get loop edges
    new_neighbours: int = ranged(1, ge=0, le=MAX_KEYFRAMES)  # graph frames on each side of the query that also get loop edges
    ransac_threshold_px: float = ranged(1.5, gt=0, le=MAX_SCALAR)  # fundamental-matrix RANSAC threshold on the loop measurements
    min_loop_edges: int = ranged(60, ge=8, le=MAX_COUNT)  # verified loop measurements needed
    min_inlier_ratio: float = ranged(0.5, ge=0, le=1)  # share of valid loop measurements that must be RANSAC inliers
    min_ba_inlier_ratio: float = ranged(0.6, ge=0, le=1)  # share of loop edges with non-zero weight after the global BA (else undone)
    cooldown: int = ranged(10, ge=0, le=MAX_KEYFRAMES)  # keyframes after an accepted proximity loop during which no other is searched
    max_stored_keyframes: int = ranged(5000, ge=1, le=MAX_KEYFRAMES)  # keyframe images kept (PNG in memory) for loop edges; oldest dropped
    ba: GlobalBAConfig = field(default_factory=GlobalBAConfig)


@dataclass
class PatchConfig:
    """Root configuration of :class:`fgslam.frontends.patch.PatchFrontend`."""

    source: Literal["lk", "dpvo", "learned"] = "lk"  # measurement source: built-in Lucas-Kanade or the DPVO network (dpvo; learned: the same)
    checkpoint: Optional[str] = None  # dpvo source: path of the DPVO checkpoint (dpvo.pth)
    dpvo: DpvoNetConfig = field(default_factory=DpvoNetConfig)  # dpvo source: iterations, threads, device
    threads: int = ranged(1, ge=0, le=MAX_THREADS)  # torch threads of the frontend (flow/bookkeeping)
    graph: PatchGraphConfig = field(default_factory=PatchGraphConfig)
    lk: LKConfig = field(default_factory=LKConfig)
    ba: BAConfig = field(default_factory=BAConfig)
    tracking: PatchTrackingConfig = field(default_factory=PatchTrackingConfig)
    proximity: ProximityConfig = field(default_factory=ProximityConfig)
    depth_align: DepthTrackingConfig = field(default_factory=DepthTrackingConfig)  # RGB-D: point-to-plane depth alignment in tracking and the window

    def wants_colour(self) -> bool:
        """The DPVO source takes the colour image (the official network's input); Lucas-Kanade grey."""
        return self.source in ("dpvo", "learned")

    def validate(self) -> None:
        """Raise ConfigError naming the first field out of its range or inconsistent with another."""
        check_ranges(self, "patch.")
        self.graph.validate()
        self.depth_align.validate()
        if self.source not in ("lk", "dpvo", "learned"):
            raise ConfigError(f"patch.source must be 'lk' or 'dpvo', got {self.source!r}")
        if self.ba.depth_model not in ("prior", "observation") or self.ba.depth_noise not in ("relative", "inverse"):
            raise ConfigError(f"patch.ba.depth_model must be prior|observation and depth_noise relative|inverse, "
                              f"got {self.ba.depth_model!r}, {self.ba.depth_noise!r}")
        if self.ba.remeasure not in ("new", "window"):
            raise ConfigError(f"patch.ba.remeasure must be new or window, got {self.ba.remeasure!r}")
        if not self.ba.depth_max > self.ba.depth_min:
            raise ConfigError(f"patch.ba.depth_max ({self.ba.depth_max}) must exceed depth_min ({self.ba.depth_min})")
        if not self.tracking.init_min_frames <= self.tracking.init_max_frames:
            raise ConfigError("patch.tracking needs init_min_frames <= init_max_frames")
        if self.tracking.keyframe_flow not in ("raw", "translation"):
            raise ConfigError("patch.tracking.keyframe_flow must be raw or translation")
        if not self.tracking.keyframe_index < self.graph.optimization_window:
            raise ConfigError("patch.tracking.keyframe_index must be in [1, optimization_window)")


# ----------------------------------------------------------------------------------------- memory estimate

#: B per patch-graph edge: its bookkeeping rows (ids, uv, confidence, weights ~ 70 B) plus the
#: bundle adjustment's linearisation (float64 residuals and 2 x 13 Jacobian entries, ~ 300 B)
PATCH_EDGE_BYTES = 400
#: B per edge of the inactive-edge store (uv_src, uv, confidence, inverse depth, ids)
INACTIVE_EDGE_BYTES = 100
#: B per patch of a graph frame (centre, inverse depths, colour, per-patch state)
PATCH_BYTES = 64
#: B per pixel of a keyframe image kept as PNG for proximity loop edges (compressed grey)
PNG_BYTES_PER_PIXEL = 0.5
#: B per pixel of a float32 image processing (corner score: gradients, structure tensor, response)
SCORE_BYTES_PER_PIXEL = 24


def _fit_width(width: int, height: int, target: int) -> tuple[int, int]:
    """``width x height`` resized to at most ``target`` wide (aspect kept; 0: unchanged)."""
    if target <= 0 or target >= width:
        return width, height
    return target, max(1, round(height * target / width))


def memory_parts(cfg: PatchConfig, sizes: MemorySizes) -> list[MemoryPart]:
    """The patch family's parts of a run's peak-memory estimate (its registry entry's ``memory``,
    :mod:`fgslam.run.memory`): the tracked frames and their Lucas-Kanade pyramids, the graph's active
    and inactive edges, and with proximity loops the stored keyframe images."""
    width, height, size_keys = sizes.width, sizes.height, sizes.size_keys
    g, lk = cfg.graph, cfg.lk
    cams = 2 if sizes.stereo else 1
    if lk.scale > 0:
        lk_w, lk_h = max(1, round(width * lk.scale)), max(1, round(height * lk.scale))
    else:
        lk_w, lk_h = _fit_width(width, height, lk.auto_width)
    score_w, score_h = _fit_width(width, height, g.score_width)
    frames_kept = g.removal_window + cfg.tracking.init_max_frames
    per_frame = (float(lk_w) * lk_h * PYRAMID_FACTOR * cams + float(width) * height * DEPTH_BYTES * sizes.rgbd
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
    if sizes.loop_mode in ("proximity", "both"):
        p = cfg.proximity
        parts.append(MemoryPart(
            "patch proximity loops",
            float(p.max_stored_keyframes) * lk_w * lk_h * PNG_BYTES_PER_PIXEL
            + float(min(p.ba.chunk_edges, g.max_inactive_edges + edges)) * PATCH_EDGE_BYTES,
            [f"patch.proximity.max_stored_keyframes={p.max_stored_keyframes}",
             f"patch.proximity.ba.chunk_edges={p.ba.chunk_edges}"]))
    return parts
