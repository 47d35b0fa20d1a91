"""Undistortion and stereo rectification of raw images with OpenCV, for the dataset loaders.

``Undistorter`` turns raw images into undistorted (and, for a stereo pair, rectified) pinhole
images, optionally resized and centre-cropped to a multiple of ``crop_multiple`` in the same single
``cv2.remap`` pass; ``Undistorter.calibration`` is the calibration of the output images
(``distortion_model == "none"``) and ``T_C_Cout`` the rotation from the output (rectified) left
camera frame to the raw left camera frame (identity without rectification). The calibration and
its conventions are :mod:`fgslam.io.calibration`'s.
"""

from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

from ..core.errors import DataError
from .calibration import Calibration

# Sanity of an undistortion (checked on its remap tables, whatever the model and coefficients):
# at least this share of the output pixels must sample the raw image, and the output must show at
# least this share of the raw image's area (sane lenses: 0.8-1.0; a distortion OpenCV cannot invert
# over the image gives a zoom onto its centre, e.g. k1 = 50: 0.0004).
UNDISTORT_MIN_VALID_FRACTION = 0.5
UNDISTORT_MIN_RAW_COVERAGE = 0.25


class Undistorter:
    """Undistort (and rectify a stereo pair), resize and crop images in one ``cv2.remap``.

    Args:
        calib: raw calibration (validated).
        rectify: for a stereo calibration, rectify the pair (``cv2.stereoRectify`` /
            ``cv2.fisheye.stereoRectify``, zero-disparity principal points) so that epipolar lines
            are image rows; otherwise undistort each camera on its own (``T_CLCR`` unchanged).
        alpha: free scaling of the undistorted image: 0 keeps only valid pixels (no black border),
            1 keeps every source pixel (``balance`` for the fisheye model).
        out_size: ``(width, height)`` to resize to before cropping; None keeps the raw size.
        crop_multiple: centre-crop the (resized) image so that width and height are multiples of
            this (values <= 1 disable cropping).
        source: what the calibration came from (a file), named in errors.
        rectification: ``(R1, R2, P1, P2)`` of a stereo pair as recorded (ROS camera_info ``R`` and
            ``P``), used instead of ``cv2.stereoRectify`` when rectifying (``alpha`` then has no effect).

    Raises:
        DataError: the calibration cannot be undistorted sanely: OpenCV finds no finite output
            camera, or the remap tables fold over, sample outside the raw image for most output
            pixels, or show only a small part of the raw image (see :func:`check_undistortion_map`).

    Attributes:
        calibration: calibration of the output images (distortion ``none``).
        T_C_Cout: ``(4, 4)`` rotation taking points of the output left camera frame into the raw
            left camera frame (identity unless stereo rectification rotated the camera). Ground
            truth and ``T_BC`` of the raw camera are converted by right-multiplying it.
        crop_offset: ``(x0, y0)`` of the crop window in the resized image.
    """

    def __init__(
        self,
        calib: Calibration,
        rectify: bool = True,
        alpha: float = 0.0,
        out_size: Optional[tuple[int, int]] = None,
        crop_multiple: int = 1,
        source: str = "calibration",
        rectification: Optional[tuple] = None,
    ) -> None:
        self.raw = calib
        self.rectification: Optional[tuple] = None  # (R1, R2, P1, P2) of a rectified stereo pair
        size = (calib.width, calib.height)
        K1, D1 = calib.K_matrix(), self._coeffs(calib)
        R1 = np.eye(3)
        R2 = None
        stereo = calib.right is not None
        if stereo and rectify:
            K2, D2 = calib.right.K_matrix(), self._coeffs(calib.right)
            if (calib.right.width, calib.right.height) != size:
                raise DataError(f"{source}: stereo rectification needs left and right images of the same size")
            T_CRCL = np.linalg.inv(calib.T_CLCR)
            R, t = np.ascontiguousarray(T_CRCL[:3, :3]), np.ascontiguousarray(T_CRCL[:3, 3].reshape(3, 1))
            if rectification is not None:
                R1, R2, P1, P2 = (np.asarray(m, dtype=np.float64) for m in rectification)
            elif calib.distortion_model == "equidistant" and calib.right.distortion_model == "equidistant":
                R1, R2, P1, P2, _ = cv2.fisheye.stereoRectify(
                    K1, D1, K2, D2, size, R, t, flags=cv2.CALIB_ZERO_DISPARITY, newImageSize=size, balance=alpha
                )
            elif "equidistant" in (calib.distortion_model, calib.right.distortion_model):
                raise DataError(f"{source}: stereo rectification of mixed fisheye / pinhole cameras is not supported")
            else:
                R1, R2, P1, P2, *_ = cv2.stereoRectify(
                    K1, D1, K2, D2, size, R, t, flags=cv2.CALIB_ZERO_DISPARITY, alpha=alpha
                )
            self.rectification = (R1, R2, P1, P2)
            fx, fy, cx, cy = P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2]
            baseline = -P2[0, 3] / P2[0, 0]
            T_CLCR_out = np.eye(4)
            T_CLCR_out[0, 3] = baseline
            right_K = np.array([P2[0, 0], P2[1, 1], P2[0, 2], P2[1, 2]])
            base = Calibration(calib.width, calib.height, [fx, fy, cx, cy], "none", [], None,
                               Calibration(calib.width, calib.height, right_K), T_CLCR_out)
        else:
            base = Calibration(calib.width, calib.height, self._new_K(calib, alpha))
            if stereo:
                base.right = Calibration(calib.width, calib.height, self._new_K(calib.right, alpha))
                base.T_CLCR = calib.T_CLCR.copy()
        self.T_C_Cout = np.eye(4)
        self.T_C_Cout[:3, :3] = R1.T
        if calib.T_BC is not None:
            base.T_BC = calib.T_BC @ self.T_C_Cout

        out_w, out_h = out_size if out_size is not None else size
        out = base.resized(out_w, out_h) if (out_w, out_h) != size else base
        x0 = y0 = 0
        if crop_multiple > 1:
            cw, ch = (out_w // crop_multiple) * crop_multiple, (out_h // crop_multiple) * crop_multiple
            if cw == 0 or ch == 0:
                raise DataError(f"image of {out_w}x{out_h} is smaller than the crop multiple {crop_multiple}")
            x0, y0 = (out_w - cw) // 2, (out_h - ch) // 2
            out = out.cropped(x0, y0, cw, ch)
        if not (np.all(np.isfinite(out.K)) and (out.right is None or np.all(np.isfinite(out.right.K)))):
            raise DataError(
                f"{source}: OpenCV finds no undistorted camera for distortion {calib.distortion_model} "
                f"{calib.distortion.tolist()}: the distortion cannot be inverted over the image"
            )
        self.calibration = out.validate(f"{source} (undistorted output calibration)")
        self.crop_offset = (x0, y0)

        identity = (
            calib.distortion_model == "none"
            and np.allclose(R1, np.eye(3))
            and np.allclose(out.K + [0, 0, x0, y0], calib.K)
            and (out_w, out_h) == size
            and (not stereo or (calib.right.distortion_model == "none" and np.allclose(out.right.K + [0, 0, x0, y0], calib.right.K)))
        )
        self._identity = identity
        if identity:
            self._maps = None
            self._maps_right = None
        else:
            self._maps = self._build_maps(calib, R1, out)
            check_undistortion_map(*self._maps, calib, source)
            self._maps_right = None
            if stereo:
                self._maps_right = self._build_maps(calib.right, np.eye(3) if R2 is None else R2, out.right)
                check_undistortion_map(*self._maps_right, calib.right, source + " (right camera)")
        # depth rescaling for the rectification rotation: z_out = z_raw / (R1^T r)_z with r the
        # output ray [(u-cx)/fx, (v-cy)/fy, 1] of each output pixel (1 everywhere when R1 = I)
        self._depth_scale = None
        if not np.allclose(R1, np.eye(3)):
            fx, fy, cx, cy = out.K
            u, v = np.meshgrid(np.arange(out.width), np.arange(out.height))
            rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u, dtype=np.float64)], axis=-1)
            z_raw_per_unit = rays @ R1[:, 2]  # (R1^T r)_z: row 2 of R1^T is column 2 of R1
            self._depth_scale = (1.0 / z_raw_per_unit).astype(np.float32)
        self._R1 = R1
        self._R2 = R2

    @staticmethod
    def _coeffs(calib: Calibration) -> np.ndarray:
        if calib.distortion_model == "none":
            return np.zeros(4)
        return calib.distortion.copy()

    @classmethod
    def _new_K(cls, calib: Calibration, alpha: float) -> np.ndarray:
        if calib.distortion_model == "none":
            return calib.K.copy()
        size = (calib.width, calib.height)
        if calib.distortion_model == "equidistant":
            Kn = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
                calib.K_matrix(), cls._coeffs(calib), size, np.eye(3), balance=alpha
            )
        else:
            Kn, _ = cv2.getOptimalNewCameraMatrix(calib.K_matrix(), cls._coeffs(calib), size, alpha, size)
        return np.array([Kn[0, 0], Kn[1, 1], Kn[0, 2], Kn[1, 2]])

    @classmethod
    def _build_maps(cls, raw: Calibration, R: np.ndarray, out: Calibration) -> tuple[np.ndarray, np.ndarray]:
        size = (out.width, out.height)
        P = out.K_matrix()
        if raw.distortion_model == "equidistant":
            return cv2.fisheye.initUndistortRectifyMap(raw.K_matrix(), cls._coeffs(raw), R, P, size, cv2.CV_32FC1)
        return cv2.initUndistortRectifyMap(raw.K_matrix(), cls._coeffs(raw), R, P, size, cv2.CV_32FC1)

    def _apply(self, img: np.ndarray, maps, interpolation: int) -> np.ndarray:
        out = self.calibration
        if self._identity:
            x0, y0 = self.crop_offset
            return np.ascontiguousarray(img[y0 : y0 + out.height, x0 : x0 + out.width])
        return cv2.remap(img, maps[0], maps[1], interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def left(self, img: np.ndarray) -> np.ndarray:
        """Output left image (bilinear) from a raw left image (grey or colour)."""
        return self._apply(img, self._maps, cv2.INTER_LINEAR)

    def right(self, img: np.ndarray) -> np.ndarray:
        """Output right image from a raw right image; needs a stereo calibration."""
        if self.raw.right is None:
            raise DataError("right image given but the calibration has no right camera")
        return self._apply(img, self._maps_right, cv2.INTER_LINEAR)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """Output depth (float32 metres, 0 invalid) from a raw left-camera z-depth map.

        Nearest-neighbour sampling (depths are never blended across edges); with stereo
        rectification the z coordinate is re-expressed in the rotated output camera frame.
        """
        out = self._apply(depth.astype(np.float32, copy=False), self._maps, cv2.INTER_NEAREST)
        if self._depth_scale is not None:
            out = out * self._depth_scale
        return out

    def points(self, uv: np.ndarray, right: bool = False) -> np.ndarray:
        """Map raw pixel coordinates ``(N, 2)`` to output pixel coordinates ``(N, 2)``."""
        raw = self.raw.right if right else self.raw
        if raw is None:
            raise DataError("right-camera points given but the calibration has no right camera")
        out = self.calibration.right if right else self.calibration
        R = (self._R2 if self._R2 is not None else np.eye(3)) if right else self._R1
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if raw.distortion_model == "equidistant":
            res = cv2.fisheye.undistortPoints(pts, raw.K_matrix(), self._coeffs(raw), R=R, P=out.K_matrix())
        else:
            res = cv2.undistortPoints(pts, raw.K_matrix(), self._coeffs(raw), R=R, P=out.K_matrix())
        return res.reshape(-1, 2)


def check_undistortion_map(map_x: np.ndarray, map_y: np.ndarray, raw: Calibration, source: str) -> None:
    """Raise DataError naming ``source`` when remap tables (raw pixel of every output pixel) are not
    those of a sane undistortion: independent of the model, its coefficients and the rectification.

    - Folding: the raw x of consecutive output pixels of a row (raw y down a column) must increase
      wherever both sample the raw image; a distortion that is not one-to-one over the image (e.g.
      strong barrel terms beyond their turning point) folds the image onto itself.
    - Mostly invalid: at least ``UNDISTORT_MIN_VALID_FRACTION`` of the output pixels sample the raw image.
    - Raw image mapped outside the output: the output border, traced in raw pixels (clipped to the
      raw image), encloses at least ``UNDISTORT_MIN_RAW_COVERAGE`` of the raw image's area.
    """
    w, h = raw.width, raw.height
    what = f"distortion {raw.distortion_model} {raw.distortion.tolist()} with intrinsics {raw.K.tolist()}"
    mx, my = np.asarray(map_x, dtype=np.float64), np.asarray(map_y, dtype=np.float64)
    inside = (mx >= -0.5) & (mx <= w - 0.5) & (my >= -0.5) & (my <= h - 0.5)
    fold_x = (np.diff(mx, axis=1) <= 0) & inside[:, 1:] & inside[:, :-1]
    fold_y = (np.diff(my, axis=0) <= 0) & inside[1:] & inside[:-1]
    if np.any(fold_x) or np.any(fold_y):
        v, u = np.argwhere(fold_x)[0] if np.any(fold_x) else np.argwhere(fold_y)[0]
        n = int(fold_x.sum() + fold_y.sum())
        raise DataError(
            f"{source}: the {what} is not one-to-one over the image: the undistortion folds the image onto "
            f"itself ({n} output pixel pairs out of order, first near output pixel ({u}, {v})); check the coefficients"
        )
    valid = float(inside.mean())
    if valid < UNDISTORT_MIN_VALID_FRACTION:
        raise DataError(
            f"{source}: the {what} leaves {1 - valid:.0%} of the undistorted image without raw pixels "
            f"(at most {1 - UNDISTORT_MIN_VALID_FRACTION:.0%} allowed); check the coefficients"
        )
    bx = np.clip(np.concatenate([mx[0, :], mx[:, -1], mx[-1, ::-1], mx[::-1, 0]]), -0.5, w - 0.5)
    by = np.clip(np.concatenate([my[0, :], my[:, -1], my[-1, ::-1], my[::-1, 0]]), -0.5, h - 0.5)
    coverage = 0.5 * abs(float(np.dot(bx, np.roll(by, -1)) - np.dot(by, np.roll(bx, -1)))) / (w * h)
    if coverage < UNDISTORT_MIN_RAW_COVERAGE:
        raise DataError(
            f"{source}: the {what} maps the image outside itself: the undistorted image shows only "
            f"{coverage:.2%} of the raw image (at least {UNDISTORT_MIN_RAW_COVERAGE:.0%} expected); check the coefficients"
        )
