"""PLY point clouds (binary little-endian, x y z as float32 and red green blue as uchar), and what
``fgslam export RUN --ply FILE`` keeps of a map (:class:`PlyExportConfig`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.config import MAX_SCALAR, ranged
from ..core.mapdata import points_near_cameras


@dataclass
class PlyExportConfig:
    """What a PLY export keeps of a run's map (``fgslam export RUN --ply FILE``)."""

    max_point_range_factor: float = ranged(10.0, ge=0, le=MAX_SCALAR)  # leave out points farther from every camera (the map's keyframes; for a run's points.ply, its posed frames) than this x the median such distance (far points: near-zero inverse depths; compare-colmap's rule, scale-free); 0: keep every point


def kept_points(X_W: np.ndarray, centres: np.ndarray, config: PlyExportConfig) -> tuple[np.ndarray, float | None]:
    """Which points a PLY keeps: ``(keep (N,) bool, limit)``, the finite points nearer to the camera
    ``centres`` than ``config.max_point_range_factor`` times their median such distance
    (:func:`fgslam.core.mapdata.points_near_cameras`; ``limit`` None: no range limit, every finite point)."""
    if config.max_point_range_factor > 0 and len(centres):
        return points_near_cameras(X_W, centres, config.max_point_range_factor)
    return np.all(np.isfinite(np.asarray(X_W).reshape(-1, 3)), axis=1), None


def write_ply(path: str | Path, X_W: np.ndarray, colour: np.ndarray) -> Path:
    """Write the finite points ``X_W (N, 3)`` with ``colour (N, 3) uint8`` to ``path``."""
    X_W = np.asarray(X_W, dtype=np.float32).reshape(-1, 3)
    colour = np.asarray(colour, dtype=np.uint8).reshape(-1, 3)
    keep = np.all(np.isfinite(X_W), axis=1)
    X_W, colour = X_W[keep], colour[keep]
    vertex = np.empty(X_W.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                            ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, name in enumerate("xyz"):
        vertex[name] = X_W[:, i]
    for i, name in enumerate(("red", "green", "blue")):
        vertex[name] = colour[:, i]
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {vertex.shape[0]}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    path = Path(path)
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vertex.tobytes())
    return path


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a PLY written by :func:`write_ply`: ``(X_W (N, 3) float32, colour (N, 3) uint8)``."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    n = int(next(line for line in data[:end].decode("ascii").splitlines() if line.startswith("element vertex")).split()[-1])
    vertex = np.frombuffer(data[end:], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                               ("red", "u1"), ("green", "u1"), ("blue", "u1")], count=n)
    return (np.stack([vertex[c] for c in "xyz"], 1), np.stack([vertex[c] for c in ("red", "green", "blue")], 1))
