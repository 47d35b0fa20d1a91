"""Built-in measurement source: pyramidal Lucas-Kanade started from the current reprojection.

For an edge (i, k, j) of the patch graph the frontend predicts where patch k of frame i lands in
frame j (its reprojection ``uv_pred`` under the current poses and inverse depth). Lucas-Kanade,
initialised at ``uv_pred``, aligns the patch's footprint (``p * stride`` pixels square) in frame j
and returns ``uv_tgt``; ``uv_tgt - uv_pred`` is exactly DPVO's residual update Delta_ikj, and
``uv_tgt`` is the BA target. The confidence (DPVO's weight w_ikj) is the product of a photometric
term (mean absolute intensity error of the aligned window) and a forward-backward term (track
``uv_tgt`` back into frame i, starting from the source pixel, and measure how far it lands from
it); tracks failing the forward-backward threshold or leaving the image get confidence 0.

OpenCV's ``calcOpticalFlowPyrLK`` with ``OPTFLOW_USE_INITIAL_FLOW`` is the engine. Its Python
binding does not accept prebuilt pyramids, so the per-frame cache (:meth:`LKSource.prepare`) holds
the image resized to the LK resolution and OpenCV builds the pyramids inside each call; calls are
therefore grouped per ordered image pair (:meth:`LKSource.measure_batch`).
Pixel convention: OpenCV's (pixel centres at integer coordinates), as everywhere in fgslam.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..photometric import BrightnessModel
from .config import LKConfig
from .measurement import Measurement, MeasurementSource


@dataclass
class LKFeatures:
    """Per-frame cache: the grey image at the LK resolution (``LKConfig.scale`` of the input)."""

    image: np.ndarray
    width: int
    height: int


class LKSource(MeasurementSource):
    """Pyramidal Lucas-Kanade with forward-backward check (see module docstring).

    Tracking runs on images resized by ``config.scale`` (pixel coordinates are converted in and out,
    so callers always work in input pixels). :meth:`measure_batch` runs all requests of one frame
    with one OpenCV call per ordered image pair and stage, merging the forward tracks of one
    direction with the backward checks of the other (3 calls per pair of frames instead of 4).

    Args:
        config: LK tunables.
        window: side of the tracked window in input pixels (the patch footprint ``p * stride``).
    """

    name = "lk"

    def __init__(self, config: LKConfig, window: int):
        import cv2  # deferred: cv2

        self.config = config
        self._window_input = window
        self.scale = config.scale if config.scale > 0 else None  # automatic: set at the first image
        if self.scale is not None:
            self._set_scale(self.scale)
        self._cv2 = cv2
        self._brightness = BrightnessModel(config.photometric, config.photometric_floor)
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, config.iterations, config.epsilon)

    def _set_scale(self, scale: float) -> None:
        self.scale = float(scale)
        self.window = max(5, int(round(self._window_input * self.scale))) | 1

    def prepare(self, image: np.ndarray) -> LKFeatures:
        cv2 = self._cv2
        image = np.ascontiguousarray(image, dtype=np.uint8)
        h, w = image.shape
        if self.scale is None:
            self._set_scale(min(1.0, self.config.auto_width / w))
        if self.scale != 1.0:
            size = (max(1, round(w * self.scale)), max(1, round(h * self.scale)))
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        image = self._brightness(image)
        return LKFeatures(image=image, width=w, height=h)

    def pack(self, features: LKFeatures) -> tuple[bytes, int, int]:
        """The LK-resolution image as lossless PNG bytes (about half the raw size on real images)."""
        ok, buf = self._cv2.imencode(".png", features.image)
        if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
            raise RuntimeError("PNG encoding of a keyframe image failed")
        return buf.tobytes(), features.width, features.height

    def unpack(self, packed: tuple[bytes, int, int]) -> LKFeatures:
        data, width, height = packed
        image = self._cv2.imdecode(np.frombuffer(data, np.uint8), self._cv2.IMREAD_GRAYSCALE)
        return LKFeatures(image=image, width=width, height=height)

    def _to_lk(self, uv: np.ndarray) -> np.ndarray:
        """Input pixels -> LK-resolution pixels (pixel centres at integers in both; the way back is in
        ``lk_jit.finish_tracks``)."""
        a = self.scale
        return np.ascontiguousarray((np.asarray(uv, np.float64) + 0.5) * a - 0.5, dtype=np.float32)

    def _track(self, src: LKFeatures, tgt: LKFeatures, uv_src: np.ndarray, uv_init: np.ndarray):
        """One OpenCV call on LK-resolution points: (uv, ok, err)."""
        cv2 = self._cv2
        uv, status, err = cv2.calcOpticalFlowPyrLK(
            src.image, tgt.image, uv_src.reshape(-1, 1, 2), uv_init.reshape(-1, 1, 2).copy(),
            winSize=(self.window, self.window), maxLevel=self.config.levels,
            criteria=self._criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, minEigThreshold=self.config.min_eigen,
        )
        return uv.reshape(-1, 2), status.reshape(-1).astype(bool), err.reshape(-1)

    def measure(self, src: LKFeatures, tgt: LKFeatures, uv_src: np.ndarray, uv_pred: np.ndarray) -> Measurement:
        return self.measure_batch([(src, tgt, uv_src, uv_pred)])[0]

    def measure_batch(self, requests: list) -> list[Measurement]:
        """Measure ``[(src, tgt, uv_src, uv_pred), ...]``; one :class:`Measurement` per request."""
        # jobs per ordered image pair: (request, stage) with stage 0 = forward, 1 = backward check
        pending: dict[tuple[int, int], list] = {}
        feats: dict[int, LKFeatures] = {}
        fwd: dict[int, tuple] = {}
        out: list = [None] * len(requests)
        for r, (src, tgt, uv_src, uv_pred) in enumerate(requests):
            feats[id(src)], feats[id(tgt)] = src, tgt
            if len(uv_src) == 0:
                out[r] = Measurement(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
                continue
            pending.setdefault((id(src), id(tgt)), []).append(
                (r, 0, self._to_lk(uv_src), self._to_lk(uv_pred)))
        while pending:
            key = max(pending, key=lambda k: len(pending[k]))
            jobs = pending.pop(key)
            start = self._to_lk(np.zeros((0, 2)))
            pts = np.concatenate([j[2] for j in jobs]) if jobs else start
            init = np.concatenate([j[3] for j in jobs]) if jobs else start
            uv, ok, err = self._track(feats[key[0]], feats[key[1]], pts, init)
            offset = 0
            for r, stage, p, _ in jobs:
                sl = slice(offset, offset + len(p))
                offset += len(p)
                if stage == 0:
                    fwd[r] = (uv[sl].copy(), ok[sl].copy(), err[sl].copy(), p)
                    pending.setdefault((key[1], key[0]), []).append((r, 1, uv[sl].copy(), p))
                else:
                    out[r] = self._finish(requests[r], fwd[r], uv[sl], ok[sl])
        return out

    def _finish(self, request, forward, uv_back: np.ndarray, ok_back: np.ndarray) -> Measurement:
        from .lk_jit import finish_tracks  # deferred: numba (compiled kernel, core/jit.py)

        cfg = self.config
        _, tgt, uv_src, uv_pred = request
        uv_fwd, ok_fwd, err, p_src = forward
        uv_out, confidence, fb = finish_tracks(
            uv_fwd, ok_fwd, err, p_src, uv_back, ok_back, np.ascontiguousarray(uv_pred, dtype=np.float64),
            float(self.scale), 0.5 * self.window / self.scale, float(tgt.width), float(tgt.height),
            float(cfg.fb_threshold), float(cfg.error_sigma), float(cfg.fb_sigma), float(cfg.min_confidence))
        return Measurement(uv=uv_out, confidence=confidence, fb_error=fb)
