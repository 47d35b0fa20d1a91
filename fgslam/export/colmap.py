"""COLMAP models through pycolmap: export a run's map, import a model for evaluation, run COLMAP's
own structure from motion.

Export (:func:`build_reconstruction`, :func:`export_colmap`): one ``PINHOLE`` camera with the
calibration the frontend used (the undistorted, resized images), one image per keyframe (or per
frame with ``all_frames``: frames that are not keyframes get a pose and no 2-D points), one 3-D
point per map point whose track keeps at least ``min_track_length`` observations within
``max_reprojection_px`` of the point's projection. COLMAP puts pixel centres at +0.5 (the top-left
pixel's centre is (0.5, 0.5)); fgslam at integer coordinates: principal points and observations are
shifted by half a pixel. A model folder holds ``cameras``, ``images`` and ``points3D`` in COLMAP's
binary (``.bin``) or text (``.txt``) format, which COLMAP, its MVS and Gaussian-splatting trainers
read directly; :func:`export_colmap` lays out ``DIR/sparse/0/`` and, when image files are given,
``DIR/images/``.

Import (:func:`read_colmap_model`): the registered images' poses (camera-to-world, rigid) by image
name, and the points with colours.

Structure from motion (:func:`run_colmap_sfm`): SIFT on the CPU, sequential matching, incremental
mapping, with the known pinhole calibration (kept fixed), as ``fgslam compare-colmap`` runs it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from ..core.config import MAX_COUNT, MAX_IMAGE_SIDE, MAX_KEYFRAMES, MAX_SCALAR, MAX_SEED, MAX_THREADS, ranged
from ..core.errors import DataError
from ..io.trajectory import Trajectory
from .map import RunMap

logger = logging.getLogger(__name__)

COLMAP_PIXEL_OFFSET = 0.5  # COLMAP's pixel centres sit at +0.5
MODEL_FILES = ("cameras", "images", "points3D")
SPARSE_SUBDIR = Path("sparse") / "0"
IMAGES_SUBDIR = "images"


@dataclass
class ColmapExportConfig:
    """What a COLMAP export keeps of the map."""

    max_reprojection_px: float = ranged(4.0, gt=0, le=MAX_SCALAR)  # drop observations farther than this from the point's projection (COLMAP's own filter: 4 px)
    min_track_length: int = ranged(2, ge=1, le=MAX_KEYFRAMES)  # points seen by fewer keyframes (after the filter) are left out
    min_depth: float = ranged(0.0, ge=0, le=MAX_SCALAR)  # drop observations of points at or behind this depth (map units)


@dataclass
class ColmapSfmConfig:
    """pycolmap's SfM as ``fgslam compare-colmap`` runs it."""

    max_num_features: int = ranged(8192, ge=16, le=MAX_COUNT)  # SIFT features per image
    max_image_size: int = ranged(3200, ge=16, le=MAX_IMAGE_SIDE)  # SIFT: larger images are downscaled (COLMAP's default)
    overlap: int = ranged(10, ge=1, le=MAX_KEYFRAMES)  # sequential matching: each image against the next this many
    num_threads: int = ranged(-1, ge=-1, le=MAX_THREADS)  # -1: every core
    min_model_size: int = ranged(10, ge=3, le=MAX_COUNT)  # smallest model the mapper keeps
    random_seed: int = ranged(0, ge=-1, le=MAX_SEED)  # mapper's RANSAC seed (-1: random)


# ------------------------------------------------------------------------------------------------ export


@dataclass
class ExportStats:
    """What an export wrote: images, points, observations kept, and what was left out."""

    images: int
    points: int
    observations: int
    dropped_observations: int  # beyond max_reprojection_px, behind the camera, repeated, or of a dropped point
    dropped_points: int  # tracks shorter than min_track_length
    median_reprojection_px: float

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def _project(T_WC: np.ndarray, X_W: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (fgslam convention) and depths of points ``X_W`` (n, 3) in cameras ``T_WC`` (n, 4, 4)."""
    R, t = T_WC[:, :3, :3], T_WC[:, :3, 3]
    X_C = np.einsum("nji,nj->ni", R, X_W - t)
    z = X_C[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([K[0] * X_C[:, 0] / z + K[2], K[1] * X_C[:, 1] / z + K[3]], 1)
    return uv, z


def build_reconstruction(run_map: RunMap, image_names: dict[int, str], config: ColmapExportConfig | None = None,
                         extra_frames: dict[int, tuple[str, np.ndarray]] | None = None):
    """A ``pycolmap.Reconstruction`` of ``run_map``.

    Args:
        run_map: the run's map.
        image_names: keyframe id -> image name (file name under the model's image folder).
        config: filtering of observations and points.
        extra_frames: image id -> (name, rigid T_WC) of frames without observations (``--all-frames``);
            their ids must not collide with keyframe image ids (keyframe ids + 1).

    Returns:
        ``(reconstruction, ExportStats)``.
    """
    import pycolmap  # deferred: pycolmap

    config = config or ColmapExportConfig()
    m = run_map.map
    K = np.asarray(run_map.intrinsics, dtype=np.float64)
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera(model="PINHOLE", width=int(run_map.width), height=int(run_map.height),
                             params=[K[0], K[1], K[2] + COLMAP_PIXEL_OFFSET, K[3] + COLMAP_PIXEL_OFFSET], camera_id=1)
    rec.add_camera_with_trivial_rig(camera)

    # observations kept: in front of the camera and within max_reprojection_px of the projection
    kf_pos = {int(k): i for i, k in enumerate(m.kf_ids)}
    obs_pos = np.array([kf_pos[int(k)] for k in m.track_kf], dtype=np.int64)
    if obs_pos.size:
        uv_hat, z = _project(m.T_WC[obs_pos], m.X_W[m.track_point], K)
        err = np.linalg.norm(uv_hat - m.track_uv, axis=1)
        keep = (z > config.min_depth) & (err <= config.max_reprojection_px)
    else:
        err, keep = np.zeros(0), np.zeros(0, bool)
    # one observation per (point, keyframe): the first
    order = np.lexsort((obs_pos, m.track_point))
    _, first = np.unique(np.stack([m.track_point[order], obs_pos[order]], 1), axis=0, return_index=True)
    unique = np.zeros(obs_pos.size, bool)
    unique[order[first]] = True
    keep &= unique
    counts = np.bincount(m.track_point[keep], minlength=m.num_points)
    good_point = counts >= config.min_track_length
    keep &= good_point[m.track_point] if m.track_point.size else keep

    # 2-D points per keyframe image
    kept = np.flatnonzero(keep)
    per_image: dict[int, list[int]] = {}
    for o in kept:
        per_image.setdefault(int(obs_pos[o]), []).append(int(o))
    point2d_index = np.full(obs_pos.size, -1, np.int64)
    for i, kf_id in enumerate(m.kf_ids):
        obs = per_image.get(i, [])
        point2d_index[obs] = np.arange(len(obs))
        keypoints = m.track_uv[obs] + COLMAP_PIXEL_OFFSET if obs else np.zeros((0, 2))
        image = pycolmap.Image(name=image_names[int(kf_id)], keypoints=np.asarray(keypoints, dtype=np.float64),
                               camera_id=1, image_id=int(i) + 1)
        rec.add_image_with_trivial_frame(image, _cam_from_world(m.T_WC[i]))
    for image_id, (name, T_WC) in sorted((extra_frames or {}).items()):
        image = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=1, image_id=int(image_id))
        rec.add_image_with_trivial_frame(image, _cam_from_world(T_WC))

    # 3-D points with their tracks
    by_point = np.argsort(m.track_point[kept], kind="stable")
    kept = kept[by_point]
    bounds = np.searchsorted(m.track_point[kept], np.arange(m.num_points + 1))
    for p in np.flatnonzero(good_point):
        obs = kept[bounds[p]:bounds[p + 1]]
        track = pycolmap.Track([pycolmap.TrackElement(int(obs_pos[o]) + 1, int(point2d_index[o])) for o in obs])
        rec.add_point3D(m.X_W[p], track, m.colour[p])
    stats = ExportStats(
        images=rec.num_images(), points=rec.num_points3D(), observations=int(keep.sum()),
        dropped_observations=int(obs_pos.size - keep.sum()), dropped_points=int((~good_point).sum()),
        median_reprojection_px=float(np.median(err[keep])) if keep.any() else float("nan"),
    )
    return rec, stats


def _cam_from_world(T_WC: np.ndarray):
    import pycolmap  # deferred: pycolmap

    T_CW = np.linalg.inv(np.asarray(T_WC, dtype=np.float64))
    return pycolmap.Rigid3d(T_CW[:3, :4])


def write_model(rec, folder: str | Path, fmt: Literal["bin", "txt"] = "bin") -> Path:
    """Write ``rec`` into ``folder`` (created) as COLMAP binary or text files."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        (rec.write_text if fmt == "txt" else rec.write_binary)(str(folder))
    except (OSError, RuntimeError, ValueError) as exc:
        raise DataError(f"{folder}: cannot write the COLMAP model: {exc}") from exc
    return folder


# ------------------------------------------------------------------------------------------------ import


@dataclass
class ColmapModel:
    """A COLMAP model read back: registered images and points.

    Attributes:
        names: image names, in image-id order.
        T_WC: (N, 4, 4) rigid camera-to-world poses of those images.
        X_W: (M, 3) points; colour: (M, 3) uint8; track_length: (M,) observations per point.
        intrinsics: camera id -> (model name, width, height, params).
    """

    names: list[str]
    T_WC: np.ndarray
    X_W: np.ndarray
    colour: np.ndarray
    track_length: np.ndarray
    intrinsics: dict[int, tuple[str, int, int, list[float]]]
    reconstruction: object = None

    def trajectory(self, timestamp_of_name: dict[str, float]):
        """The images whose names ``timestamp_of_name`` knows as a :class:`~fgslam.io.trajectory.Trajectory`
        (sorted by time); raises DataError when none does."""
        rows = sorted((timestamp_of_name[n], i) for i, n in enumerate(self.names) if n in timestamp_of_name)
        if not rows:
            raise DataError(f"none of the model's {len(self.names)} image names is a frame of the sequence "
                            f"(e.g. {self.names[:3]})")
        return Trajectory(np.array([t for t, _ in rows]), self.T_WC[[i for _, i in rows]])


def check_model_folder(folder: str | Path) -> str:
    """The format (``bin`` or ``txt``) of the COLMAP model in ``folder``; DataError naming the missing
    files when neither set is complete."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: no such COLMAP model folder")
    for ext in ("bin", "txt"):
        if all((folder / f"{name}.{ext}").is_file() for name in MODEL_FILES):
            return ext
    present = {ext: [n for n in MODEL_FILES if (folder / f"{n}.{ext}").is_file()] for ext in ("bin", "txt")}
    ext = "bin" if len(present["bin"]) >= len(present["txt"]) else "txt"
    missing = [f"{n}.{ext}" for n in MODEL_FILES if n not in present[ext]]
    raise DataError(f"{folder}: incomplete COLMAP model: missing {', '.join(missing)} "
                    f"(a model needs {', '.join(n + '.' + ext for n in MODEL_FILES)})")


def read_colmap_model(folder: str | Path) -> ColmapModel:
    """Read a COLMAP model (binary or text) from ``folder`` (or ``folder/sparse/0``)."""
    import pycolmap  # deferred: pycolmap

    folder = Path(folder)
    if not any((folder / f"{n}.{e}").exists() for n in MODEL_FILES for e in ("bin", "txt")) and (folder / SPARSE_SUBDIR).is_dir():
        folder = folder / SPARSE_SUBDIR
    check_model_folder(folder)
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except (RuntimeError, ValueError, OSError) as exc:
        raise DataError(f"{folder}: cannot read the COLMAP model: {exc}") from exc
    return model_from_reconstruction(rec)


def model_from_reconstruction(rec) -> ColmapModel:
    """:class:`ColmapModel` of a ``pycolmap.Reconstruction`` (registered images only)."""
    names, poses = [], []
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.image(image_id)
        T_CW = np.eye(4)
        T_CW[:3, :4] = image.cam_from_world().matrix()
        names.append(image.name)
        poses.append(np.linalg.inv(T_CW))
    pids = sorted(rec.point3D_ids())
    X = np.array([rec.point3D(p).xyz for p in pids], dtype=np.float64).reshape(-1, 3)
    colour = np.array([rec.point3D(p).color for p in pids], dtype=np.uint8).reshape(-1, 3)
    track_length = np.array([rec.point3D(p).track.length() for p in pids], dtype=np.int64)
    intrinsics = {int(cid): (cam.model.name, int(cam.width), int(cam.height), [float(v) for v in cam.params])
                  for cid, cam in rec.cameras.items()}
    return ColmapModel(names, np.array(poses).reshape(-1, 4, 4), X, colour, track_length, intrinsics, rec)


def reprojection_errors(rec) -> np.ndarray:
    """Pixel reprojection error of every observation of every 3-D point of ``rec``."""
    errors = []
    for pid in rec.point3D_ids():
        point = rec.point3D(pid)
        for el in point.track.elements:
            image = rec.image(el.image_id)
            uv = image.project_point(point.xyz)
            if uv is None:
                errors.append(np.inf)
                continue
            errors.append(float(np.linalg.norm(np.asarray(uv) - image.points2D[el.point2D_idx].xy)))
    return np.asarray(errors, dtype=np.float64)


# ------------------------------------------------------------------------------------------------ SfM


@dataclass
class SfmResult:
    """What :func:`run_colmap_sfm` produced: the largest model and the time of each stage (s)."""

    model: ColmapModel | None
    models: int
    seconds: dict[str, float]
    cpu_seconds: float


def run_colmap_sfm(image_dir: str | Path, work_dir: str | Path, intrinsics: np.ndarray, config: ColmapSfmConfig | None = None,
                   image_names: list[str] | None = None) -> SfmResult:
    """pycolmap's SfM on the images in ``image_dir`` with a known pinhole camera (fgslam convention
    ``fx, fy, cx, cy``; kept fixed): SIFT on the CPU, sequential matching, incremental mapping.
    The database and models go to ``work_dir``."""
    import resource  # deferred: Unix-only standard module (the SfM reports its CPU time)

    import pycolmap  # deferred: pycolmap

    config = config or ColmapSfmConfig()
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    db.unlink(missing_ok=True)
    K = np.asarray(intrinsics, dtype=np.float64)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(f"{v:.10g}" for v in (K[0], K[1], K[2] + COLMAP_PIXEL_OFFSET, K[3] + COLMAP_PIXEL_OFFSET))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = config.num_threads
    extraction.max_image_size = config.max_image_size
    extraction.sift.max_num_features = config.max_num_features
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = config.overlap
    mapper = pycolmap.IncrementalPipelineOptions()
    mapper.num_threads = config.num_threads
    mapper.min_model_size = config.min_model_size
    mapper.random_seed = config.random_seed
    mapper.ba_refine_focal_length = False
    mapper.ba_refine_principal_point = False
    mapper.ba_refine_extra_params = False

    def cpu() -> float:
        u = resource.getrusage(resource.RUSAGE_SELF)
        return u.ru_utime + u.ru_stime

    seconds: dict[str, float] = {}
    saved_level = pycolmap.logging.minloglevel
    if not logger.isEnabledFor(logging.DEBUG):  # COLMAP's own log: one line per image and step
        pycolmap.logging.minloglevel = int(pycolmap.logging.Level.WARNING.value)
    try:
        cpu0 = cpu()
        models = _sfm_stages(pycolmap, db, image_dir, image_names, reader, extraction, pairing, mapper, work, seconds)
        cpu_s = cpu() - cpu0
    finally:
        pycolmap.logging.minloglevel = saved_level
    best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
    logger.info("COLMAP SfM: %d model(s), largest %s registered images, %.1f s", len(models),
                None if best is None else best.num_reg_images(), seconds["total"])
    return SfmResult(None if best is None else model_from_reconstruction(best), len(models), seconds, cpu_s)


def _sfm_stages(pycolmap, db, image_dir, image_names, reader, extraction, pairing, mapper, work, seconds):
    t0 = time.perf_counter()
    pycolmap.extract_features(db, image_dir, image_names=image_names or [], camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    seconds["features"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)
    seconds["matching"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    models = pycolmap.incremental_mapping(db, image_dir, work / "sparse", options=mapper)
    seconds["mapping"] = time.perf_counter() - t0
    seconds["total"] = sum(seconds.values())
    return models
