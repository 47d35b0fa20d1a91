"""A frontend's map for export: keyframes and tracked 3-D points (:class:`MapExport`).

Below the frontends, which build it (:meth:`fgslam.frontends.base.Frontend.map_export`), and the
exporters, which save and convert it (:mod:`fgslam.export.map`, :mod:`fgslam.export.colmap`). Poses
are rigid ``[R | t]`` camera-to-world; a track observation ``(point, kf_id, u, v)`` says that
keyframe ``kf_id`` sees point ``point`` at pixel ``(u, v)`` (pixel centres at integer coordinates).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import DataError


def rigid_poses(T_WC: np.ndarray) -> np.ndarray:
    """Rigid ``[R | t]`` of (N, 4, 4) Sim(3) matrices ``[[s R, t], [0, 1]]`` (the map's points stay
    where they are: a point seen at ``X_C`` by the Sim(3) pose is seen at ``s X_C`` by the rigid one,
    on the same pixel)."""
    from .lie import sim3_matrix_parts  # deferred: lie pulls torch (loading a map, a config need none)

    T = np.array(T_WC, dtype=np.float64, copy=True).reshape(-1, 4, 4)
    for k in range(T.shape[0]):
        T[k, :3, :3] = sim3_matrix_parts(T[k], project=True)[0]
        T[k, 3] = (0.0, 0.0, 0.0, 1.0)
    return T


def points_near_cameras(X: np.ndarray, centres: np.ndarray, range_factor: float) -> tuple[np.ndarray, float | None]:
    """Which points of a cloud are not far ones: ``(near (N,) bool, limit)``, a point near when its
    distance to the nearest camera centre is at most ``range_factor`` times the median such distance of
    the cloud's finite points (``limit``, in the cloud's units: a bound relative to the scene, right for
    a monocular map's arbitrary scale too). Far points are near-zero inverse depths and sky, up to
    thousands of times the scene's size away. A non-finite point is never near; without a finite point
    or a camera no point is, and ``limit`` is None. The one rule of ``fgslam compare-colmap``'s cloud
    metrics and the PLY export (``max_point_range_factor`` of each)."""
    from scipy.spatial import cKDTree  # deferred: scipy

    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(X), axis=1)
    near = np.zeros(X.shape[0], bool)
    if not finite.any() or centres.shape[0] == 0:
        return near, None
    dist = cKDTree(centres).query(X[finite])[0]
    limit = float(range_factor * np.median(dist))
    near[finite] = dist <= limit
    return near, limit


@dataclass
class MapExport:
    """A frontend's map for export (see the module docstring).

    Attributes:
        kf_ids: (K,) int64 keyframe ids (unique).
        kf_timestamps: (K,) float64 seconds.
        T_WC: (K, 4, 4) float64 rigid camera-to-world poses.
        X_W: (M, 3) float64 points in the world frame.
        colour: (M, 3) uint8 RGB.
        track_point: (T,) int64 point index of each observation.
        track_kf: (T,) int64 keyframe id of each observation.
        track_uv: (T, 2) float64 pixel of each observation.
    """

    kf_ids: np.ndarray
    kf_timestamps: np.ndarray
    T_WC: np.ndarray
    X_W: np.ndarray
    colour: np.ndarray
    track_point: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    track_kf: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    track_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def __post_init__(self) -> None:
        self.kf_ids = np.asarray(self.kf_ids, dtype=np.int64).reshape(-1)
        self.kf_timestamps = np.asarray(self.kf_timestamps, dtype=np.float64).reshape(-1)
        self.T_WC = np.asarray(self.T_WC, dtype=np.float64).reshape(-1, 4, 4)
        self.X_W = np.asarray(self.X_W, dtype=np.float64).reshape(-1, 3)
        self.colour = np.asarray(self.colour, dtype=np.uint8).reshape(-1, 3)
        self.track_point = np.asarray(self.track_point, dtype=np.int64).reshape(-1)
        self.track_kf = np.asarray(self.track_kf, dtype=np.int64).reshape(-1)
        self.track_uv = np.asarray(self.track_uv, dtype=np.float64).reshape(-1, 2)
        k, m, t = self.kf_ids.shape[0], self.X_W.shape[0], self.track_point.shape[0]
        if self.kf_timestamps.shape[0] != k or self.T_WC.shape[0] != k:
            raise DataError(f"map export: {k} keyframe ids, {self.kf_timestamps.shape[0]} timestamps, "
                            f"{self.T_WC.shape[0]} poses")
        if np.unique(self.kf_ids).shape[0] != k:
            raise DataError("map export: repeated keyframe ids")
        if self.colour.shape[0] != m:
            raise DataError(f"map export: {m} points but {self.colour.shape[0]} colours")
        if self.track_kf.shape[0] != t or self.track_uv.shape[0] != t:
            raise DataError(f"map export: tracks of unequal length ({t}, {self.track_kf.shape[0]}, "
                            f"{self.track_uv.shape[0]})")
        if t and (self.track_point.min() < 0 or self.track_point.max() >= m):
            raise DataError("map export: a track observation names a point that does not exist")
        if t and not np.all(np.isin(self.track_kf, self.kf_ids)):
            raise DataError("map export: a track observation names a keyframe that does not exist")

    @property
    def num_points(self) -> int:
        return int(self.X_W.shape[0])

    @property
    def num_keyframes(self) -> int:
        return int(self.kf_ids.shape[0])
