"""The dense frontend's measurement weights and grid pooling: the Huber weight of a flow revision, the
information of a confident flow row, the dense block's settings, block means over the grid stride and
the texture test of a frame."""

from __future__ import annotations

import cv2
import numpy as np

from ...factors.dense import DenseBlockConfig
from ...factors.reprojection import ReprojectionConfig
from ...factors.visual_block import BlockConfig
from .config import DenseConfig


def pool(a: np.ndarray, s: int) -> np.ndarray:
    """Block means of an (H, W[, C]) array over s x s blocks."""
    H, W = a.shape[:2]
    return a.reshape(H // s, s, W // s, s, *a.shape[2:]).mean(axis=(1, 3))


def textured_share(image: np.ndarray, stride: int, texture_gradient: float) -> float:
    """Share of grid blocks of ``image`` (the grid's crop) whose RMS image gradient exceeds ``texture_gradient``."""
    img = image.astype(np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)
    energy = pool(gx * gx + gy * gy, stride)
    return float((energy > texture_gradient ** 2).mean())


def huber_weight(revision: np.ndarray, config: DenseConfig, stride: int) -> np.ndarray:
    """Huber weight (h, w, 1) of a revision (grid px) measured in image px (1 below ``ba.huber``)."""
    k = config.ba.huber
    if k <= 0:
        return np.ones(revision.shape[:-1] + (1,))
    r = np.linalg.norm(np.nan_to_num(revision, nan=0.0), axis=-1, keepdims=True) * stride
    return np.where(r <= k, 1.0, k / np.maximum(r, 1e-12))


def information(config: DenseConfig, stride: int) -> float:
    """Weight of a fully confident flow row: 1 / sigma^2 with sigma in grid px."""
    return (stride / config.ba.pixel_sigma) ** 2


def block_config(config: DenseConfig, reprojection: ReprojectionConfig) -> DenseBlockConfig:
    """The dense block's settings from the ``ba`` section."""
    return DenseBlockConfig(block=BlockConfig(structure_damping=config.ba.damping, threads=config.threads),
                            reprojection=reprojection, depth_prior=config.ba.depth_prior)
