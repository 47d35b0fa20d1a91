"""The map a run saves for ``fgslam export`` (``map.npz`` in the run folder).

:class:`~fgslam.core.mapdata.MapExport` (defined below the frontends, in :mod:`fgslam.core.mapdata`) is what
:meth:`fgslam.frontends.base.Frontend.map_export` returns (any frontend): keyframes (id, timestamp,
camera-to-world pose) and 3-D points with colour and tracks (the keyframe pixels that observe each
point). :class:`RunMap` adds what only the runner knows: the
pinhole calibration of the images the frontend saw, and every input frame (timestamp, dataset index,
image path). Poses are rigid ``[R | t]`` camera-to-world in the map's world frame; for monocular
runs the translations and points are in the map's own (arbitrary) scale.

Conventions: a track observation ``(point, kf_id, u, v)`` says that keyframe ``kf_id`` sees point
``point`` at pixel ``(u, v)`` (pixel centres at integer coordinates, as fgslam's cameras: COLMAP's
are at +0.5, :mod:`fgslam.export.colmap` converts).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import DataError
from ..core.mapdata import MapExport
from .mapfile import DAMAGED_ARCHIVE_ERRORS, check_map_file, damaged_map_error

MAP_FILE = "map.npz"
MAP_FORMAT_VERSION = 1


@dataclass
class RunMap:
    """What ``map.npz`` holds: a frontend's :class:`MapExport`, the calibration of the images the
    frontend saw and the run's input frames.

    Attributes:
        map: the keyframes and points.
        intrinsics: (4,) ``fx, fy, cx, cy`` of the undistorted (resized, cropped) images.
        width, height: their size in pixels.
        frame_timestamps: (N,) seconds of every frame of the dataset selection.
        frame_indices: (N,) int64 dataset indices (``Frame.index``; position in the selection).
        frame_paths: N image paths (``""`` where none, e.g. video frames).
        sensor: ``mono``, ``stereo`` or ``rgbd`` (monocular maps have an arbitrary scale).
    """

    map: MapExport
    intrinsics: np.ndarray
    width: int
    height: int
    frame_timestamps: np.ndarray
    frame_indices: np.ndarray
    frame_paths: list[str]
    sensor: str = "mono"

    def keyframe_frame_indices(self) -> np.ndarray:
        """Dataset index of each keyframe (the input frame nearest to its timestamp)."""
        t = self.frame_timestamps
        if t.shape[0] == 0:
            return np.full(self.map.num_keyframes, -1, np.int64)
        pos = np.clip(np.searchsorted(t, self.map.kf_timestamps), 1, max(t.shape[0] - 1, 1))
        left = np.clip(pos - 1, 0, t.shape[0] - 1)
        pos = np.clip(pos, 0, t.shape[0] - 1)
        nearer = np.where(np.abs(t[left] - self.map.kf_timestamps) <= np.abs(t[pos] - self.map.kf_timestamps), left, pos)
        return self.frame_indices[nearer]


def save_run_map(path: str | Path, run_map: RunMap) -> Path:
    """Write ``run_map`` as a compressed ``.npz`` (to a temporary file renamed into place)."""
    path = Path(path)
    m = run_map.map
    tmp = path.with_name(path.name + ".tmp.npz")
    try:
        np.savez_compressed(
            tmp, version=np.int64(MAP_FORMAT_VERSION),
            kf_ids=m.kf_ids, kf_timestamps=m.kf_timestamps, T_WC=m.T_WC, X_W=m.X_W, colour=m.colour,
            track_point=m.track_point, track_kf=m.track_kf, track_uv=m.track_uv,
            intrinsics=np.asarray(run_map.intrinsics, dtype=np.float64), size=np.array([run_map.width, run_map.height]),
            frame_timestamps=np.asarray(run_map.frame_timestamps, dtype=np.float64),
            frame_indices=np.asarray(run_map.frame_indices, dtype=np.int64),
            frame_paths=np.array(run_map.frame_paths, dtype=str), sensor=np.array(run_map.sensor),
        )
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


_KEYS = ("version", "kf_ids", "kf_timestamps", "T_WC", "X_W", "colour", "track_point", "track_kf", "track_uv",
         "intrinsics", "size", "frame_timestamps", "frame_indices", "frame_paths", "sensor")


def load_run_map(path: str | Path) -> RunMap:
    """Read a ``map.npz`` written by :func:`save_run_map`.

    Raises:
        DataError: missing, not an npz archive, truncated or damaged (the checks and messages of a stored
            map, :func:`fgslam.export.mapfile.check_map_file`), of another format version, or lacking an
            array (named).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no saved map (runs save {MAP_FILE} since fgslam exports maps; "
                        "rerun the sequence with this version)")
    check_map_file(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _KEYS if k not in z.files]
            if missing:
                raise DataError(f"{path}: not a fgslam map (missing {', '.join(missing)})")
            d = {k: z[k] for k in _KEYS}
    except DAMAGED_ARCHIVE_ERRORS as exc:
        raise damaged_map_error(path, exc) from exc
    if int(d["version"]) != MAP_FORMAT_VERSION:
        raise DataError(f"{path}: map format version {int(d['version'])}, this fgslam reads {MAP_FORMAT_VERSION}")
    m = MapExport(d["kf_ids"], d["kf_timestamps"], d["T_WC"], d["X_W"], d["colour"],
                  d["track_point"], d["track_kf"], d["track_uv"])
    return RunMap(m, d["intrinsics"], int(d["size"][0]), int(d["size"][1]), d["frame_timestamps"],
                  d["frame_indices"], [str(p) for p in d["frame_paths"]], str(d["sensor"]))
