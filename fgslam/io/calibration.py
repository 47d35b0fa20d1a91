"""Camera calibration: intrinsics, distortion, extrinsics, and their YAML files.

Conventions
-----------
- ``K`` is the 4-vector ``[fx, fy, cx, cy]`` in pixels; pixel ``(u, v)`` has its origin at the
  *centre* of the top-left pixel (OpenCV), so a pixel centre is at integer coordinates.
- Distortion models (coefficients in OpenCV order):
  ``none`` (no coefficients), ``radtan`` (``[k1, k2, p1, p2]`` or ``[k1, k2, p1, p2, k3]``: the
  OpenCV / EuRoC "radial-tangential" model), ``equidistant`` (``[k1, k2, k3, k4]``: Kannala-Brandt,
  OpenCV ``cv2.fisheye``).
- ``T_BC`` (4x4) maps points of the camera frame into the body (= IMU) frame:
  ``X_in_B = T_BC @ X_in_C``.  ``T_CLCR`` (4x4) maps points of the right camera frame into the
  left camera frame: ``X_in_CL = T_CLCR @ X_in_CR``; for a rectified horizontal rig it is a pure
  translation ``[b, 0, 0]`` with baseline ``b > 0`` (the right camera sits at ``+x`` of the left).

Calibration YAML (``Calibration.from_yaml``) keys::

    width: 640                      # image size in pixels (required)
    height: 480
    intrinsics: [fx, fy, cx, cy]    # required
    distortion_model: none          # none | radtan | equidistant (default none)
    distortion: []                  # coefficients as above (default none)
    rate_hz: 30                     # optional: frame rate for folders/videos without timestamps
    T_BC: [16 numbers, row-major]   # optional camera-to-body (IMU) transform
    right:                          # optional right camera: same keys width..distortion
      {width: ..., height: ..., intrinsics: [...], distortion_model: ..., distortion: [...]}
    T_CLCR: [16 numbers, row-major] # required with ``right``

:mod:`fgslam.io.undistort` turns raw images of a calibration into undistorted (and rectified) ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional

import numpy as np
from numpy.typing import ArrayLike

from ..core.config import read_yaml
from ..core.errors import DataError

DISTORTION_MODELS = ("none", "radtan", "equidistant")
# number of coefficients accepted per model (OpenCV order, see the module docstring)
DISTORTION_SIZES = {"none": (0,), "radtan": (4, 5), "equidistant": (4,)}
# a pose's bottom row / rotation must be exact to this (files store ~9 significant digits)
TRANSFORM_TOL = 1e-4


def _as_transform(value: ArrayLike, what: str, source: str) -> np.ndarray:
    T = np.asarray(value, dtype=np.float64)
    if T.size != 16:
        raise DataError(f"{source}: {what} must have 16 numbers (4x4 row-major), got {T.size}")
    T = T.reshape(4, 4)
    R = T[:3, :3]
    if not np.all(np.isfinite(T)) or np.abs(T[3] - [0, 0, 0, 1]).max() > TRANSFORM_TOL:
        raise DataError(f"{source}: {what} is not a rigid transform (bottom row {T[3].tolist()})")
    if np.abs(R.T @ R - np.eye(3)).max() > TRANSFORM_TOL or np.linalg.det(R) <= 0:
        raise DataError(f"{source}: {what} has a rotation block that is not a rotation matrix")
    return T


@dataclass(eq=False)  # numpy fields: no element-wise __eq__
class Calibration:
    """Intrinsics/extrinsics of a (stereo) camera, see the module docstring for conventions.

    Attributes:
        width, height: image size in pixels the intrinsics refer to.
        K: ``(4,)`` float64 ``[fx, fy, cx, cy]``.
        distortion_model: ``none | radtan | equidistant``.
        distortion: ``(n,)`` float64 coefficients of the model.
        T_BC: optional ``(4, 4)`` camera-to-body (IMU) transform.
        right: optional calibration of the right camera (its own ``right`` is None).
        T_CLCR: ``(4, 4)`` right-to-left camera transform; required when ``right`` is given.
    """

    width: int
    height: int
    K: np.ndarray
    distortion_model: str = "none"
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(0))
    T_BC: Optional[np.ndarray] = None
    right: Optional["Calibration"] = None
    T_CLCR: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(-1)
        self.distortion = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
        self.width, self.height = int(self.width), int(self.height)

    def validate(self, source: str = "calibration") -> "Calibration":
        """Check shapes and values; raise DataError naming ``source``. Returns self."""
        if self.width <= 0 or self.height <= 0:
            raise DataError(f"{source}: image size must be positive, got {self.width}x{self.height}")
        if self.K.shape != (4,) or not np.all(np.isfinite(self.K)) or self.K[0] <= 0 or self.K[1] <= 0:
            raise DataError(f"{source}: intrinsics must be 4 finite numbers fx, fy, cx, cy with fx, fy > 0, got {self.K.tolist()}")
        cx, cy = self.K[2], self.K[3]
        if not (-0.5 <= cx <= self.width - 0.5 and -0.5 <= cy <= self.height - 0.5):
            raise DataError(
                f"{source}: principal point ({cx:g}, {cy:g}) lies outside the {self.width}x{self.height} image "
                f"(intrinsics are [fx, fy, cx, cy] in pixels of this image size)"
            )
        if self.distortion_model not in DISTORTION_MODELS:
            raise DataError(f"{source}: unknown distortion model {self.distortion_model!r} (expected one of {', '.join(DISTORTION_MODELS)})")
        if self.distortion.size not in DISTORTION_SIZES[self.distortion_model]:
            raise DataError(
                f"{source}: distortion model {self.distortion_model} needs {' or '.join(map(str, DISTORTION_SIZES[self.distortion_model]))} "
                f"coefficients, got {self.distortion.size}"
            )
        if not np.all(np.isfinite(self.distortion)):
            raise DataError(f"{source}: non-finite distortion coefficient")
        if self.T_BC is not None:
            self.T_BC = _as_transform(self.T_BC, "T_BC", source)
        if self.right is not None:
            if self.right.right is not None:
                raise DataError(f"{source}: the right camera cannot have a right camera itself")
            self.right.validate(source + " (right camera)")
            if self.T_CLCR is None:
                raise DataError(f"{source}: a right camera needs T_CLCR")
            self.T_CLCR = _as_transform(self.T_CLCR, "T_CLCR", source)
            if np.linalg.norm(self.T_CLCR[:3, 3]) == 0:
                raise DataError(f"{source}: T_CLCR has a zero baseline")
        elif self.T_CLCR is not None:
            raise DataError(f"{source}: T_CLCR given without a right camera")
        return self

    # ------------------------------------------------------------------ accessors
    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)``."""
        return self.width, self.height

    @property
    def has_stereo(self) -> bool:
        return self.right is not None

    @property
    def baseline(self) -> float:
        """Distance between the left and right camera centres, metres (0 for a mono camera)."""
        return 0.0 if self.T_CLCR is None else float(np.linalg.norm(self.T_CLCR[:3, 3]))

    def K_matrix(self) -> np.ndarray:
        """The 3x3 camera matrix."""
        fx, fy, cx, cy = self.K
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def check_image_size(self, width: int, height: int, source: str) -> None:
        """Raise DataError when an image of ``width x height`` does not match this calibration."""
        if (width, height) != (self.width, self.height):
            raise DataError(
                f"{source}: image size {width}x{height} does not match the calibration ({self.width}x{self.height})"
            )

    # ------------------------------------------------------------------ geometry edits
    def resized(self, width: int, height: int) -> "Calibration":
        """Calibration of the image resized to ``width x height`` (pixel-centre convention:
        ``u' = (u + 0.5) * sx - 0.5``). Only for undistorted (``none``) mono or rectified cameras."""
        sx, sy = width / self.width, height / self.height
        fx, fy, cx, cy = self.K
        K = np.array([fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5])
        right = None if self.right is None else self.right.resized(width, height)
        return replace(self, width=width, height=height, K=K, right=right)

    def cropped(self, x0: int, y0: int, width: int, height: int) -> "Calibration":
        """Calibration of the window ``[x0, x0 + width) x [y0, y0 + height)`` of the image."""
        K = self.K - np.array([0.0, 0.0, x0, y0])
        right = None if self.right is None else self.right.cropped(x0, y0, width, height)
        return replace(self, width=width, height=height, K=K, right=right)

    # ------------------------------------------------------------------ YAML
    @classmethod
    def from_dict(cls, data: dict, source: str = "<dict>") -> "Calibration":
        """Build from the YAML keys of the module docstring; DataError names ``source`` and the key."""
        if not isinstance(data, dict):
            raise DataError(f"{source}: calibration must be a mapping")
        allowed = {"width", "height", "intrinsics", "distortion_model", "distortion", "rate_hz", "T_BC", "right", "T_CLCR"}
        unknown = sorted(set(data) - allowed)
        if unknown:
            raise DataError(f"{source}: unknown calibration key {unknown[0]!r} (valid: {', '.join(sorted(allowed))})")
        for key in ("width", "height", "intrinsics"):
            if key not in data:
                raise DataError(f"{source}: missing calibration key {key!r}")
        try:
            right = None
            if data.get("right") is not None:
                right = cls.from_dict(dict(data["right"]), source + " (right)")
            calib = cls(
                width=int(data["width"]),
                height=int(data["height"]),
                K=np.asarray(data["intrinsics"], dtype=np.float64),
                distortion_model=str(data.get("distortion_model", "none")),
                distortion=np.asarray(data.get("distortion", []) or [], dtype=np.float64),
                T_BC=None if data.get("T_BC") is None else np.asarray(data["T_BC"], dtype=np.float64),
                right=right,
                T_CLCR=None if data.get("T_CLCR") is None else np.asarray(data["T_CLCR"], dtype=np.float64),
            )
        except (TypeError, ValueError) as exc:
            raise DataError(f"{source}: malformed calibration value: {exc}") from exc
        return calib.validate(source)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "Calibration":
        """Read a calibration YAML (keys in the module docstring)."""
        return cls.from_dict(read_yaml_file(path), str(path))

    def to_dict(self) -> dict[str, object]:
        """Inverse of ``from_dict`` (plain Python types)."""
        out: dict[str, object] = {
            "width": self.width,
            "height": self.height,
            "intrinsics": self.K.tolist(),
            "distortion_model": self.distortion_model,
            "distortion": self.distortion.tolist(),
        }
        if self.T_BC is not None:
            out["T_BC"] = self.T_BC.reshape(-1).tolist()
        if self.right is not None:
            out["right"] = self.right.to_dict()
            out["T_CLCR"] = self.T_CLCR.reshape(-1).tolist()
        return out


def read_yaml_file(path: str | Path) -> dict:
    """Read a calibration or dataset YAML file (:func:`fgslam.core.config.read_yaml`, the one UTF-8 YAML
    reader, which tolerates OpenCV's ``%YAML:1.0`` header line of EuRoC's ``sensor.yaml``); its errors
    are DataErrors: the file is the dataset's."""
    return read_yaml(path, DataError, "YAML file")
