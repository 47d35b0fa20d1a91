"""The typed configs of the factor modules, in a module that imports neither torch nor gtsam, so that a
run's configuration (:class:`fgslam.run.config.SlamConfig`) loads and is checked without them (a refused
command answers at once). Each is re-exported by the module that uses it, where its fields are explained:

- :class:`RobustConfig` (and :data:`KernelKind`): :mod:`fgslam.factors.robust`;
- :class:`DepthPriorConfig`: :mod:`fgslam.factors.depth`;
- :class:`PointmapResidualConfig`: :mod:`fgslam.factors.pointmap`;
- :class:`PointmapBlockConfig`: :mod:`fgslam.factors.pointmap_block`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from ..core.config import MAX_COUNT, MAX_IMAGE_SIDE, MAX_SCALAR, MAX_THREADS, ranged
from ..core.errors import ConfigError

__all__ = ["INTRINSICS", "MAX_LEVELS", "PIXEL_DIM", "RAY_DIST_ROWS", "SIM3_DOF", "DepthAlignConfig", "DepthPriorConfig", "KernelKind", "PointmapBlockConfig", "PointmapResidualConfig", "RobustConfig"]

MAX_LEVELS = 8  # pyramid levels of a depth surface (the coarsest steps 2^7 times the finest)
SIM3_DOF = 7  # dimension of the Sim(3) tangent [w(3), u(3), log s]
RAY_DIST_ROWS = 4  # rows of a pointmap ray-and-distance residual: the unit ray (3) and the distance (1)
PIXEL_DIM = 2  # entries of a pixel (u, v): the rows of a reprojection residual
INTRINSICS = 4  # pinhole intrinsics [fx, fy, cx, cy]

KernelKind = Literal["none", "huber", "cauchy", "tukey"]


@dataclass
class RobustConfig:
    """Robust weighting of whitened residuals (see :mod:`fgslam.factors.robust`)."""

    # Robust kernel applied to the whitened residual norm e.
    kind: KernelKind = "huber"
    # Kernel threshold in whitened units: 1.345 is Huber's 95%-efficiency constant under Gaussian
    # noise (Cauchy: 2.3849, Tukey: 4.6851 for the same efficiency).
    delta: float = ranged(1.345, gt=0, le=MAX_SCALAR)
    # Measurements whose confidence is below this get zero weight (MASt3R's q_min; 0 keeps all).
    min_confidence: float = ranged(0.0, ge=0, le=MAX_SCALAR)


@dataclass
class DepthPriorConfig:
    """Noise model of sensor inverse depths (the RGB-D prior of DROID-SLAM section 3.4, and the
    depth rows of the patch frontend's observation model). The patch frontend fills it from
    ``patch.ba.depth_prior_sigma`` and ``patch.ba.depth_noise``."""

    sigma: float = ranged(0.05, gt=0, le=MAX_SCALAR)  # relative (noise: relative) or in 1/m of inverse depth (noise: inverse)
    noise: Literal["relative", "inverse"] = "relative"  # relative: sigma_d = sigma * d_sensor (sigma_z grows with z); inverse: sigma_d = sigma (sigma_z grows with z^2, Kinect)


@dataclass
class PointmapResidualConfig:
    """Noise levels and degeneracy thresholds of the pointmap residuals (defaults: MASt3R-SLAM)."""

    sigma_ray: float = ranged(0.003, gt=0, le=MAX_SCALAR)  # std of the unit-ray difference (dimensionless)
    sigma_dist: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # std of the distance-to-centre difference (pointmap units); weak term
    sigma_point: float = ranged(0.05, gt=0, le=MAX_SCALAR)  # std of the 3-D point difference (pointmap units)
    sigma_pixel: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # std of the pixel difference (px)
    sigma_log_depth: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # std of the log-depth difference (dimensionless)
    min_norm: float = ranged(1e-6, ge=0, le=MAX_SCALAR)  # points with a norm at or below this are degenerate (masked)
    min_depth: float = ranged(1e-6, ge=0, le=MAX_SCALAR)  # calibrated case: z at or below this is behind the camera (masked)


@dataclass
class PointmapBlockConfig:
    """Residuals, weighting and threads of the pointmap blocks."""

    mode: Literal["ray", "calibrated"] = "ray"  # ray + distance rows, or pixel + log-depth rows (needs K and uv_i)
    residual: PointmapResidualConfig = field(default_factory=PointmapResidualConfig)
    robust: RobustConfig = field(default_factory=RobustConfig)  # kernel on each row group's whitened norm; min_confidence drops matches
    threads: int = ranged(1, ge=0, le=MAX_THREADS)  # torch intra-op threads while linearising (0: torch's setting)


@dataclass
class DepthAlignConfig:
    """Depth alignment (:mod:`fgslam.factors.depth_align`): the pyramid, the association gates, the noise model."""

    grid_width: int = ranged(80, ge=4, le=MAX_IMAGE_SIDE)  # points across the finest level (its pixel step: image width // this)
    levels: int = ranged(3, ge=1, le=MAX_LEVELS)  # pyramid levels, each coarser one at twice the step
    min_depth: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # m; sensor depths below this are invalid
    max_depth: float = ranged(8.0, gt=0, le=MAX_SCALAR)  # m; sensor depths above this are invalid
    max_discontinuity: float = ranged(0.01, gt=0, le=MAX_SCALAR)  # relative depth jump per image pixel between grid neighbours that marks an edge (no normal)
    max_distance: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # m; association gate on |T X_f - X_k| on the finest level (a level of stride s: s / finest stride times this)
    max_normal_angle_deg: float = ranged(30.0, gt=0, le=180.0)  # association gate on the angle between the normals
    sigma: float = ranged(0.01, gt=0, le=MAX_SCALAR)  # m; std of the point-to-plane distance at 1 m depth (grows with z^2)
    robust: RobustConfig = field(default_factory=RobustConfig)  # kernel on the whitened distance
    min_pairs: int = ranged(100, ge=1, le=MAX_COUNT)  # fewer associated pairs: the depth does not constrain the pose
    min_pair_fraction: float = ranged(0.5, ge=0, le=1)  # fewer of the frame's vertices paired: the alignment is not trusted (little overlap, or a wrong minimum)
    max_direction_sigma: float = ranged(0.05, gt=0, le=MAX_SCALAR)  # m; a rigid direction counts as constrained when its standard deviation is below this (rotations as displacements at the median depth)

    def validate(self) -> None:
        if self.max_depth <= self.min_depth:
            raise ConfigError(f"depth_align.max_depth ({self.max_depth}) must exceed min_depth ({self.min_depth})")

    def strides(self, width: int) -> tuple[int, ...]:
        """Pixel step of each level (coarse to fine) for images ``width`` pixels wide."""
        finest = max(1, int(width) // self.grid_width)
        return tuple(finest << (self.levels - 1 - i) for i in range(self.levels))
