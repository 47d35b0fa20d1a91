"""Pinhole camera math with analytic Jacobians, batched in torch (float32 or float64).

Conventions
-----------
- Intrinsics ``K (..., 4) = [fx, fy, cx, cy]`` (no skew, no distortion: images are undistorted
  upstream by ``fgslam.io.calibration``). Pixel coordinates follow OpenCV: the centre of the
  top-left pixel is ``(0, 0)``, ``u`` grows to the right, ``v`` downwards.
- Camera frame: ``x`` right, ``y`` down, ``z`` forward (optical axis); a point is in front of the
  camera when its ``z`` is positive.
- Inverse-depth parametrisation (DROID-SLAM appendix C, eqs. 6-8): a pixel ``uv`` with inverse
  depth ``d`` is the point ``X = [(u - cx) / fx, (v - cy) / fy, 1] / d``; its homogeneous form
  ``[(u - cx) / fx, (v - cy) / fy, 1, d]`` is what the reprojection factors use, so ``d = 0``
  (a point at infinity) needs no division there.
- Every function accepts any leading batch shape ``...`` (broadcast between arguments) and returns a
  boolean ``valid`` mask of the broadcast batch shape. Invalid rows (point behind the camera, zero
  or negative depth, non-finite input or result) hold zeros in every output, never NaN or inf:
  callers give them zero weight and count them.

Deviation from the first TEAM.md contract: ``project``, ``unproject`` and ``normalize_rays`` return
a third element, the ``valid`` mask, so that degenerate geometry can never pass silently.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .errors import ConfigError

__all__ = [
    "PinholeCamera",
    "StereoRig",
    "normalize_rays",
    "pixel_rays",
    "project",
    "unproject",
]


def _zero_invalid(x: torch.Tensor, valid: torch.Tensor, n_trailing: int) -> torch.Tensor:
    """``x`` with the rows where ``valid`` is False set to 0 (NaN/inf there are dropped too)."""
    mask = valid.reshape(valid.shape + (1,) * n_trailing)
    return torch.where(mask, x, torch.zeros((), dtype=x.dtype, device=x.device))


def project(
    X: torch.Tensor, K: torch.Tensor, min_depth: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pinhole projection of camera-frame points.

    Args:
        X: ``(..., 3)`` points in the camera frame.
        K: ``(..., 4)`` intrinsics ``[fx, fy, cx, cy]`` (broadcast against ``X``).
        min_depth: a point is valid only when its ``z`` is strictly above this value (0: in front).

    Returns:
        ``uv (..., 2)`` with ``u = fx x / z + cx``, ``v = fy y / z + cy``;
        ``J_uv_X (..., 2, 3)`` = d(uv)/dX ``= [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]``;
        ``valid (...)``. Invalid rows are zero in ``uv`` and ``J_uv_X``.
    """
    x, y, z = X.unbind(-1)
    fx, fy, cx, cy = K.unbind(-1)
    valid = z > min_depth
    inv_z = 1.0 / torch.where(valid, z, torch.ones((), dtype=z.dtype, device=z.device))
    xn = x * inv_z
    yn = y * inv_z
    fx_iz = fx * inv_z
    fy_iz = fy * inv_z
    zero = torch.zeros_like(fx_iz)
    uv = torch.stack((fx * xn + cx, fy * yn + cy), dim=-1)
    J = torch.stack(
        (
            torch.stack((fx_iz, zero, -fx_iz * xn), dim=-1),
            torch.stack((zero, fy_iz, -fy_iz * yn), dim=-1),
        ),
        dim=-2,
    )
    valid = valid & torch.isfinite(uv).all(-1) & torch.isfinite(J).all(-1).all(-1)
    return _zero_invalid(uv, valid, 1), _zero_invalid(J, valid, 2), valid


def pixel_rays(uv: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Normalised image coordinates ``p = [(u - cx) / fx, (v - cy) / fy, 1]`` of pixels ``uv (..., 2)``.

    ``p`` is the camera-frame point of unit depth on the pixel's ray; shape ``(..., 3)``.
    """
    u, v = uv.unbind(-1)
    fx, fy, cx, cy = K.unbind(-1)
    xn = (u - cx) / fx
    yn = (v - cy) / fy
    return torch.stack((xn, yn, torch.ones_like(xn)), dim=-1)


def unproject(
    uv: torch.Tensor, inv_depth: torch.Tensor, K: torch.Tensor, min_inv_depth: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Back-project pixels with inverse depth (DROID-SLAM appendix C, eq. 7).

    Args:
        uv: ``(..., 2)`` pixel coordinates.
        inv_depth: ``(...)`` inverse depth ``d = 1 / z`` of each pixel.
        K: ``(..., 4)`` intrinsics ``[fx, fy, cx, cy]``.
        min_inv_depth: a row is valid only when ``d`` is strictly above this value (0: finite depth).

    Returns:
        ``X (..., 3) = [(u - cx) / fx, (v - cy) / fy, 1] / d`` in the camera frame,
        ``dX_dd (..., 3) = -X / d``, ``valid (...)``. Invalid rows are zero.
    """
    p = pixel_rays(uv, K)
    valid = inv_depth > min_inv_depth
    inv_d = 1.0 / torch.where(valid, inv_depth, torch.ones((), dtype=inv_depth.dtype, device=inv_depth.device))
    X = p * inv_d[..., None]
    dX_dd = -X * inv_d[..., None]
    valid = valid & torch.isfinite(X).all(-1) & torch.isfinite(dX_dd).all(-1)
    return _zero_invalid(X, valid, 1), _zero_invalid(dX_dd, valid, 1), valid


def normalize_rays(X: torch.Tensor, min_norm: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Generic central camera of MASt3R-SLAM: ``psi(X) = X / |X|`` (a unit ray) and its Jacobian.

    Args:
        X: ``(..., 3)`` points in the camera frame.
        min_norm: a row is valid only when ``|X|`` is strictly above this value.

    Returns:
        ``psi (..., 3)``, ``J_psi_X (..., 3, 3) = (I - psi psi^T) / |X|``, ``valid (...)``.
        Invalid rows (``X = 0``) are zero.
    """
    norm = torch.linalg.vector_norm(X, dim=-1)
    valid = norm > min_norm
    inv_n = 1.0 / torch.where(valid, norm, torch.ones((), dtype=norm.dtype, device=norm.device))
    psi = X * inv_n[..., None]
    eye = torch.eye(3, dtype=X.dtype, device=X.device)
    J = (eye - psi[..., :, None] * psi[..., None, :]) * inv_n[..., None, None]
    valid = valid & torch.isfinite(psi).all(-1) & torch.isfinite(J).all(-1).all(-1)
    return _zero_invalid(psi, valid, 1), _zero_invalid(J, valid, 2), valid


@dataclass(frozen=True)
class PinholeCamera:
    """An undistorted pinhole camera: intrinsics ``K = (fx, fy, cx, cy)`` in pixels and image size.

    Pixel convention as in the module docstring (OpenCV: pixel centres at integer coordinates).
    """

    K: tuple[float, float, float, float]
    width: int
    height: int

    def __post_init__(self) -> None:
        if len(self.K) != 4:
            raise ConfigError(f"PinholeCamera.K must be [fx, fy, cx, cy], got {self.K!r}")
        K = tuple(float(k) for k in self.K)
        if not all(math.isfinite(k) for k in K) or K[0] <= 0 or K[1] <= 0:
            raise ConfigError(f"PinholeCamera.K needs finite values and fx, fy > 0, got {K!r}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ConfigError(f"PinholeCamera size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def fx(self) -> float:
        return self.K[0]

    @property
    def fy(self) -> float:
        return self.K[1]

    @property
    def cx(self) -> float:
        return self.K[2]

    @property
    def cy(self) -> float:
        return self.K[3]

    def K_tensor(self, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> torch.Tensor:
        """Intrinsics as a ``(4,)`` tensor ``[fx, fy, cx, cy]``."""
        return torch.tensor(self.K, dtype=dtype, device=device)

    def matrix(self) -> np.ndarray:
        """The 3x3 calibration matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (float64)."""
        fx, fy, cx, cy = self.K
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def resized(self, width: int, height: int) -> PinholeCamera:
        """The camera of this image resampled to ``width x height`` pixels (e.g. ``cv2.resize``).

        With pixel centres at integer coordinates a resize by ``a = width / self.width`` maps
        ``u -> a (u + 1/2) - 1/2``, hence ``fx' = a fx`` and ``cx' = a (cx + 1/2) - 1/2`` (same in v).
        """
        if int(width) <= 0 or int(height) <= 0:
            raise ConfigError(f"PinholeCamera.resized: size must be positive, got {width}x{height}")
        ax = int(width) / self.width
        ay = int(height) / self.height
        fx, fy, cx, cy = self.K
        K = (ax * fx, ay * fy, ax * (cx + 0.5) - 0.5, ay * (cy + 0.5) - 0.5)
        return PinholeCamera(K, int(width), int(height))

    def scaled(self, factor: float) -> PinholeCamera:
        """The camera of this image resized by ``factor`` (sizes rounded to whole pixels).

        E.g. ``factor = 1/8`` gives DROID-SLAM's feature resolution. See :meth:`resized` for the
        half-pixel-exact intrinsics.
        """
        if not (factor > 0 and math.isfinite(factor)):
            raise ConfigError(f"PinholeCamera.scaled: factor must be positive and finite, got {factor!r}")
        width = max(1, round(self.width * factor))
        height = max(1, round(self.height * factor))
        return self.resized(width, height)

    def cropped(self, x0: int, y0: int, width: int, height: int) -> PinholeCamera:
        """The camera of the crop ``image[y0:y0 + height, x0:x0 + width]``: ``cx' = cx - x0``, ``cy' = cy - y0``."""
        x0, y0, width, height = int(x0), int(y0), int(width), int(height)
        if x0 < 0 or y0 < 0 or width <= 0 or height <= 0 or x0 + width > self.width or y0 + height > self.height:
            raise ConfigError(
                f"PinholeCamera.cropped: box x0={x0}, y0={y0}, {width}x{height} is not inside the "
                f"{self.width}x{self.height} image"
            )
        fx, fy, cx, cy = self.K
        return PinholeCamera((fx, fy, cx - x0, cy - y0), width, height)

    def contains(self, uv: torch.Tensor, margin: float = 0.0) -> torch.Tensor:
        """Mask ``(...)`` of pixels ``uv (..., 2)`` at least ``margin`` pixels inside the image.

        The image covers ``[-1/2, width - 1/2] x [-1/2, height - 1/2]`` (pixel centres at integers).
        """
        u, v = uv.unbind(-1)
        return (
            (u >= margin - 0.5)
            & (u <= self.width - 0.5 - margin)
            & (v >= margin - 0.5)
            & (v <= self.height - 0.5 - margin)
        )


# A rotation block is accepted as orthonormal when |R^T R - I| and |det R - 1| are below this
# (float64 calibration files carry about 8-9 significant digits).
_ROTATION_TOLERANCE = 1e-6


@dataclass(frozen=True, eq=False)
class StereoRig:
    """A calibrated stereo pair: two pinhole cameras and the fixed right-to-left extrinsics.

    ``T_CLCR (4, 4)`` float64 maps right-camera coordinates to left-camera coordinates,
    ``X_in_CL = R_CLCR X_in_CR + t_CLCR``, in metres (from calibration, e.g. EuRoC
    ``T_BS(cam0)^-1 T_BS(cam1)``). The baseline is derived from it, never assumed.
    """

    left: PinholeCamera
    right: PinholeCamera
    T_CLCR: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        T = np.asarray(self.T_CLCR, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ConfigError(f"StereoRig.T_CLCR must be a finite 4x4 matrix, got shape {T.shape}")
        R = T[:3, :3]
        if (
            np.abs(R.T @ R - np.eye(3)).max() > _ROTATION_TOLERANCE
            or abs(np.linalg.det(R) - 1.0) > _ROTATION_TOLERANCE
            or np.abs(T[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 0.0
        ):
            raise ConfigError("StereoRig.T_CLCR is not a rigid transform (rotation block or last row invalid)")
        if not np.linalg.norm(T[:3, 3]) > 0.0:
            raise ConfigError("StereoRig.T_CLCR has a zero baseline")
        T.setflags(write=False)
        object.__setattr__(self, "T_CLCR", T)

    @property
    def T_CRCL(self) -> np.ndarray:
        """Left-to-right transform ``X_in_CR = R_CRCL X_in_CL + t_CRCL`` (4x4 float64)."""
        R = self.T_CLCR[:3, :3]
        t = self.T_CLCR[:3, 3]
        T = np.eye(4)
        T[:3, :3] = R.T
        T[:3, 3] = -R.T @ t
        return T

    @property
    def baseline(self) -> float:
        """Distance between the two optical centres, ``|t_CLCR|`` in metres."""
        return float(np.linalg.norm(self.T_CLCR[:3, 3]))

    def scaled(self, factor: float) -> StereoRig:
        """Both cameras resized by ``factor`` (extrinsics unchanged)."""
        return StereoRig(self.left.scaled(factor), self.right.scaled(factor), self.T_CLCR)
