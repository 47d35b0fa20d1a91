"""Maps that persist: the stored map of ``fgslam run ... --save-map MAP`` and its loader (read by
``fgslam localize``, :mod:`fgslam.localize`).

Format (``MAP_FORMAT``, version :data:`MAP_FORMAT_VERSION`): a zip archive of ``.npy`` arrays that
``numpy.load(path, allow_pickle=False)`` reads (no pickled object anywhere), written with fixed
entry dates, no compression and in a fixed order, so the same map always gives the same bytes
(save -> load -> save is byte-identical), to a temporary file renamed into place (atomic).

``meta`` (uint8 array of UTF-8 JSON, sorted keys): ``format``, ``version``, ``family``, ``sensor``
(``mono`` maps have the map's own scale), ``metric``, ``camera`` (``K`` = fx, fy, cx, cy, ``width``,
``height``: the run's output images, which a sequence localised in the map must match),
``features`` (the settings the keyframe features were made with: ``image_scale``, the ORB settings,
the vocabulary, and ``K``/``width``/``height`` of the scaled feature image), ``config`` (the run's
resolved configuration less its machine-dependent fields, :func:`portable_config`), ``dataset``
(format, number of frames and the run's raw ``start``, ``end``, ``stride``: no name or path) and ``groundtruth_alignment`` (the map run's own
alignment to its ground truth, 4x4 ``[[s R, t], [0, 1]]`` with its method, or null). Nothing in a
map depends on where it is saved or where its data lies: the same run saved to two paths, or from
a copy of its data in another folder, gives the same bytes.

Per keyframe ``k`` (K keyframes, in id order): ``kf_ids`` (K,) int64, ``kf_timestamps`` (K,)
float64 s, ``kf_frame_index`` (K,) int64 dataset index of the keyframe's image, ``T_WC`` (K, 4, 4)
float64 Sim(3) camera-to-world poses in the map's world frame (``X_W = s R X_C + t``; the families'
exports are rigid, ``s = 1``, the world frame carries the scale). Keyframe features, concatenated
over keyframes with offsets ``feat_ptr`` (K+1,) int64: ``feat_uv`` (N, 2) float32 pixels of the
feature image, ``feat_desc`` (N, 32) uint8 ORB descriptors, ``feat_X_C`` (N, 3) float32 the feature's
3-D point in its keyframe's camera frame (map units; NaN: none; RGB-D: from the sensor depth,
monocular and stereo: triangulated with neighbouring keyframes by the loop verifier's
triangulation). Retrieval database, with offsets ``bow_ptr`` (K+1,) int64: ``bow_words`` int32 and
``bow_weights`` float64 of each keyframe's bag-of-words vector. The family's structure
(:class:`fgslam.core.mapdata.MapExport`): ``points_X_W`` (M, 3) float64, ``points_colour`` (M, 3) uint8,
``track_point`` / ``track_kf`` (T,) int64 and ``track_uv`` (T, 2) float64 (keyframe pixel of each
observation).

Sessions and frames (version 2): ``kf_session`` (K,) int64, the session each keyframe came from: a
recording, or a part of one whose run started a new map after a lost track (0: the map's first; a map
extended with ``fgslam run --map`` holds several, joined in one pose graph,
:func:`fgslam.localize.merge.join_sessions`). Every frame the recordings posed, in time order per
session: ``frame_timestamps`` (F,) float64 s, ``frame_kf`` (F,) int64 the position of its anchor
keyframe (the last keyframe of its own map at or before it, :func:`anchor_frames`) and ``frame_T_KC`` (F, 4, 4) float64 its pose relative
to that keyframe (``T_WC = T_WC[frame_kf] frame_T_KC``, :meth:`StoredMap.frame_poses`), so the frames
move with their keyframes when a join corrects them.

Errors: a missing, truncated or foreign file, another format version, or inconsistent arrays raise
:class:`MapFileError` naming the file and what is wrong; :func:`check_map_camera` names what differs
between the map's camera and a sequence's.
"""

from __future__ import annotations

import io
import json
import logging
import threading
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config import MAX_KEYFRAMES, MAX_SCALAR, check_ranges, ranged
from ..core.errors import DataError
from ..loop.bow import BowConfig, KeyframeFeatures, PlaceRecognizer
from ..loop.features import OrbConfig, to_grey_uint8
from ..loop.records import PoseGraphConfig, VerificationConfig
from ..core.mapdata import MapExport, rigid_poses
from .inplace import written_in_place

logger = logging.getLogger(__name__)

MAP_FORMAT = "fgslam-map"
MAP_FORMAT_VERSION = 2  # 2: sessions and frames
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)        # fixed entry date: identical maps give identical bytes
_ZIP_MAGIC = b"PK\x03\x04"
_CAMERA_RTOL = 1e-6                      # intrinsics equal up to float round-off
DESCRIPTOR_BYTES = 32
#: config keys whose values are file paths on the machine that ran (the map file itself, the map it
#: extends, calibration / ground-truth files, network checkpoints): left out of a map's meta
MACHINE_DEPENDENT_KEYS = ("save_map", "extend_map", "checkpoint")
MACHINE_DEPENDENT_SUFFIXES = ("_file", "_path", "_dir")

#: array name -> (dtype, trailing shape); the archive holds them in this order after ``meta``
ARRAYS: dict[str, tuple[str, tuple[int, ...]]] = {
    "kf_ids": ("int64", ()),
    "kf_timestamps": ("float64", ()),
    "kf_frame_index": ("int64", ()),
    "T_WC": ("float64", (4, 4)),
    "feat_ptr": ("int64", ()),
    "feat_uv": ("float32", (2,)),
    "feat_desc": ("uint8", (DESCRIPTOR_BYTES,)),
    "feat_X_C": ("float32", (3,)),
    "bow_ptr": ("int64", ()),
    "bow_words": ("int32", ()),
    "bow_weights": ("float64", ()),
    "points_X_W": ("float64", (3,)),
    "points_colour": ("uint8", (3,)),
    "track_point": ("int64", ()),
    "track_kf": ("int64", ()),
    "track_uv": ("float64", (2,)),
    "kf_session": ("int64", ()),
    "frame_timestamps": ("float64", ()),
    "frame_kf": ("int64", ()),
    "frame_T_KC": ("float64", (4, 4)),
}


class MapFileError(DataError):
    """A stored map that cannot be used: missing, truncated, foreign, another version, another camera."""


@dataclass
class MapFeaturesConfig:
    """Keyframe features of a stored map (and of the frames localised in it: the map's settings)."""

    image_scale: float = ranged(0.5, gt=0, le=1)  # features on the run's images scaled by this (VGA -> 320x240)
    bow: BowConfig = field(default_factory=lambda: BowConfig(orb=OrbConfig(n_features=800)))  # ORB + vocabulary
    min_depth: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # RGB-D: sensor depths (m) below this are no depth
    max_depth: float = ranged(8.0, gt=0, le=MAX_SCALAR)  # RGB-D: ... and above this
    max_depth_step: float = ranged(0.03, gt=0, le=1)  # RGB-D: no depth where the 3x3 depths differ by more than this share (edges)

    def validate(self) -> None:
        check_ranges(self)
        self.bow.orb.validate()


@dataclass
class MapMergeConfig:
    """Merging a recording into a stored map (``fgslam run ... --map MAP``, :func:`fgslam.localize.merge.merge_recording`;
    ``output.map_merge`` of a run, ``merge`` of ``fgslam localize``'s config)."""

    min_keyframes: int = ranged(3, ge=1, le=MAX_KEYFRAMES)  # recording keyframes localised in the map (consistently) to merge
    max_rotation_deg: float = ranged(5.0, gt=0, le=180)  # consistent: their map-from-recording rotations within this of each other
    max_position_error: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # ... and their positions within this share of the keyframes' extent


@dataclass
class MapJoinConfig:
    """The sessions of a merged map optimised together (``fgslam run ... --map MAP``, ``output.map_join``;
    :func:`fgslam.localize.merge.join_sessions`)."""

    enabled: bool = True  # optimise the sessions in one pose graph; False: the recording is moved by the merge's one transform
    # The joint pose graph: the consistent localisations are its loops. A localisation measures the
    # camera's pose in the map, not the recording's scale there: its log-scale sigma says nothing (1.0).
    # The plausibility gate measures a correction against the keyframe path between the two ends, which
    # across sessions runs through the boundary; the merge's consistency check has vetted the links, so
    # the gate (1.0: a correction up to that path) only drops gross ones.
    pose_graph: PoseGraphConfig = field(default_factory=lambda: PoseGraphConfig(
        loop_sigmas=(0.01, 0.01, 0.01, 0.1, 0.1, 0.1, 1.0), max_correction_translation_fraction=1.0))
    session_link_sigma_multiple: float = ranged(1000.0, ge=1, le=MAX_SCALAR)  # smoothness sigmas x this across a session boundary (a weak link)
    # The translation sigmas of pose_graph (loops and smoothness) hold for a scene this deep, in metres:
    # they are scaled by the stored map's median feature depth over it, so that a monocular map (units
    # of its own) is held to the same share of its scene as a metric one.
    reference_depth: float = ranged(2.0, gt=0, le=MAX_SCALAR)


@dataclass
class StoredMap:
    """A stored map in memory (the module docstring describes every array)."""

    meta: dict[str, Any]
    kf_ids: np.ndarray
    kf_timestamps: np.ndarray
    kf_frame_index: np.ndarray
    T_WC: np.ndarray
    feat_ptr: np.ndarray
    feat_uv: np.ndarray
    feat_desc: np.ndarray
    feat_X_C: np.ndarray
    bow_ptr: np.ndarray
    bow_words: np.ndarray
    bow_weights: np.ndarray
    points_X_W: np.ndarray
    points_colour: np.ndarray
    track_point: np.ndarray
    track_kf: np.ndarray
    track_uv: np.ndarray
    kf_session: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # empty: all session 0
    frame_timestamps: np.ndarray = field(default_factory=lambda: np.zeros(0))  # empty: no frames stored
    frame_kf: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    frame_T_KC: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))

    def __post_init__(self) -> None:
        for name, (dtype, tail) in ARRAYS.items():
            setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=dtype).reshape((-1, *tail)))
        if self.kf_session.size == 0:
            self.kf_session = np.zeros(self.num_keyframes, np.int64)

    @property
    def sessions(self) -> int:
        """The sessions joined in this map: its recordings, and the parts of a recording whose run started
        a new map after a lost track (1 for a map of one run that kept its track)."""
        return int(self.kf_session.max()) + 1 if self.kf_session.size else 1

    def frame_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """``(timestamps (F,), T_WC (F, 4, 4))`` of the stored frames in the map's frame: each frame's
        keyframe pose times its relative pose, made rigid (:func:`fgslam.core.mapdata.rigid_poses`: a
        Sim(3) keyframe pose carries its scale into the position only)."""
        return self.frame_timestamps.copy(), rigid_poses(self.T_WC[self.frame_kf] @ self.frame_T_KC)

    @property
    def num_keyframes(self) -> int:
        return int(self.kf_ids.shape[0])

    @property
    def metric(self) -> bool:
        return bool(self.meta.get("metric", False))

    def features(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(uv, descriptors, X_C)`` of the keyframe at position ``k``."""
        a, b = int(self.feat_ptr[k]), int(self.feat_ptr[k + 1])
        return self.feat_uv[a:b], self.feat_desc[a:b], self.feat_X_C[a:b]

    def bow(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(words, weights)`` of the keyframe at position ``k``."""
        a, b = int(self.bow_ptr[k]), int(self.bow_ptr[k + 1])
        return self.bow_words[a:b], self.bow_weights[a:b]

    def check(self, source: str) -> None:
        """Consistent shapes and offsets; :class:`MapFileError` naming ``source`` and what is wrong."""
        k = self.num_keyframes

        def bad(what: str) -> MapFileError:
            return MapFileError(f"{source}: inconsistent map: {what}")

        for name in ("kf_timestamps", "kf_frame_index", "T_WC"):
            if getattr(self, name).shape[0] != k:
                raise bad(f"{k} keyframe ids but {getattr(self, name).shape[0]} entries in {name}")
        for ptr, arrays in (("feat_ptr", ("feat_uv", "feat_desc", "feat_X_C")), ("bow_ptr", ("bow_words", "bow_weights"))):
            p = getattr(self, ptr)
            n = getattr(self, arrays[0]).shape[0]
            if p.shape[0] != k + 1 or p[0] != 0 or p[-1] != n or np.any(np.diff(p) < 0):
                raise bad(f"{ptr} does not index the {n} rows of {arrays[0]}")
            for other in arrays[1:]:
                if getattr(self, other).shape[0] != n:
                    raise bad(f"{other} has {getattr(self, other).shape[0]} rows, {arrays[0]} {n}")
        m, t = self.points_X_W.shape[0], self.track_point.shape[0]
        if self.points_colour.shape[0] != m or self.track_kf.shape[0] != t or self.track_uv.shape[0] != t:
            raise bad("points or tracks of unequal length")
        if t and (self.track_point.min() < 0 or self.track_point.max() >= m):
            raise bad("a track names a point that does not exist")
        if not np.isfinite(self.T_WC).all():
            raise bad("a keyframe pose is not finite")
        if self.kf_session.shape[0] != k or (k and self.kf_session.min() < 0):
            raise bad(f"kf_session has {self.kf_session.shape[0]} entries for {k} keyframes, or a negative one")
        f = self.frame_timestamps.shape[0]
        if self.frame_kf.shape[0] != f or self.frame_T_KC.shape[0] != f:
            raise bad("frame_timestamps, frame_kf and frame_T_KC of unequal length")
        if f and (self.frame_kf.min() < 0 or self.frame_kf.max() >= k):
            raise bad("frame_kf names a keyframe position that does not exist")
        if not (np.isfinite(self.frame_T_KC).all() and np.isfinite(self.frame_timestamps).all()):
            raise bad("a frame pose or time is not finite")
        if len(np.unique(self.kf_ids)) != k:
            raise bad("kf_ids are not unique")
        if t and not np.isin(self.track_kf, self.kf_ids).all():
            raise bad("track_kf names a keyframe id that is not in kf_ids")
        camera = self.meta.get("camera")
        if not isinstance(camera, dict) or not _numbers(camera.get("K"), 4) or not _numbers(
                [camera.get("width"), camera.get("height")], 2):
            raise bad("meta has no camera (K: 4 numbers, width, height)")
        features = self.meta.get("features")
        if not isinstance(features, dict):
            raise bad("meta has no features section")
        missing = [key for key in ("image_scale", "K", "width", "height", "vocabulary", "orb") if key not in features]
        if missing:
            raise bad(f"meta features has no {', '.join(missing)}")
        if not _numbers(features["K"], 4) or not _numbers([features["image_scale"], features["width"],
                                                            features["height"]], 3):
            raise bad("meta features: K must be 4 numbers, image_scale / width / height numbers")
        if not isinstance(features["orb"], dict) or not isinstance(features["vocabulary"], str):
            raise bad("meta features: orb must be a mapping, vocabulary a name")


def _numbers(values: object, n: int) -> bool:
    """``values`` is a list of ``n`` finite numbers (not booleans)."""
    return (isinstance(values, (list, tuple)) and len(values) == n
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in values))


# ----------------------------------------------------------------------------------- save / load

def _meta_bytes(meta: dict) -> np.ndarray:
    text = json.dumps(meta, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return np.frombuffer(text.encode("utf-8"), dtype=np.uint8)


def save_stored_map(path: str | Path, stored: StoredMap) -> Path:
    """Write ``stored`` to ``path`` (module docstring: deterministic bytes, atomic replace)."""
    path = Path(path)
    stored.check(str(path))
    meta = dict(stored.meta, format=MAP_FORMAT, version=MAP_FORMAT_VERSION)
    items = [("meta", _meta_bytes(meta))] + [(name, getattr(stored, name)) for name in ARRAYS]
    with written_in_place(path, overwrite=True) as tmp:  # replaced: the callers check an existing path
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name, arr in items:
                info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_DATE)
                info.compress_type = zipfile.ZIP_STORED
                info.external_attr = 0o644 << 16
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
                zf.writestr(info, buf.getvalue())
    return path


def check_map_file(path: str | Path) -> Path:
    """The cheap checks of a map file, before any work (``fgslam run --map``: before the dataset is
    opened): it exists and is a whole npz archive; :class:`MapFileError` otherwise."""
    path = Path(path)
    if not path.is_file():
        raise MapFileError(f"{path}: no such map file")
    with open(path, "rb") as f:
        magic = f.read(len(_ZIP_MAGIC))
    if magic != _ZIP_MAGIC:
        raise MapFileError(f"{path}: not a fgslam map (not an npz archive)")
    if not zipfile.is_zipfile(path):
        raise MapFileError(f"{path}: truncated or damaged map file (no zip directory at its end)")
    return path


#: what numpy and zipfile raise reading a damaged npz archive whose zip directory is whole (a truncated
#: or corrupted entry, a bad header)
DAMAGED_ARCHIVE_ERRORS = (OSError, ValueError, EOFError, KeyError, UnicodeDecodeError, zipfile.BadZipFile)


def damaged_map_error(path: str | Path, exc: BaseException) -> MapFileError:
    """The error of a map file (a stored map, a run's ``map.npz``) that reading failed on with ``exc``,
    one of :data:`DAMAGED_ARCHIVE_ERRORS`."""
    return MapFileError(f"{path}: truncated or damaged map file ({type(exc).__name__}: {exc})")


def load_stored_map(path: str | Path) -> StoredMap:
    """Read a map written by :func:`save_stored_map` (:class:`MapFileError` on bad input)."""
    path = check_map_file(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            if "meta" not in z.files:
                raise MapFileError(f"{path}: not a fgslam map (an npz archive without 'meta')")
            meta = json.loads(z["meta"].tobytes().decode("utf-8"))
            if not isinstance(meta, dict) or meta.get("format") != MAP_FORMAT:
                raise MapFileError(f"{path}: not a fgslam map (meta format {meta.get('format')!r}, "
                                   f"expected {MAP_FORMAT!r})" if isinstance(meta, dict) else
                                   f"{path}: not a fgslam map (meta is not a JSON object)")
            version = meta.get("version")
            if version != MAP_FORMAT_VERSION:
                newer = isinstance(version, int) and version > MAP_FORMAT_VERSION
                raise MapFileError(f"{path}: map format version {version}, this fgslam reads version "
                                   f"{MAP_FORMAT_VERSION} " + ("(written by a newer fgslam: update fgslam)" if newer else
                                                               "(version 2 stores each recording's frames: run the "
                                                               "map's recording again with --save-map)"))
            missing = [name for name in ARRAYS if name not in z.files]
            if missing:
                raise MapFileError(f"{path}: not a complete fgslam map (missing {', '.join(missing)})")
            arrays = {}
            for name, (dtype, _) in ARRAYS.items():
                arr = z[name]
                if arr.dtype != np.dtype(dtype):
                    raise MapFileError(f"{path}: array {name} is {arr.dtype}, expected {dtype}")
                arrays[name] = arr
    except MapFileError:
        raise
    except DAMAGED_ARCHIVE_ERRORS as exc:
        raise damaged_map_error(path, exc) from exc
    try:
        stored = StoredMap(meta, **arrays)
    except ValueError as exc:
        raise MapFileError(f"{path}: inconsistent map arrays ({exc})") from exc
    stored.check(str(path))
    return stored


def check_map_camera(stored: StoredMap, K: np.ndarray, width: int, height: int, map_path: str | Path,
                     data: str | Path) -> None:
    """:class:`MapFileError` when the sequence ``data`` (images ``width x height``, intrinsics ``K``)
    has another camera than the map's, naming both files and what differs."""
    cam = stored.meta["camera"]
    K_map = np.asarray(cam["K"], np.float64)
    K_seq = np.asarray(K, np.float64).reshape(-1)
    diffs = []
    if (int(cam["width"]), int(cam["height"])) != (int(width), int(height)):
        diffs.append(f"image size {cam['width']}x{cam['height']} vs {width}x{height}")
    if K_seq.shape != (4,) or not np.allclose(K_map, K_seq, rtol=_CAMERA_RTOL, atol=0.0):
        diffs.append("intrinsics fx, fy, cx, cy " + ", ".join(f"{v:g}" for v in K_map) + " vs "
                     + ", ".join(f"{v:g}" for v in K_seq))
    if diffs:
        raise MapFileError(f"{map_path}: the map's camera differs from the sequence's ({data}): {'; '.join(diffs)}")


# ----------------------------------------------------------------------------------- building

def portable_config(config: dict) -> dict:
    """``config`` (a resolved configuration as a dict) without its machine-dependent fields, at any
    depth: the keys :data:`MACHINE_DEPENDENT_KEYS` and those ending with
    :data:`MACHINE_DEPENDENT_SUFFIXES` (file paths). What is left is content: the same settings on
    another machine or with other paths give the same dict."""
    def machine(key: str) -> bool:
        return key in MACHINE_DEPENDENT_KEYS or key.endswith(MACHINE_DEPENDENT_SUFFIXES)

    return {k: portable_config(v) if isinstance(v, dict) else v for k, v in config.items() if not machine(str(k))}


def feature_camera(K: np.ndarray, width: int, height: int, scale: float) -> tuple[np.ndarray, int, int]:
    """Intrinsics and size of the feature image: the run's image resized by ``scale`` (pixel centres
    at integer coordinates: ``c' = (c + 0.5) s - 0.5``)."""
    w, h = max(1, round(width * scale)), max(1, round(height * scale))
    sx, sy = w / width, h / height
    K = np.asarray(K, np.float64).reshape(-1)
    return np.array([K[0] * sx, K[1] * sy, (K[2] + 0.5) * sx - 0.5, (K[3] + 0.5) * sy - 0.5]), w, h


def feature_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """The grey image resized to the feature image size (area interpolation)."""
    import cv2  # deferred: cv2

    grey = to_grey_uint8(image)
    if grey.shape[1] == width and grey.shape[0] == height:
        return grey
    return cv2.resize(grey, (width, height), interpolation=cv2.INTER_AREA)


def depth_points(uv: np.ndarray, depth: np.ndarray, K_feat: np.ndarray, scale: float,
                 cfg: MapFeaturesConfig) -> np.ndarray:
    """(N, 3) camera points of feature pixels ``uv`` (feature image) from a sensor ``depth`` at the
    run's resolution (metres, 0 = none); NaN where the depth is missing, out of range or at an edge."""
    X = np.full((len(uv), 3), np.nan, np.float32)
    if len(uv) == 0:
        return X
    h, w = depth.shape
    col = np.clip(np.rint((uv[:, 0] + 0.5) / scale - 0.5).astype(np.int64), 1, w - 2)
    row = np.clip(np.rint((uv[:, 1] + 0.5) / scale - 0.5).astype(np.int64), 1, h - 2)
    offsets = np.array([-1, 0, 1])
    patch = depth[row[:, None, None] + offsets[None, :, None], col[:, None, None] + offsets[None, None, :]]
    patch = patch.reshape(len(uv), -1)
    z = depth[row, col]
    ok = (patch.min(axis=1) >= cfg.min_depth) & (patch.max(axis=1) <= cfg.max_depth)
    ok &= (patch.max(axis=1) - patch.min(axis=1)) <= cfg.max_depth_step * np.maximum(z, cfg.min_depth)
    X[ok, 0] = (uv[ok, 0] - K_feat[2]) / K_feat[0] * z[ok]
    X[ok, 1] = (uv[ok, 1] - K_feat[3]) / K_feat[1] * z[ok]
    X[ok, 2] = z[ok]
    return X


def _frame_range(dataset) -> dict[str, Any]:
    """The raw frames of the map run: ``start``, ``end`` (None: to the end) and ``stride``."""
    cfg = getattr(dataset, "config", None)
    if cfg is None:
        return {}
    return {"start": int(cfg.start), "end": None if cfg.end is None else int(cfg.end), "stride": int(cfg.stride)}


def anchor_frames(kf_timestamps: np.ndarray, T_WK: np.ndarray, trajectory: tuple[np.ndarray, np.ndarray] | None,
                  map_starts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(frame_timestamps, frame_kf, frame_T_KC)`` of a run's frames ``trajectory = (timestamps, T_WC)``:
    each frame's anchor is the last keyframe at or before it (the first keyframe for frames before
    it), its pose kept relative to that keyframe. With ``map_starts`` (the times the run started a new
    map, :func:`map_segments`) the anchor is one of the frame's own map when that map has a keyframe. No
    trajectory or no keyframe: no frames."""
    if trajectory is None or len(kf_timestamps) == 0:
        return np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 4, 4))
    t, T_WC = np.asarray(trajectory[0], np.float64), np.asarray(trajectory[1], np.float64)
    kf_t = np.asarray(kf_timestamps, np.float64)
    by_time = np.argsort(kf_t, kind="stable")
    before = np.searchsorted(kf_t[by_time], t, side="right") - 1
    anchor = by_time[np.clip(before, 0, len(kf_t) - 1)]
    if map_starts is not None and len(map_starts):
        kf_seg, frame_seg = map_segments(kf_t, map_starts), map_segments(t, map_starts)
        for s in np.unique(frame_seg):
            own = by_time[kf_seg[by_time] == s]  # the segment's keyframes by time
            if own.size == 0:
                continue
            rows = np.flatnonzero(frame_seg == s)
            at = np.searchsorted(kf_t[own], t[rows], side="right") - 1
            anchor[rows] = own[np.clip(at, 0, own.size - 1)]
    return t, anchor.astype(np.int64), np.linalg.inv(T_WK[anchor]) @ T_WC


def map_segments(timestamps: np.ndarray, map_starts: np.ndarray | None) -> np.ndarray:
    """(N,) int64: the part of a recording each time belongs to, 0 before the first of ``map_starts``
    (the times a run started a new map after a lost track), k from the k-th on."""
    starts = np.sort(np.asarray([] if map_starts is None else map_starts, np.float64))
    return np.searchsorted(starts, np.asarray(timestamps, np.float64), side="right").astype(np.int64)


def build_stored_map(exported: MapExport, dataset, *, sensor: str, family: str, config: dict,
                     features: MapFeaturesConfig, verification: VerificationConfig | None = None, groundtruth_alignment: dict | None = None,
                     frame_indices: np.ndarray | None = None,
                     trajectory: tuple[np.ndarray, np.ndarray] | None = None,
                     map_starts: np.ndarray | None = None) -> StoredMap:
    """The stored map of a run: the frontend's keyframes and structure (``exported``), the keyframe
    images re-read from ``dataset`` (the frame nearest to each keyframe's time among
    ``frame_indices``, default all) for their features, 3-D points from the sensor depth (``rgbd``)
    or triangulated between neighbouring keyframes (``verification``:
    :class:`fgslam.loop.records.VerificationConfig`), and their BoW vectors; ``trajectory``
    (``(timestamps, T_WC)`` of the run's frames, in the keyframes' frame) gives the stored frames;
    ``map_starts`` (the times the run started a new map after a lost track) makes each of its maps a
    session of its own (``kf_session``; its points triangulated within it), which a later ``--map`` run
    places in the map by its own localisations."""
    features.validate()
    calib = dataset.calibration
    K_feat, w_feat, h_feat = feature_camera(calib.K, calib.width, calib.height, features.image_scale)
    recognizer = PlaceRecognizer(features.bow)
    t = np.asarray(dataset.timestamps, np.float64)
    indices = np.arange(len(t)) if frame_indices is None else np.asarray(frame_indices, np.int64)
    order = np.argsort(exported.kf_ids, kind="stable")
    kf_ids = exported.kf_ids[order]
    stamps = exported.kf_timestamps[order]
    T_WC = exported.T_WC[order]
    kf_session = np.unique(map_segments(stamps, map_starts), return_inverse=True)[1].astype(np.int64)  # maps with keyframes
    t_sel = t[indices]
    kf_frame = indices[np.argmin(np.abs(t_sel[None, :] - stamps[:, None]), axis=1)] if len(indices) else \
        np.full(len(kf_ids), -1, np.int64)
    feats: list[KeyframeFeatures] = []
    X_list: list[np.ndarray] = []
    for fi in kf_frame:
        frame = dataset[int(fi)]
        f = recognizer.describe(feature_image(frame.image, w_feat, h_feat))
        feats.append(f)
        if sensor == "rgbd" and frame.depth is not None:
            X_list.append(depth_points(f.uv, frame.depth, K_feat, w_feat / calib.width, features))
        else:
            X_list.append(None)
    if any(X is None for X in X_list):  # no sensor depth: triangulate with neighbouring keyframes
        from ..loop.verification import LoopKeyframe, Verifier  # deferred: torch (loading a map, a config need none)

        table = {int(i): LoopKeyframe(int(i), float(s), None, K_feat, (), f) for i, s, f in zip(kf_ids, stamps, feats)}
        verifier = Verifier(verification or VerificationConfig(), table, threading.RLock(), metric=sensor != "mono")
        poses = {int(i): T for i, T in zip(kf_ids, T_WC)}
        id_order = {int(s): [int(i) for i in kf_ids[kf_session == s]] for s in np.unique(kf_session)}  # per map
        for k, X in enumerate(X_list):
            if X is None:  # the neighbours of its own map
                X_tri, ok = verifier.triangulate(table[int(kf_ids[k])], id_order[int(kf_session[k])], poses)
                X_tri = X_tri.astype(np.float32)
                X_tri[~ok] = np.nan
                X_list[k] = X_tri
    counts = np.array([len(f.uv) for f in feats], np.int64)
    bow_counts = np.array([len(f.bow.words) for f in feats], np.int64)

    def cat(arrays: list[np.ndarray], empty_shape: tuple[int, ...], dtype) -> np.ndarray:
        return np.concatenate(arrays).astype(dtype) if arrays else np.zeros(empty_shape, dtype)

    orb = features.bow.orb
    meta = {
        "family": family,
        "sensor": sensor,
        "metric": sensor != "mono",
        "camera": {"K": [float(v) for v in calib.K], "width": int(calib.width), "height": int(calib.height)},
        "features": {"image_scale": features.image_scale, "K": [float(v) for v in K_feat], "width": w_feat,
                     "height": h_feat, "vocabulary": features.bow.vocabulary,
                     "orb": {k: getattr(orb, k) for k in orb.__dataclass_fields__}},
        "config": portable_config(config),
        "dataset": {"format": str(getattr(dataset, "format", "")), "frames": int(len(indices)),
                    **_frame_range(dataset)},
        "groundtruth_alignment": groundtruth_alignment,
    }
    stored = StoredMap(
        meta, kf_ids, stamps, kf_frame, T_WC,
        np.concatenate([[0], np.cumsum(counts)]), cat([f.uv for f in feats], (0, 2), np.float32),
        cat([f.descriptors for f in feats], (0, DESCRIPTOR_BYTES), np.uint8), cat(X_list, (0, 3), np.float32),
        np.concatenate([[0], np.cumsum(bow_counts)]), cat([f.bow.words for f in feats], (0,), np.int32),
        cat([f.bow.weights for f in feats], (0,), np.float64),
        exported.X_W, exported.colour, exported.track_point, exported.track_kf, exported.track_uv,
        kf_session, *anchor_frames(stamps, T_WC, trajectory, map_starts))
    n_3d = int(np.isfinite(stored.feat_X_C[:, 0]).sum())
    logger.info("stored map: %d keyframes, %d features (%d with a 3-D point), %d points", stored.num_keyframes,
                len(stored.feat_uv), n_3d, len(stored.points_X_W))
    return stored
