"""How much of a frame's view a map saw, by ground truth: the upper bound of a localisation's coverage.

A frame that looks at what no keyframe of the map saw cannot be localised in it, whatever the localiser
does. :func:`view_overlap` measures, for a frame with a ground-truth pose and a depth image, the share of
its view some map keyframe (ground-truth pose, depth image) also saw:

- the frame's depth pixels on a ``grid`` (columns, rows) of pixel centres, back-projected to 3-D points
  (pixels without depth are left out);
- each point projected into each keyframe: it counts as seen there when it falls inside that image, in
  front of the camera, and its depth agrees with the keyframe's depth at the nearest pixel (pixel centres
  at integer coordinates) within ``depth_tolerance`` of the latter (a point behind a nearer surface, or
  in a hole, is not seen);
- the frame's overlap is the largest share over the keyframes (the one keyframe that saw most of it; a
  localiser that uses several keyframes at once may pose a frame no single keyframe sees much of).

Pure numpy; the caller reads the images and poses (``tools/bench_maps.py``: frames of the localised
sequence against the keyframes of the map, all from the dataset's ground truth).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the pixel grid (columns, rows) a frame's view is sampled on
DEFAULT_GRID = (32, 24)
#: a point is seen by a keyframe when its depth there is within this share of the keyframe's depth
DEFAULT_DEPTH_TOLERANCE = 0.1


@dataclass(frozen=True)
class ViewSamples:
    """A frame's view on the grid: 3-D points ``X_C`` ``(N, 3)`` in its camera frame (N: the grid pixels
    with depth) and its pose ``T_WC``."""

    X_C: np.ndarray
    T_WC: np.ndarray


def grid_pixels(width: int, height: int, grid: tuple[int, int] = DEFAULT_GRID) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixel columns and rows ``(G,)`` each of a ``grid`` of cell centres over a ``width x height`` image."""
    cols, rows = grid
    u = ((np.arange(cols) + 0.5) * width / cols).astype(np.int64)
    v = ((np.arange(rows) + 0.5) * height / rows).astype(np.int64)
    uu, vv = np.meshgrid(u, v)
    return uu.ravel(), vv.ravel()


def view_samples(depth: np.ndarray, K: np.ndarray, T_WC: np.ndarray,
                 grid: tuple[int, int] = DEFAULT_GRID) -> ViewSamples:
    """The frame's view (:class:`ViewSamples`) from its depth image ``(H, W)`` (metres; 0 or non-finite:
    none), intrinsics ``K`` ``[fx, fy, cx, cy]`` and ground-truth pose ``T_WC`` ``(4, 4)``."""
    h, w = depth.shape
    u, v = grid_pixels(w, h, grid)
    z = depth[v, u].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    fx, fy, cx, cy = (float(k) for k in K)
    z = z[ok]
    X_C = np.stack([(u[ok] - cx) / fx * z, (v[ok] - cy) / fy * z, z], axis=1)
    return ViewSamples(X_C, np.asarray(T_WC, dtype=np.float64))


def seen_share(view: ViewSamples, depth_k: np.ndarray, K: np.ndarray, T_WCk: np.ndarray,
               depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE) -> float:
    """Share of ``view``'s points the keyframe (depth image ``depth_k``, pose ``T_WCk``, intrinsics ``K``)
    sees (module docstring); 0.0 for a view without points."""
    n = len(view.X_C)
    if n == 0:
        return 0.0
    T_CkC = np.linalg.inv(np.asarray(T_WCk, dtype=np.float64)) @ view.T_WC
    X_Ck = view.X_C @ T_CkC[:3, :3].T + T_CkC[:3, 3]
    fx, fy, cx, cy = (float(k) for k in K)
    h, w = depth_k.shape
    z = X_Ck[:, 2]
    front = z > 0
    with np.errstate(divide="ignore", invalid="ignore"):  # nearest pixel: centres at integer coordinates
        u = np.floor(np.where(front, fx * X_Ck[:, 0] / z + cx, -1.0) + 0.5)
        v = np.floor(np.where(front, fy * X_Ck[:, 1] / z + cy, -1.0) + 0.5)
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    d = np.zeros(n)
    d[inside] = depth_k[v[inside].astype(np.int64), u[inside].astype(np.int64)]
    seen = inside & np.isfinite(d) & (d > 0) & (np.abs(z - d) <= depth_tolerance * d)
    return float(seen.sum()) / n


def view_overlap(view: ViewSamples, depths_k, K: np.ndarray, T_WCk: np.ndarray,
                 depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE) -> float:
    """The largest :func:`seen_share` of ``view`` over keyframes with depth images ``depths_k`` (a sequence
    of ``(H, W)``, one per pose) and poses ``T_WCk`` ``(M, 4, 4)``; 0.0 without keyframes."""
    best = 0.0
    for depth_k, T_WCk_i in zip(depths_k, T_WCk, strict=True):
        best = max(best, seen_share(view, depth_k, K, T_WCk_i, depth_tolerance))
    return best
