"""Dense correspondence fields shared by the dense and pointmap families: the source interface
(:class:`DenseSource`, :class:`FlowRevision`), the built-in OpenCV DIS flow (:class:`DenseFlowSource`)
and the grid convention (:func:`grid_intrinsics`).

The dense frontend measures its frame graph with it (:mod:`fgslam.frontends.dense.source` adds the
learned DROID slot and the factory); the pointmap family's built-in pointmap source runs it at full
resolution (stride 1). The module docstring of :mod:`fgslam.frontends.dense.source` describes the
sources, the confidences and the grid convention.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..core.arrays import finite_rows, norm2_rows
from ..core.config import MAX_IMAGE_SIDE, MAX_SCALAR, ranged
from ..core.errors import DataError
from .photometric import BrightnessModel, PhotometricModel

#: ``preset`` -> the name of its OpenCV constant (cv2 is imported where the flow runs)
_DIS_PRESETS = {"ultrafast": "DISOPTICAL_FLOW_PRESET_ULTRAFAST", "fast": "DISOPTICAL_FLOW_PRESET_FAST",
                "medium": "DISOPTICAL_FLOW_PRESET_MEDIUM"}


@dataclass
class DenseFlowConfig:
    """Built-in dense flow source (OpenCV DIS) and its confidences."""

    preset: Literal["ultrafast", "fast", "medium"] = "medium"  # DIS preset (speed vs accuracy)
    image_scale: float = ranged(0.5, gt=0, le=1)  # DIS runs on the images resized by this factor
    warm_start: bool = True  # start DIS from the flow the current poses and depths induce
    fb_sigma: float = ranged(1.0, gt=0, le=MAX_SCALAR)  # image px: forward-backward confidence exp(-0.5 (e_fb / sigma)^2)
    fb_max: float = ranged(4.0, gt=0, le=MAX_SCALAR)  # image px: a block whose mean forward-backward error exceeds this gets 0
    photo_sigma: float = ranged(12.0, gt=0, le=MAX_SCALAR)  # grey levels: photometric confidence exp(-0.5 (e / sigma)^2), e = block mean |I_j(p + f) - I_i(p)|
    aperture_gradient: float = ranged(3.0, ge=0, le=MAX_SCALAR)  # grey levels per px: per-axis confidence G / (G + a^2), G = block mean squared gradient along the axis; 0: off
    border: float = ranged(0.0, ge=0, le=MAX_IMAGE_SIDE)  # grid px: targets closer than this to the image border (or outside) get 0
    photometric: PhotometricModel = "raw"  # raw (brightness constancy) | gain (undo a gain per image, auto-exposure: fgslam/frontends/photometric.py)
    photometric_floor: float = ranged(4.0, gt=0, le=255)  # gain: added to each image's median (grey levels), so a nearly black image is not amplified


@dataclass
class FlowRevision:
    """What a source measured on one edge ``(i, j)``: ``target`` ``(h, w, 2)`` the correspondence
    field p*_ij in grid pixels of ``j``; ``weight`` ``(h, w, 2)`` per-axis confidence in [0, 1]
    (0: no measurement); ``damping`` ``(h, w)`` DROID's per-pixel eta for the source keyframe, or None
    (the block's configured constant); ``fb_error`` ``(h, w)`` forward-backward error in image pixels
    (NaN where the source has none)."""

    target: np.ndarray
    weight: np.ndarray
    damping: np.ndarray | None = None
    fb_error: np.ndarray | None = None


def grid_to_image(uv_grid: np.ndarray, stride: int) -> np.ndarray:
    """Image pixel coordinates of grid pixel coordinates: ``u = s (x + 1/2) - 1/2``."""
    return stride * (np.asarray(uv_grid, np.float64) + 0.5) - 0.5


def image_to_grid(uv: np.ndarray, stride: int) -> np.ndarray:
    """Grid pixel coordinates of image pixel coordinates (inverse of :func:`grid_to_image`)."""
    return (np.asarray(uv, np.float64) + 0.5) / stride - 0.5


def grid_intrinsics(K, stride: int) -> tuple[float, float, float, float]:
    """Intrinsics ``(fx, fy, cx, cy)`` of the grid of an image with intrinsics ``K`` (same convention
    as :meth:`fgslam.core.camera.PinholeCamera.resized`)."""
    fx, fy, cx, cy = (float(k) for k in K)
    return fx / stride, fy / stride, (cx + 0.5) / stride - 0.5, (cy + 0.5) / stride - 0.5


def _grid(h: int, w: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack((x, y), -1)


class DenseSource(abc.ABC):
    """Where the frame graph's correspondence fields come from (module docstring)."""

    name: str = ""
    stride: int = 8
    colour: bool = False  # True: add_frame gets the colour image (RGB, Frame.colour_or_grey) instead of the grey one

    @abc.abstractmethod
    def add_frame(self, frame_id: int, image: np.ndarray) -> None:
        """Cache per-frame work for a uint8 image ``(H, W)`` (``H``, ``W`` multiples of the stride): grey,
        or for a source with ``colour`` the RGB image ``(H, W, 3)`` when the frame has one."""

    @abc.abstractmethod
    def remove_frame(self, frame_id: int) -> None:
        """Drop what :meth:`add_frame` cached (the frame left the graph)."""

    @abc.abstractmethod
    def revise(self, edges: Sequence[tuple[int, int]], uv_induced: np.ndarray) -> list[FlowRevision]:
        """Measure edges ``[(i, j), ...]`` (frames added before) starting from ``uv_induced``
        ``(E, h, w, 2)``: each grid pixel of ``i`` reprojected into ``j`` with the current poses and
        depths, in grid pixels (NaN where the reprojection is invalid). One revision per edge."""

    def grid_shape(self, image_shape: tuple[int, int]) -> tuple[int, int]:
        """``(h, w)`` of the grid of an image of shape ``(H, W)``."""
        H, W = image_shape[:2]
        return H // self.stride, W // self.stride


class DenseFlowSource(DenseSource):
    """Built-in dense measurements: warm-started DIS flow with consistency confidences (module docstring)."""

    name = "flow"

    def __init__(self, config: DenseFlowConfig | None = None, stride: int = 8):
        import cv2  # deferred: OpenCV (DenseFlowConfig loads without it)

        self.config = config or DenseFlowConfig()
        self.stride = int(stride)
        self._frames: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # grey, gx^2, gy^2 (working scale)
        self._shape: tuple[int, int] | None = None
        self._dis = cv2.DISOpticalFlow_create(getattr(cv2, _DIS_PRESETS[self.config.preset]))
        self._brightness = BrightnessModel(self.config.photometric, self.config.photometric_floor)
        self._grid_cache: dict = {}

    # ------------------------------------------------------------------ frames
    def add_frame(self, frame_id: int, image: np.ndarray) -> None:
        import cv2  # deferred: OpenCV (DenseFlowConfig loads without it)

        image = np.asarray(image)
        if image.ndim != 2 or image.dtype != np.uint8:
            raise DataError(f"dense flow source: frame {frame_id} must be a grey uint8 image, got "
                            f"{image.dtype} {image.shape}")
        H, W = image.shape
        s = self.stride
        if H % s or W % s or H < s or W < s:
            raise DataError(f"dense flow source: image size {W}x{H} is not a multiple of the stride {s} "
                            "(dataset.crop_multiple)")
        if self._shape is not None and self._shape != (H, W):
            raise DataError(f"dense flow source: frame {frame_id} is {W}x{H}, earlier frames "
                            f"{self._shape[1]}x{self._shape[0]}")
        self._shape = (H, W)
        a = self.config.image_scale
        Hw, Ww = self._working_shape()
        grey = image if (Hw, Ww) == (H, W) else cv2.resize(image, (Ww, Hw), interpolation=cv2.INTER_AREA)
        grey = self._brightness(grey)
        # gradient energy per axis, in grey levels per image pixel (the working image is a times smaller)
        f = grey.astype(np.float32)
        gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3, scale=a / 8.0)
        gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3, scale=a / 8.0)
        self._frames[int(frame_id)] = (np.ascontiguousarray(grey), gx * gx, gy * gy)

    def remove_frame(self, frame_id: int) -> None:
        self._frames.pop(int(frame_id), None)

    def _working_shape(self) -> tuple[int, int]:
        """Working image size: the grid times ``stride * image_scale`` (an integer pooling factor where possible)."""
        H, W = self._shape
        a = self.config.image_scale
        return max(1, int(round(H * a))), max(1, int(round(W * a)))

    def _grids(self, h: int, w: int, Hw: int, Ww: int) -> tuple[np.ndarray, np.ndarray]:
        """The grid's pixel coordinates ``(h, w, 2)`` and the working image's ``(y, x)`` maps (float32), made
        once per size (read-only: every edge of a run shares them)."""
        key = (h, w, Hw, Ww)
        if self._grid_cache.get("key") != key:
            grid = _grid(h, w)
            yx = np.mgrid[0:Hw, 0:Ww].astype(np.float32)
            grid.flags.writeable = yx.flags.writeable = False
            self._grid_cache = {"key": key, "grids": (grid, yx)}
        return self._grid_cache["grids"]

    def _frame(self, frame_id: int):
        try:
            return self._frames[int(frame_id)]
        except KeyError:
            raise DataError(f"dense flow source: frame {frame_id} was not added (add_frame) or was removed") from None

    # ------------------------------------------------------------------ measurement
    def revise(self, edges: Sequence[tuple[int, int]], uv_induced: np.ndarray) -> list[FlowRevision]:
        uv_induced = np.asarray(uv_induced, np.float64)
        if self._shape is None:
            raise DataError("dense flow source: no frame added")
        h, w = self.grid_shape(self._shape)
        if uv_induced.shape != (len(edges), h, w, 2):
            raise DataError(f"dense flow source: uv_induced has shape {uv_induced.shape}, expected "
                            f"{(len(edges), h, w, 2)} for {len(edges)} edges on the {w}x{h} grid")
        return [self._revise_edge(i, j, uv_induced[n]) for n, (i, j) in enumerate(edges)]

    def _revise_edge(self, i: int, j: int, uv_induced: np.ndarray) -> FlowRevision:
        import cv2  # deferred: OpenCV (DenseFlowConfig loads without it)

        cfg, s = self.config, self.stride
        Ii, gxx, gyy = self._frame(i)
        Ij = self._frame(j)[0]
        Hw, Ww = Ii.shape
        h, w = uv_induced.shape[:2]
        grid, (yy, xx) = self._grids(h, w, Hw, Ww)
        # working-scale pixel u_w = k (u + 1/2) - 1/2 with k = Ww / W: flows scale by k * stride per grid px
        k = Ww / self._shape[1]
        init = np.zeros((Hw, Ww, 2), np.float32)
        if cfg.warm_start:
            flow8 = uv_induced - grid
            ok = finite_rows(flow8)
            if ok.any():
                flow8 = np.where(ok[..., None], flow8, np.median(flow8[ok], axis=0))
                init = cv2.resize((flow8 * (s * k)).astype(np.float32), (Ww, Hw), interpolation=cv2.INTER_LINEAR)
        # warm start: the target image warped by the induced flow, so DIS measures only the residual
        # flow (DROID's correlation lookup around the current reprojection)
        Wj = cv2.remap(Ij, xx + init[..., 0], yy + init[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        # OpenCV's DIS keeps the initial flow of the last call given one (the backward check below), and a
        # call given none starts from it: this forward flow starts from the negated residual of the edge
        # measured before, not from zero (measured, docs/benchmarks/stability.md). Deterministic for the
        # same calls in the same order; the presets were chosen with it, and removing it changes every
        # dense and pointmap figure (none of the variants measured is better on every case).
        res_f = self._dis.calc(Ii, Wj, None)
        res_b = self._dis.calc(Wj, Ii, np.ascontiguousarray(-res_f))
        map_x, map_y = xx + res_f[..., 0], yy + res_f[..., 1]
        fwd = res_f + cv2.remap(init, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        # per working pixel: forward-backward error and photometric error of the warped target
        back = cv2.remap(res_b, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        fb = norm2_rows(res_f + back) / k  # image pixels
        warped = cv2.remap(Wj, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        photo = np.abs(warped.astype(np.float32) - Ii.astype(np.float32))

        def pool(x: np.ndarray) -> np.ndarray:  # block means on the grid (at the grid's own size: x itself)
            return x if x.shape[:2] == (h, w) else cv2.resize(x, (w, h), interpolation=cv2.INTER_AREA)

        flow_grid = pool(fwd).astype(np.float64) / (s * k)
        target = grid + flow_grid
        fb_grid = pool(fb.astype(np.float32)).astype(np.float64)
        photo_grid = pool(photo).astype(np.float64)
        conf = np.exp(-0.5 * (fb_grid / cfg.fb_sigma) ** 2) * np.exp(-0.5 * (photo_grid / cfg.photo_sigma) ** 2)
        conf = np.where(fb_grid <= cfg.fb_max, conf, 0.0)
        inside = ((target[..., 0] >= cfg.border - 0.5) & (target[..., 0] <= w - 0.5 - cfg.border)
                  & (target[..., 1] >= cfg.border - 0.5) & (target[..., 1] <= h - 0.5 - cfg.border))
        conf = np.where(inside, conf, 0.0)
        if cfg.aperture_gradient > 0:  # per axis: conf G / (G + a^2)
            a2 = cfg.aperture_gradient ** 2
            axes = []
            for energy in (gxx, gyy):
                G = pool(energy).astype(np.float64)
                axes.append(conf * G / (G + a2))
            weight = np.stack(axes, -1)
        else:
            weight = np.repeat(conf[..., None], 2, axis=-1)
        return FlowRevision(target=target, weight=weight, damping=None, fb_error=fb_grid)
