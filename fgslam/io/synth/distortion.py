"""Raw images with lens distortion: render a pinhole canvas, resample it through the distortion.

Model: OpenCV radial-tangential ``(k1, k2, p1, p2)`` (EuRoC's ``radial-tangential``), on normalised
coordinates ``(x, y)`` of the undistorted ray ``[x, y, 1]``::

    r2 = x^2 + y^2,  g = 1 + k1 r2 + k2 r2^2
    x_d = x g + 2 p1 x y + p2 (r2 + 2 x^2),   y_d = y g + p1 (r2 + 2 y^2) + 2 p2 x y
    raw pixel (u, v) = (fx x_d + cx, fy y_d + cy)

For every raw pixel the undistorted ray is found by Newton's method (exact to float64 rounding, not
OpenCV's approximate ``undistortPoints``); the pinhole canvas (same focal lengths) is sized to hold
all of them, rendered by :class:`~.render.Renderer`, and resampled at the rays of the raw pixels:
bilinear for the image, nearest for the z-depth and the quad ids (z-depth is along the optical axis,
so the raw pixel's ray has the depth of the canvas pixel it samples). The loaders undistort raw
images with the same coefficients (:class:`fgslam.io.undistort.Undistorter`).

Model ``equidistant`` (Kannala-Brandt, TUM-VI's fisheye, OpenCV ``cv2.fisheye``) with ``(k1, k2, k3, k4)``
on the angle ``theta = atan(r)`` of the undistorted ray, ``r = |(x, y)|``::

    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),  (x_d, y_d) = theta_d / r (x, y)

inverted per raw pixel by Newton's method on ``theta`` (the rays must stay within 90 degrees of the axis:
the pinhole canvas holds them).
"""

from __future__ import annotations

import numpy as np

from ...core.errors import ConfigError
from .render import RenderOutput

_NEWTON_ITERATIONS = 50  # undistortion iterations (converges in < 10 for sane lenses)
_NEWTON_TOLERANCE = 1e-12  # normalised units: largest residual accepted after the iterations
_CANVAS_MARGIN_PX = 2  # canvas pixels beyond the outermost undistorted ray (bilinear neighbours)
_MAX_RAY_ANGLE_RAD = 1.4  # equidistant: rays beyond this angle from the axis need an unbounded pinhole canvas


def distort_normalized(x: np.ndarray, y: np.ndarray, coeffs) -> tuple[np.ndarray, np.ndarray]:
    """Distorted normalised coordinates of undistorted ``(x, y)`` (module docstring)."""
    k1, k2, p1, p2 = (float(c) for c in coeffs)
    r2 = x * x + y * y
    g = 1.0 + k1 * r2 + k2 * r2 * r2
    return x * g + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * g + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def undistort_normalized(xd: np.ndarray, yd: np.ndarray, coeffs) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted ``(x, y)`` of distorted normalised coordinates, by Newton's method; ConfigError when
    it does not converge (a distortion that is not invertible over the given points)."""
    k1, k2, p1, p2 = (float(c) for c in coeffs)
    x, y = np.array(xd, np.float64), np.array(yd, np.float64)
    for _ in range(_NEWTON_ITERATIONS):
        fx_, fy_ = distort_normalized(x, y, coeffs)
        ex, ey = fx_ - xd, fy_ - yd
        r2 = x * x + y * y
        g = 1.0 + k1 * r2 + k2 * r2 * r2
        dg = 2 * k1 + 4 * k2 * r2  # d g / d (x or y) = dg * (x or y)
        j11 = g + x * dg * x + 2 * p1 * y + 6 * p2 * x
        j12 = x * dg * y + 2 * p1 * x + 2 * p2 * y
        j21 = y * dg * x + 2 * p1 * x + 2 * p2 * y
        j22 = g + y * dg * y + 6 * p1 * y + 2 * p2 * x
        det = j11 * j22 - j12 * j21
        x = x - (j22 * ex - j12 * ey) / det
        y = y - (-j21 * ex + j11 * ey) / det
    fx_, fy_ = distort_normalized(x, y, coeffs)
    err = np.hypot(fx_ - xd, fy_ - yd)
    if not np.all(np.isfinite(err)) or float(err.max()) > _NEWTON_TOLERANCE:
        raise ConfigError(f"camera.distortion {list(coeffs)}: not invertible over the image "
                          f"(largest undistortion residual {float(np.nanmax(err)):.3g})")
    return x, y


def distort_equidistant(x: np.ndarray, y: np.ndarray, coeffs) -> tuple[np.ndarray, np.ndarray]:
    """Equidistant (Kannala-Brandt) distorted normalised coordinates of undistorted ``(x, y)``."""
    k1, k2, k3, k4 = (float(c) for c in coeffs)
    r = np.hypot(x, y)
    theta = np.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    ratio = np.where(r > 0, theta_d / np.where(r > 0, r, 1.0), 1.0)
    return x * ratio, y * ratio


def undistort_equidistant(xd: np.ndarray, yd: np.ndarray, coeffs) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted ``(x, y)`` of equidistant-distorted normalised coordinates (Newton on the ray angle);
    ConfigError when it does not converge or a ray leaves the pinhole canvas (beyond ~80 degrees)."""
    k1, k2, k3, k4 = (float(c) for c in coeffs)
    theta_d = np.hypot(xd, yd)
    theta = theta_d.copy()
    for _ in range(_NEWTON_ITERATIONS):
        t2 = theta * theta
        f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        theta = theta - f / df
    t2 = theta * theta
    err = np.abs(theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d)
    if not np.all(np.isfinite(err)) or float(err.max()) > _NEWTON_TOLERANCE or float(theta.max()) > _MAX_RAY_ANGLE_RAD:
        raise ConfigError(f"camera.distortion {list(coeffs)} (equidistant): not invertible over the image or rays "
                          f"beyond {_MAX_RAY_ANGLE_RAD} rad of the axis (largest {float(np.nanmax(theta)):.3g} rad): "
                          "lower camera.hfov_deg")
    scale = np.where(theta_d > 0, np.tan(theta) / np.where(theta_d > 0, theta_d, 1.0), 1.0)
    return xd * scale, yd * scale


class DistortedCamera:
    """Pinhole canvas and resampling tables of a raw ``width x height`` camera ``K`` with distortion
    ``coeffs`` of ``model`` (``radtan`` or ``equidistant``): ``canvas_K``, ``canvas_size`` (w, h) and
    :meth:`resample` of a canvas render."""

    def __init__(self, K, width: int, height: int, coeffs, model: str = "radtan"):
        fx, fy, cx, cy = (float(k) for k in K)
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        undistort = undistort_equidistant if model == "equidistant" else undistort_normalized
        x, y = undistort((u - cx) / fx, (v - cy) / fy, coeffs)
        x0, x1, y0, y1 = x.min(), x.max(), y.min(), y.max()
        ccx = np.ceil(-x0 * fx) + _CANVAS_MARGIN_PX
        ccy = np.ceil(-y0 * fy) + _CANVAS_MARGIN_PX
        self.canvas_size = (int(ccx + np.ceil(x1 * fx)) + _CANVAS_MARGIN_PX + 1,
                            int(ccy + np.ceil(y1 * fy)) + _CANVAS_MARGIN_PX + 1)
        self.canvas_K = (fx, fy, float(ccx), float(ccy))
        self.map_x = (fx * x + ccx).astype(np.float32)
        self.map_y = (fy * y + ccy).astype(np.float32)

    def resample(self, out: RenderOutput) -> RenderOutput:
        """The raw (distorted) view of a canvas render."""
        import cv2  # not at import time: the CLI's parser must not import OpenCV (tests/test_cli.py)

        image = cv2.remap(out.image, self.map_x, self.map_y, cv2.INTER_LINEAR)
        depth = cv2.remap(out.depth, self.map_x, self.map_y, cv2.INTER_NEAREST)
        quad = cv2.remap(out.quad_id.astype(np.float32), self.map_x, self.map_y, cv2.INTER_NEAREST)
        return RenderOutput(image=image, depth=depth, quad_id=np.rint(quad).astype(np.int32))
