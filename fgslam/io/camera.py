"""The camera a script describes to :class:`fgslam.Slam`: intrinsics, image size, distortion and the
optional stereo partner and IMU extrinsics, in the units and frames of :mod:`fgslam.io.calibration`.

:class:`Camera` is the public, typed face of :class:`~fgslam.io.calibration.Calibration`: a script
writes ``fgslam.Camera(fx, fy, cx, cy, width, height)``, a calibration YAML gives
:meth:`Camera.from_yaml`, and a dataset opened by :func:`fgslam.open_dataset` gives the camera of
the frames it yields (:meth:`Camera.of_frames`: those are already undistorted, rectified and resized,
so the system uses them as they come).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from .calibration import Calibration

_NO_DISTORTION = "none"
_DEFAULT_MODEL = "radtan"  # OpenCV's [k1, k2, p1, p2(, k3)], what cv2.calibrateCamera gives


@dataclass(frozen=True, eq=False)  # numpy fields: no element-wise __eq__
class Camera:
    """A pinhole camera (and its stereo partner), in pixels of the images given to ``Slam.track``.

    Attributes:
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels (OpenCV: the centre of the top-left pixel is ``(0, 0)``).
        width, height: image size in pixels.
        distortion: lens distortion coefficients in OpenCV order (empty: none).
        model: distortion model, ``radtan`` (``[k1, k2, p1, p2(, k3)]``) or ``equidistant``
            (``[k1, k2, k3, k4]``, OpenCV's fisheye); ignored without coefficients.
        baseline: stereo baseline in metres for a rectified pair with the same intrinsics (the right
            camera at ``+x`` of the left); or give ``right`` and ``T_CLCR``.
        right: the right camera of a stereo pair (its own ``right`` is None).
        T_CLCR: ``(4, 4)`` right-to-left camera transform (``X_CL = T_CLCR X_CR``), metres.
        T_BC: ``(4, 4)`` camera-to-body (IMU) transform (``X_B = T_BC X_C``), metres; needed for IMU fusion.
        prepared: the images are already undistorted, rectified and resized for the run (the frames of
            :func:`fgslam.open_dataset`): the system uses them as they come.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: Sequence[float] = ()
    model: str = _DEFAULT_MODEL
    baseline: Optional[float] = None
    right: Optional["Camera"] = None
    T_CLCR: Optional[np.ndarray] = None
    T_BC: Optional[np.ndarray] = None
    prepared: bool = field(default=False)

    def calibration(self) -> Calibration:
        """This camera as a validated :class:`~fgslam.io.calibration.Calibration` (DataError naming
        what is wrong: a principal point outside the image, a wrong number of coefficients, ...)."""
        right, T_CLCR = None, None
        if self.right is not None:
            right = self.right._single()
            T_CLCR = None if self.T_CLCR is None else np.asarray(self.T_CLCR, dtype=np.float64)
        elif self.baseline is not None:
            right = self._single()
            T_CLCR = np.eye(4)
            T_CLCR[0, 3] = float(self.baseline)
        calib = self._single()
        data = calib.to_dict()
        if self.T_BC is not None:
            data["T_BC"] = np.asarray(self.T_BC, dtype=np.float64).reshape(-1).tolist()
        if right is not None:
            data["right"] = right.to_dict()
            data["T_CLCR"] = None if T_CLCR is None else np.asarray(T_CLCR, dtype=np.float64).reshape(-1).tolist()
        return Calibration.from_dict(data, "fgslam.Camera").validate("fgslam.Camera")

    def _single(self) -> Calibration:
        coeffs = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
        model = self.model if coeffs.size else _NO_DISTORTION
        K = np.array([self.fx, self.fy, self.cx, self.cy], dtype=np.float64)
        return Calibration(self.width, self.height, K, model, coeffs)

    @classmethod
    def from_calibration(cls, calib: Calibration, prepared: bool = False) -> "Camera":
        """The camera of a :class:`~fgslam.io.calibration.Calibration` (``prepared``: see the attribute)."""
        right = None if calib.right is None else cls.from_calibration(calib.right)
        fx, fy, cx, cy = (float(v) for v in calib.K)
        return cls(fx, fy, cx, cy, calib.width, calib.height, tuple(float(v) for v in calib.distortion),
                   calib.distortion_model if calib.distortion.size else _DEFAULT_MODEL, None, right,
                   None if calib.T_CLCR is None else np.array(calib.T_CLCR, dtype=np.float64),
                   None if calib.T_BC is None else np.array(calib.T_BC, dtype=np.float64), prepared)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "Camera":
        """The camera of a calibration YAML (keys: :mod:`fgslam.io.calibration`); DataError naming the file."""
        return cls.from_calibration(Calibration.from_yaml(path).validate(str(path)))

    @classmethod
    def of_frames(cls, calib: Calibration) -> "Camera":
        """The camera of frames a loader already undistorted, rectified and resized (``prepared``)."""
        return cls.from_calibration(calib, prepared=True)
