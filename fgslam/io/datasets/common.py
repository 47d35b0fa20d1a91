"""Shared machinery of the dataset loaders: configuration, the lazy ``Dataset`` base class, time and
pose helpers (the loaders read their files with :mod:`.files`).

A ``Dataset`` is a lazy sequence of :class:`~fgslam.io.frame.Frame`: opening it reads only the
index files (lists of frames, timestamps, calibration, IMU table) and one image to check the
calibration against the image size; image, depth and pose files are read when a frame is requested,
and nothing per frame is cached, so memory does not grow while iterating.

Corrupt frames: ``dataset[i]`` raises :class:`~fgslam.io.frame.FrameReadError` for a frame whose
files cannot be read or have the wrong size; iterating a dataset skips such frames with a warning
and records ``(index, reason)`` in ``dataset.skipped_frames`` (the next frame's IMU block then
starts at the last frame actually yielded). More than ``DatasetConfig.max_skipped_fraction`` of the
frames skipped raises :class:`~fgslam.core.errors.DataError`.

Depth: a frame whose depth map has no valid pixel is yielded as it is; at the end of an iteration
a depth stream without a single valid pixel is reported once with a warning (``RGB-D: no valid
depth in N frames``), a stream with some empty maps with an info line.

Ground truth: ``dataset.groundtruth`` is a :class:`~fgslam.io.trajectory.Trajectory` of the output
left camera (after rectification, ``T_WC = T_W_Craw @ T_Craw_Cout``) at the timestamps of the
dataset's frames that have ground truth; time-stamped ground truth is interpolated (linear position,
slerp rotation) between samples at most ``gt_max_gap`` apart and never extrapolated beyond
``gt_snap_dt``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, NamedTuple, Optional

import numpy as np
from numpy.typing import ArrayLike

from ...core.config import MAX_FRAMES, MAX_IMAGE_SIDE, MAX_SCALAR, check_ranges, ranged
from ...core.errors import ConfigError, DataError
from ..calibration import Calibration
from ..frame import Frame, FrameReadError, FrameSizeError, ImuSamples
from ..trajectory import Trajectory
from .files import to_grey_and_rgb

if TYPE_CHECKING:
    from ..camera import Camera

logger = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000  # nanoseconds per second (EuRoC timestamps are integer nanoseconds)
#: the most (s) two timestamps of one frame differ once handed through a frontend or a trajectory file: float64
#: holds an epoch time (~1.7e9 s) to 2.4e-7 s, and a camera's frames are milliseconds apart (an absolute bound:
#: one relative to the stamp would span minutes of an epoch-time sequence)
SAME_FRAME_DT = 1e-6
#: frames tried, spread over the selection, before a dataset whose first frame is unreadable is said to
#: have no readable image (:meth:`Dataset.check_readable`)
READABLE_PROBE_FRAMES = 5
#: how a message tells the user to give a calibration YAML (the override of ``fgslam run``, ``localize`` and ``info``)
CALIBRATION_OVERRIDE = "-o dataset.calibration_file=PATH"


@dataclass
class BagTopicsConfig:
    """Which bag topic serves which role (None: automatic when there is exactly one candidate)."""

    left: Optional[str] = None  # left / mono colour or grey images
    right: Optional[str] = None  # right images of a stereo pair
    depth: Optional[str] = None  # depth images registered to the left camera
    imu: Optional[str] = None  # sensor_msgs/Imu
    left_info: Optional[str] = None  # CameraInfo of the left camera (None: <namespace of left>/camera_info)
    right_info: Optional[str] = None  # CameraInfo of the right camera


@dataclass
class DatasetConfig:
    """How a dataset is opened (all loaders). Loadable with ``fgslam.core.config.load_config``."""

    start: int = ranged(0, ge=0, le=MAX_FRAMES)  # first raw frame index used
    end: Optional[int] = ranged(None, ge=1, le=MAX_FRAMES)  # one past the last raw frame index used (None: to the end)
    stride: int = ranged(1, ge=1, le=MAX_FRAMES)  # use every stride-th raw frame
    rectify_stereo: bool = True  # rectify stereo pairs (else undistort each camera on its own)
    undistort_alpha: float = ranged(0.0, ge=0, le=1)  # 0: output has only valid pixels; 1: keeps all source pixels
    resize_scale: float = ranged(1.0, ge=0.05, le=4)  # scale factor of the output image (ignored when resize_width/height set)
    resize_width: int = ranged(0, ge=0, le=MAX_IMAGE_SIDE)  # output width before cropping (0: from resize_height/aspect or scale)
    resize_height: int = ranged(0, ge=0, le=MAX_IMAGE_SIDE)  # output height before cropping (0: from resize_width/aspect or scale)
    max_width: int = ranged(0, ge=0, le=MAX_IMAGE_SIDE)  # wider outputs are scaled down to this width, aspect kept (0: off)
    crop_multiple: int = ranged(8, ge=0, le=MAX_IMAGE_SIDE)  # centre-crop output to multiples of this (network frontends need 8); 0 or 1: off
    min_image_side: int = ranged(32, ge=8, le=MAX_IMAGE_SIDE)  # a SLAM run needs output images (resized, cropped) at least this many px a side
    load_rgb: bool = True  # also return the RGB image of colour sources
    load_right: bool = True  # read the right image of stereo sources
    load_depth: bool = True  # read depth of RGB-D sources
    load_imu: bool = True  # attach IMU samples
    calibration_file: Optional[str] = None  # calibration YAML overriding the source's (folder, video, TUM, ROS bag, camera; the other loaders refuse it)
    groundtruth_file: Optional[str] = None  # ground-truth file overriding the default location
    tum_camera: Optional[str] = None  # fr1|fr2|fr3 for TUM RGB-D (None: from the folder name, else fr1)
    sequence: Optional[str] = None  # 7-Scenes sequence folder (None: the first seq-NN)
    association_max_dt: float = ranged(0.02, gt=0, le=MAX_SCALAR)  # s, TUM rgb/depth association (the benchmark's associate.py)
    stereo_max_dt: float = ranged(0.001, gt=0, le=MAX_SCALAR)  # s, EuRoC cam0/cam1/depth0 timestamp matching
    gt_max_gap: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # s, largest ground-truth sample gap a frame pose is interpolated across
    gt_snap_dt: float = ranged(0.001, gt=0, le=MAX_SCALAR)  # s, a frame this close outside the ground-truth time range snaps to its end
    max_skipped_fraction: float = ranged(0.1, ge=0, lt=1)  # iteration fails when more corrupt frames than this fraction
    default_rate_hz: float = ranged(30.0, gt=0, le=MAX_SCALAR)  # frame rate of image folders without timestamps.txt or rate_hz
    topics: BagTopicsConfig = field(default_factory=BagTopicsConfig)  # ROS bags: topic per role
    T_BC: Optional[list[float]] = ranged(None, ge=-MAX_SCALAR, le=MAX_SCALAR)  # ROS bags: camera-to-IMU transform, 16 numbers row-major (else the calibration YAML's)

    def validate(self) -> None:
        check_ranges(self)
        if self.end is not None and self.end <= self.start:
            raise ConfigError(f"end ({self.end}) must be > start ({self.start})")
        if self.T_BC is not None and len(self.T_BC) != 16:
            raise ConfigError(f"T_BC must have 16 numbers (4x4 row-major camera-to-IMU transform), got {len(self.T_BC)}")
        if self.tum_camera is not None and self.tum_camera not in ("fr1", "fr2", "fr3"):
            raise ConfigError(f"tum_camera must be fr1, fr2 or fr3, got {self.tum_camera!r}")

    def warn_unused_bag_keys(self, fmt: str, bag_format: str = "rosbag") -> list[str]:
        """Log a warning naming ``T_BC`` / ``topics`` when they are set for a loader other than the
        ROS bag one (they do nothing there); returns the keys named."""
        keys = ([] if self.T_BC is None else ["dataset.T_BC"]) + (
            [] if self.topics == BagTopicsConfig() else ["dataset.topics"])
        if keys and fmt != bag_format:
            logger.warning("%s only apply to ROS bags: ignored for the %s loader (calibration, topics: "
                           "its own files)", " and ".join(keys), fmt)
            return keys
        return []

    def resize_keys(self) -> list[str]:
        """The keys that set the output size, with their values (``key=value`` each)."""
        cap = [f"dataset.max_width={self.max_width}"] if self.max_width else []
        if self.resize_width or self.resize_height:
            return [f"dataset.resize_width={self.resize_width}", f"dataset.resize_height={self.resize_height}", *cap]
        return [f"dataset.resize_scale={self.resize_scale:g}", *cap]

    def resize_text(self) -> str:
        """The keys that set the output size, with their values (for error messages)."""
        return ", ".join(self.resize_keys())

    def output_size(self, width: int, height: int) -> tuple[int, int]:
        """Output size before cropping for a raw ``width x height`` image (at most ``max_width`` wide)."""
        w, h = self._resized(width, height)
        if self.max_width and w > self.max_width:
            return self.max_width, max(1, round(h * self.max_width / w))
        return w, h

    def _resized(self, width: int, height: int) -> tuple[int, int]:
        if self.resize_width and self.resize_height:
            return self.resize_width, self.resize_height
        if self.resize_width:
            return self.resize_width, max(1, round(height * self.resize_width / width))
        if self.resize_height:
            return max(1, round(width * self.resize_height / height)), self.resize_height
        return max(1, round(width * self.resize_scale)), max(1, round(height * self.resize_scale))


class RawFrame(NamedTuple):
    """What a loader reads for one raw frame, before any geometry is applied."""

    image: np.ndarray  # uint8 grey (H, W) or BGR (H, W, 3) as OpenCV reads it
    path: Optional[Path]
    right: Optional[np.ndarray] = None  # grey uint8
    depth: Optional[np.ndarray] = None  # float32 metres, any value (sanitised by the base class)


# ---------------------------------------------------------------------------- helpers
def ns_to_seconds(ns: np.ndarray) -> np.ndarray:
    """Integer nanoseconds ``(N,)`` int64 -> float64 seconds without losing the sub-second part."""
    ns = np.asarray(ns, dtype=np.int64)
    return (ns // NS_PER_S).astype(np.float64) + (ns % NS_PER_S) / NS_PER_S


def same_frame_stamps(stamps: ArrayLike, wanted: ArrayLike) -> np.ndarray:
    """For each of ``stamps`` (seconds): whether one of ``wanted`` is the same frame's timestamp, within
    :data:`SAME_FRAME_DT` (a frame's time handed back by a frontend, or read from a trajectory file); a
    boolean array."""
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    targets = np.sort(np.asarray(wanted, dtype=np.float64).reshape(-1))
    if targets.size == 0 or stamps.size == 0:
        return np.zeros(stamps.shape[0], dtype=bool)
    above = np.clip(np.searchsorted(targets, stamps), 0, targets.size - 1)
    below = np.clip(above - 1, 0, targets.size - 1)
    nearest = np.minimum(np.abs(targets[below] - stamps), np.abs(targets[above] - stamps))
    return nearest <= SAME_FRAME_DT


def interpolate_poses(
    times: np.ndarray, gt_times: np.ndarray, gt_T: np.ndarray, max_gap: float, snap_dt: float
) -> np.ndarray:
    """Poses ``(N, 4, 4)`` at ``times`` from time-stamped poses; NaN where not available.

    Linear in position, slerp in rotation between the bracketing samples when they are at most
    ``max_gap`` apart; times up to ``snap_dt`` outside ``[gt_times[0], gt_times[-1]]`` take the end
    sample; anything else gets NaN (never extrapolated).
    """
    from scipy.spatial.transform import Rotation  # deferred: scipy

    times = np.asarray(times, dtype=np.float64)
    out = np.full((times.shape[0], 4, 4), np.nan)
    if gt_times.shape[0] == 0:
        return out
    t = times.copy()
    lo_snap = (t < gt_times[0]) & (gt_times[0] - t <= snap_dt)
    hi_snap = (t > gt_times[-1]) & (t - gt_times[-1] <= snap_dt)
    t[lo_snap], t[hi_snap] = gt_times[0], gt_times[-1]
    inside = (t >= gt_times[0]) & (t <= gt_times[-1])
    if gt_times.shape[0] == 1:
        out[inside] = gt_T[0]
        return out
    k = np.clip(np.searchsorted(gt_times, t, side="right") - 1, 0, gt_times.shape[0] - 2)
    t0, t1 = gt_times[k], gt_times[k + 1]
    exact0, exact1 = t == t0, t == t1
    ok = inside & ((t1 - t0 <= max_gap) | exact0 | exact1)
    alpha = np.where(exact1, 1.0, np.where(exact0, 0.0, (t - t0) / np.maximum(t1 - t0, 1e-300)))
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return out
    a = alpha[idx]
    T0, T1 = gt_T[k[idx]], gt_T[k[idx] + 1]
    R0, R1 = T0[:, :3, :3], T1[:, :3, :3]
    dR = Rotation.from_matrix(np.einsum("nji,njk->nik", R0, R1)).as_rotvec()
    R = R0 @ Rotation.from_rotvec(dR * a[:, None]).as_matrix()
    out[idx] = np.eye(4)
    out[idx, :3, :3] = R
    out[idx, :3, 3] = (1 - a)[:, None] * T0[:, :3, 3] + a[:, None] * T1[:, :3, 3]
    return out


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """Closest rotation matrices (Frobenius norm, SVD) to ``(..., 3, 3)`` near-rotations."""
    U, _, Vt = np.linalg.svd(R)
    D = np.ones(R.shape[:-1])
    D[..., -1] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def make_undistorter(calib: Calibration, cfg: DatasetConfig, source: str, rectification: Optional[tuple] = None) -> Any:
    """The :class:`~fgslam.io.undistort.Undistorter` of raw images of ``calib`` (validated) with the dataset
    keys of ``cfg`` (undistortion, stereo rectification, resizing, cropping): every loader's, and
    ``fgslam.Slam``'s for a script's images. ConfigError when the output images would exceed
    :data:`MAX_IMAGE_SIDE` pixels a side (checked before the remap tables, 8 bytes per output pixel, are built)."""
    out_w, out_h = cfg.output_size(calib.width, calib.height)
    if max(out_w, out_h) > MAX_IMAGE_SIDE:
        raise ConfigError(
            f"{cfg.resize_text()} gives {out_w}x{out_h} images from {calib.width}x{calib.height} "
            f"({source}); at most {MAX_IMAGE_SIDE} pixels a side are supported: "
            f"set dataset.resize_width or dataset.resize_scale to make them smaller")
    from ..undistort import Undistorter  # deferred: OpenCV (importing the loaders' configs stays light)

    return Undistorter(calib, rectify=cfg.rectify_stereo, alpha=cfg.undistort_alpha, out_size=(out_w, out_h),
                       crop_multiple=cfg.crop_multiple, source=source, rectification=rectification)


def clean_depth(depth: np.ndarray) -> np.ndarray:
    """A depth map as float32 metres with every non-finite, zero or negative value set to 0 (no depth)."""
    depth = np.asarray(depth, dtype=np.float32)
    return np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0))


# ---------------------------------------------------------------------------- base class
class Dataset:
    """Lazy sequence of frames (``len``, ``[i]``, iteration); see the module docstring.

    Subclasses set the attributes below, implement ``_read_raw`` (and ``_raw_groundtruth`` when the
    source has ground truth), and call ``_setup()`` at the end of their ``__init__``.

    Attributes:
        root: the path opened.
        format: loader name (``tum``, ``euroc``, ...).
        name: sequence name (folder or file name).
        config: the DatasetConfig used.
        raw_calibration: calibration of the raw images.
        calibration: calibration of the output images (undistorted, rectified, resized, cropped).
        skipped_frames: ``[(index, reason), ...]`` of the frames skipped while iterating.
        imu: all IMU samples of the source (None without IMU).
    """

    format: str = ""

    def __init__(self, root: Path, config: Optional[DatasetConfig] = None) -> None:
        config = DatasetConfig() if config is None else config
        config.validate()
        self.root = Path(root)
        self.config = config
        self.name = self.root.name
        self.skipped_frames: list[tuple[int, str]] = []
        self.raw_timestamps = np.zeros(0)
        self.raw_calibration: Optional[Calibration] = None
        self.calibration_source = str(self.root)
        self.imu: Optional[ImuSamples] = None
        self.imu_noise: Optional[dict[str, float]] = None  # noise densities of the IMU (EuRoC sensor.yaml keys) when given
        self._has_stereo = False
        self._has_depth = False
        self.stereo_rectification: Optional[tuple] = None  # (R1, R2, P1, P2) as recorded (ROS camera_info)
        self._gt_cache: Optional[np.ndarray] = None
        self.first_frame_error: Optional[str] = None  # why the first frame could not be read at open (None: it could)

    # ------------------------------------------------------------ subclass interface
    def _read_raw(self, raw_index: int) -> RawFrame:
        raise NotImplementedError

    def _raw_groundtruth(self) -> Optional[np.ndarray]:
        """``(N_raw, 4, 4)`` raw-left-camera camera-to-world poses per raw frame, NaN where absent."""
        return None

    def _setup(self) -> None:
        """Select frames, build the undistortion maps, check the first image against the calibration."""
        n_raw = self.raw_timestamps.shape[0]
        if n_raw == 0:
            raise DataError(f"{self.root}: empty sequence (no frames)")
        cfg = self.config
        self._indices = np.arange(n_raw)[cfg.start : cfg.end : cfg.stride]
        if self._indices.size == 0:
            raise DataError(f"{self.root}: empty selection: start={cfg.start}, end={cfg.end} of {n_raw} frames")
        calib = self.raw_calibration.validate(self.calibration_source)
        self._undistorter = make_undistorter(calib, cfg, self.calibration_source, self.stereo_rectification)
        self.calibration = self._undistorter.calibration
        try:
            first = self._read_raw(int(self._indices[0]))
        except FrameReadError as exc:  # said when read (a skipped frame), or by check_readable (fgslam info)
            self.first_frame_error = str(exc)
            logger.debug("first frame of %s is unreadable (%s); image size not checked at open", self.root, exc)
        else:
            h, w = first.image.shape[:2]
            if (w, h) != (calib.width, calib.height):
                raise DataError(
                    f"{self.calibration_source}: calibration is for {calib.width}x{calib.height} images but "
                    f"{first.path or self.root} is {w}x{h}"
                )
        if self.imu is not None and len(self.imu) == 0:
            self.imu = None

    def check_readable(self) -> None:
        """DataError when no image can be read: the first frame failed at open and so do up to
        :data:`READABLE_PROBE_FRAMES` frames spread over the selection (nothing is read when the first
        frame could be); a warning when only the first frame failed (its size was not checked at open)."""
        if self.first_frame_error is None:
            return
        n = len(self)
        probes = np.unique(np.linspace(0, n - 1, min(n, READABLE_PROBE_FRAMES)).round().astype(np.int64))
        for position in probes[1:]:
            try:
                self._read_raw(int(self._indices[position]))
            except FrameReadError:
                continue
            logger.warning("first frame of %s is unreadable (%s); image size not checked at open", self.root,
                           self.first_frame_error)
            return
        tried = "its only frame" if n == 1 else f"none of the {probes.size} frames tried (of {n}, first to last)"
        raise DataError(f"{self.root}: the images cannot be read ({tried}; the first: {self.first_frame_error})")

    # ------------------------------------------------------------ properties
    @property
    def timestamps(self) -> np.ndarray:
        """Timestamps (s) of the dataset's frames."""
        return self.raw_timestamps[self._indices]

    @property
    def camera(self) -> "Camera":
        """The camera of the frames this dataset yields (undistorted, rectified, resized: ``prepared``), for
        :class:`fgslam.Slam`."""
        from ..camera import Camera

        return Camera.of_frames(self.calibration)

    @property
    def rate(self) -> float:
        """Frame rate (Hz) of the dataset's frames (after stride): 1 / median interval (0 for one frame)."""
        t = self.timestamps
        if t.shape[0] < 2:
            return 0.0
        return float(1.0 / np.median(np.diff(t)))

    @property
    def has_stereo(self) -> bool:
        return self._has_stereo and self.config.load_right

    @property
    def has_depth(self) -> bool:
        return self._has_depth and self.config.load_depth

    @property
    def has_imu(self) -> bool:
        return self.imu is not None and self.config.load_imu

    @property
    def imu_count(self) -> int:
        return 0 if self.imu is None else len(self.imu)

    def _gt_out(self) -> Optional[np.ndarray]:
        if self._gt_cache is None:
            raw = self._raw_groundtruth()
            if raw is None:
                return None
            self._gt_cache = raw @ self._undistorter.T_C_Cout
        return self._gt_cache

    @property
    def groundtruth(self) -> Optional[Trajectory]:
        """Ground truth of the output left camera at the frames that have it (None: no ground truth)."""
        gt = self._gt_out()
        if gt is None:
            return None
        sel = gt[self._indices]
        ok = np.all(np.isfinite(sel), axis=(1, 2))
        if not np.any(ok):
            return None
        return Trajectory(self.timestamps[ok], sel[ok])

    @property
    def has_groundtruth(self) -> bool:
        return self.groundtruth is not None

    # ------------------------------------------------------------ sequence protocol
    def __len__(self) -> int:
        return int(self._indices.shape[0])

    def __getitem__(self, index: int) -> Frame:
        n = len(self)
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"dataset indices must be integers, got {type(index).__name__}")
        if index < 0:
            index += n
        if not 0 <= index < n:
            raise IndexError(f"frame index {index} out of range for {n} frames")
        prev_t = None if index == 0 else float(self.raw_timestamps[self._indices[index - 1]])
        return self._frame(int(index), prev_t)

    def __iter__(self) -> Iterator[Frame]:
        prev_t = None
        n = len(self)
        max_skipped = int(self.config.max_skipped_fraction * n)
        recorded = {i for i, _ in self.skipped_frames}
        skipped_now = wrong_size = 0
        depth_frames = empty_depth = 0
        for i in range(n):
            try:
                frame = self._frame(i, prev_t)
            except FrameReadError as exc:
                skipped_now += 1
                wrong_size += isinstance(exc, FrameSizeError)
                if i not in recorded:
                    self.skipped_frames.append((i, str(exc)))
                    recorded.add(i)
                logger.warning("skipping frame %d: %s", i, exc)
                if skipped_now > max_skipped:
                    kinds = [f"{k} {what}" for k, what in ((skipped_now - wrong_size, "unreadable"),
                                                           (wrong_size, "of the wrong size")) if k]
                    raise DataError(
                        f"{self.root}: {skipped_now} of the first {i + 1} frames (of {n}) skipped: "
                        f"{', '.join(kinds)}; more than allowed (max_skipped_fraction="
                        f"{self.config.max_skipped_fraction}: at most {max_skipped} of {n}); last: {exc}"
                    ) from exc
                continue
            prev_t = frame.timestamp
            if frame.depth is not None:
                depth_frames += 1
                empty_depth += not np.any(frame.depth)
            yield frame
        self._report_empty_depth(depth_frames, empty_depth)

    def _report_empty_depth(self, depth_frames: int, empty_depth: int) -> None:
        """One log line at the end of an iteration when depth maps had no valid pixel."""
        if empty_depth == 0:
            return
        if empty_depth == depth_frames:
            logger.warning(
                "RGB-D: no valid depth in %d frames of %s (every depth map is 0, NaN, infinite or negative "
                "everywhere): check the depth files and their scale", depth_frames, self.root,
            )
        else:
            logger.info("RGB-D: no valid depth in %d of %d frames of %s", empty_depth, depth_frames, self.root)

    # ------------------------------------------------------------ frame assembly
    def _frame(self, index: int, prev_t: Optional[float]) -> Frame:
        cfg = self.config
        raw_index = int(self._indices[index])
        raw = self._read_raw(raw_index)
        calib = self.raw_calibration
        where = raw.path or f"{self.root} frame {raw_index}"
        h, w = raw.image.shape[:2]
        if (w, h) != (calib.width, calib.height):
            raise FrameSizeError(f"{where}: frame {index} is {w}x{h}, expected {calib.width}x{calib.height} "
                                 "(the calibration's size)")
        grey, rgb = to_grey_and_rgb(raw.image, cfg.load_rgb, raw.path)
        und = self._undistorter
        frame = Frame(
            index=index,
            source_index=raw_index,
            timestamp=float(self.raw_timestamps[raw_index]),
            image=und.left(grey),
            calibration=self.calibration,
            rgb=None if rgb is None else und.left(rgb),
            path=raw.path,
        )
        if raw.right is not None and self.has_stereo:
            rh, rw = raw.right.shape[:2]
            if (rw, rh) != (calib.right.width, calib.right.height):
                raise FrameSizeError(f"{where}: the right image of frame {index} is {rw}x{rh}, expected "
                                     f"{calib.right.width}x{calib.right.height} (the calibration's size)")
            grey_right, rgb_right = to_grey_and_rgb(raw.right, cfg.load_rgb, raw.path)
            frame.image_right = und.right(grey_right)
            frame.rgb_right = None if rgb_right is None else und.right(rgb_right)
        if raw.depth is not None and self.has_depth:
            dh, dw = raw.depth.shape[:2]
            if (dw, dh) != (calib.width, calib.height) or raw.depth.ndim != 2:
                shape = "x".join(str(v) for v in raw.depth.shape[1::-1] + raw.depth.shape[2:])
                raise FrameSizeError(f"{where}: the depth map of frame {index} is {shape}, expected "
                                     f"{calib.width}x{calib.height} (the calibration's size, one channel)")
            frame.depth = und.depth(clean_depth(raw.depth))
        if self.has_imu:
            frame.imu = self._imu_between(prev_t, frame.timestamp)
        gt = self._gt_out()
        if gt is not None and np.all(np.isfinite(gt[raw_index])):
            frame.T_WC_gt = gt[raw_index].copy()
        return frame

    def _imu_between(self, t_prev: Optional[float], t: float) -> ImuSamples:
        imu = self.imu
        hi = int(np.searchsorted(imu.timestamps, t, side="right"))
        lo = hi if t_prev is None else int(np.searchsorted(imu.timestamps, t_prev, side="right"))
        return ImuSamples(imu.timestamps[lo:hi].copy(), imu.gyro[lo:hi].copy(), imu.accel[lo:hi].copy())

    def _imu_in_span(self) -> int:
        """IMU samples with ``t_first < t <= t_last`` of the dataset's frames (what frames carry)."""
        if not self.has_imu:
            return 0
        t = self.timestamps
        return len(self._imu_between(float(t[0]), float(t[-1])))

    def summary(self) -> dict:
        """Plain-type description (what ``fgslam info`` prints)."""
        calib = self.calibration
        gt = self.groundtruth
        out = {
            "path": str(self.root),
            "format": self.format,
            "name": self.name,
            "frames": len(self),
            "resolution": [calib.width, calib.height],
            "raw_resolution": [self.raw_calibration.width, self.raw_calibration.height],
            "rate_hz": round(self.rate, 6),
            "stereo": self.has_stereo,
            "depth": self.has_depth,
            "imu": self.has_imu,
            "imu_samples": self.imu_count,
            "imu_samples_in_span": self._imu_in_span(),
            "groundtruth": gt is not None,
            "groundtruth_poses": 0 if gt is None else len(gt),
            "intrinsics": [round(float(v), 6) for v in calib.K],
            "raw_distortion_model": self.raw_calibration.distortion_model,
        }
        if calib.right is not None:
            out["baseline_m"] = round(calib.baseline, 6)
        return out

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.root} frames={len(self)}>"
