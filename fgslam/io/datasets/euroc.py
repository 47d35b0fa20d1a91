"""EuRoC MAV loader (ASL folder layout), including the synthetic ``depth0`` extension.

Layout (``ROOT`` or ``ROOT/mav0`` may be given)::

    mav0/cam0/data.csv, cam0/data/<ts_ns>.png, cam0/sensor.yaml     (required)
    mav0/cam1/...                                                   (optional: stereo)
    mav0/imu0/data.csv, imu0/sensor.yaml                            (optional: IMU, 200 Hz)
    mav0/depth0/data.csv, depth0/data/<ts_ns>.png, depth0/sensor.yaml (synthetic only: 16-bit
        z-depth of cam0 in units of 1/depth_scale m (default 1000), 0 = invalid)
    mav0/state_groundtruth_estimate0/data.csv  or  ROOT/groundtruth.txt  (optional ground truth)

Frames are the cam0 rows; cam1 and depth0 rows are matched to them by timestamp (within
``stereo_max_dt``); cam1/depth0 rows without a cam0 partner are ignored, a cam0 row without a
partner is an error (streams of different lengths).  Calibration: ``T_BC = T_BS(imu0)^-1 T_BS(cam0)``
(body = IMU frame), ``T_CLCR = T_BS(cam0)^-1 T_BS(cam1)``.  Ground truth is the body (IMU) pose
``T_WB``; the camera pose is ``T_WC = T_WB @ T_BC``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional

import numpy as np

from ...core.errors import DataError
from ..calibration import Calibration, read_yaml_file
from ..frame import ImuSamples
from ..trajectory import read_trajectory
from .common import Dataset, DatasetConfig, RawFrame, interpolate_poses, ns_to_seconds
from .files import check_increasing, read_image, read_text_lines, require_dir, require_file

logger = logging.getLogger(__name__)

DISTORTION_NAMES = {"radial-tangential": "radtan", "radtan": "radtan", "equidistant": "equidistant",
                    "fisheye": "equidistant", "none": "none"}
DEFAULT_DEPTH_SCALE = 1000.0  # units per metre of the synthetic depth0 PNGs (TEAM.md layout contract)


def mav0_dir(path: Path) -> Optional[Path]:
    """The ``mav0`` folder of an EuRoC sequence at ``path`` (ROOT or ROOT/mav0), else None."""
    for cand in (path / "mav0", path):
        if (cand / "cam0").is_dir():
            return cand
    return None


def _read_stream(csv: Path) -> tuple[np.ndarray, list[str]]:
    """``(timestamps ns int64, file names)`` of a cam/depth ``data.csv``."""
    stamps, names, lines = [], [], []
    for lineno, line in read_text_lines(require_file(csv, "stream index")):
        parts = [p.strip() for p in line.split(",")]
        if len(parts) < 2:
            raise DataError(f"{csv}:{lineno}: expected 'timestamp,filename', got {line!r}")
        try:
            stamps.append(int(parts[0]))
        except ValueError as exc:
            raise DataError(f"{csv}:{lineno}: bad timestamp {parts[0]!r}") from exc
        names.append(parts[1])
        lines.append(lineno)
    ts = np.asarray(stamps, dtype=np.int64)
    check_increasing(csv, ts, lines)
    return ts, names


def _transform(data: dict, key: str, source: Path) -> np.ndarray:
    block = data.get(key)
    if not isinstance(block, dict) or "data" not in block:
        raise DataError(f"{source}: missing {key} {{rows, cols, data}}")
    T = np.asarray(block["data"], dtype=np.float64)
    if T.size != 16:
        raise DataError(f"{source}: {key} must have 16 values, got {T.size}")
    return T.reshape(4, 4)


def _camera(sensor: Path) -> tuple[Calibration, np.ndarray]:
    """Calibration (no extrinsics) and ``T_BS`` of one ``camN/sensor.yaml``."""
    data = read_yaml_file(require_file(sensor, "camera sensor.yaml"))
    for key in ("resolution", "intrinsics"):
        if key not in data:
            raise DataError(f"{sensor}: missing key {key!r}")
    if data.get("camera_model", "pinhole") != "pinhole":
        raise DataError(f"{sensor}: camera_model {data['camera_model']!r} not supported (pinhole only)")
    model = DISTORTION_NAMES.get(str(data.get("distortion_model", "none")))
    if model is None:
        raise DataError(f"{sensor}: unknown distortion_model {data['distortion_model']!r}")
    try:
        width, height = (int(v) for v in data["resolution"])
        calib = Calibration(width, height, np.asarray(data["intrinsics"], dtype=np.float64), model,
                            np.asarray(data.get("distortion_coefficients", []) or [], dtype=np.float64))
    except (TypeError, ValueError) as exc:
        raise DataError(f"{sensor}: malformed camera values: {exc}") from exc
    return calib.validate(str(sensor)), _transform(data, "T_BS", sensor)


def _match(ts0: np.ndarray, ts1: np.ndarray, max_dt_ns: int, what: str, csv0: Path, csv1: Path) -> np.ndarray:
    """Index into ts1 of the partner of each ts0 entry; DataError when a cam0 entry has none."""
    if ts1.size == 0:
        best, ok = np.zeros(ts0.size, dtype=np.int64), np.zeros(ts0.size, dtype=bool)
    else:
        j = np.clip(np.searchsorted(ts1, ts0), 0, ts1.size - 1)
        left = np.clip(j - 1, 0, ts1.size - 1)
        best = np.where(np.abs(ts1[left] - ts0) < np.abs(ts1[j] - ts0), left, j)
        ok = np.abs(ts1[best] - ts0) <= max_dt_ns
    if not np.all(ok):
        raise DataError(
            f"{csv0} has {ts0.size} frames but {csv1} ({what}) has {ts1.size}; "
            f"{int((~ok).sum())} cam0 frames have no {what} partner (streams of different lengths)"
        )
    if ts1.size > ts0.size:
        logger.info("%s: %d %s entries without a cam0 frame ignored", csv1, ts1.size - ts0.size, what)
    return best


class EurocDataset(Dataset):
    """EuRoC MAV sequence (see the module docstring)."""

    format = "euroc"

    def __init__(self, root: Path, config: Optional[DatasetConfig] = None) -> None:
        super().__init__(root, config)
        config = self.config
        mav = mav0_dir(self.root)
        if mav is None:
            raise DataError(f"{self.root}: missing EuRoC folder mav0/cam0")
        self.mav = mav
        if self.root.name == "mav0":
            self.name = self.root.parent.name
        cam0 = require_dir(mav / "cam0", "cam0")
        ts0, names0 = _read_stream(cam0 / "data.csv")
        self._left = [cam0 / "data" / n for n in names0]
        calib, T_BS0 = _camera(cam0 / "sensor.yaml")
        self.calibration_source = str(cam0 / "sensor.yaml")

        T_BS_imu = np.eye(4)
        imu_dir = mav / "imu0"
        if (imu_dir / "data.csv").is_file():
            if (imu_dir / "sensor.yaml").is_file():
                imu_yaml = read_yaml_file(imu_dir / "sensor.yaml")
                T_BS_imu = _transform(imu_yaml, "T_BS", imu_dir / "sensor.yaml")
                self.imu_noise = _imu_noise(imu_yaml)
            if config.load_imu:
                self.imu = _read_imu(imu_dir / "data.csv")
        calib.T_BC = np.linalg.inv(T_BS_imu) @ T_BS0

        max_dt_ns = int(round(config.stereo_max_dt * 1e9))
        self._right: Optional[list[Path]] = None
        cam1 = mav / "cam1"
        if (cam1 / "data.csv").is_file():
            ts1, names1 = _read_stream(cam1 / "data.csv")
            right, T_BS1 = _camera(cam1 / "sensor.yaml")
            j = _match(ts0, ts1, max_dt_ns, "cam1", cam0 / "data.csv", cam1 / "data.csv")
            self._right = [cam1 / "data" / names1[k] for k in j]
            calib.right = right
            calib.T_CLCR = np.linalg.inv(T_BS0) @ T_BS1
            self._has_stereo = True

        self._depth: Optional[list[Path]] = None
        self.depth_scale = DEFAULT_DEPTH_SCALE
        depth0 = mav / "depth0"
        if (depth0 / "data.csv").is_file():
            tsd, namesd = _read_stream(depth0 / "data.csv")
            j = _match(ts0, tsd, max_dt_ns, "depth0", cam0 / "data.csv", depth0 / "data.csv")
            self._depth = [depth0 / "data" / namesd[k] for k in j]
            if (depth0 / "sensor.yaml").is_file():
                scale = read_yaml_file(depth0 / "sensor.yaml").get("depth_scale", DEFAULT_DEPTH_SCALE)
                if not isinstance(scale, (int, float)) or scale <= 0:
                    raise DataError(f"{depth0 / 'sensor.yaml'}: depth_scale must be a positive number, got {scale!r}")
                self.depth_scale = float(scale)
            self._has_depth = True

        self.raw_calibration = calib
        self.raw_timestamps = ns_to_seconds(ts0)
        self._gt_path = self._find_groundtruth()
        self._setup()

    def _find_groundtruth(self) -> Optional[Path]:
        if self.config.groundtruth_file:
            return require_file(Path(self.config.groundtruth_file), "ground-truth")
        for cand in (
            self.mav / "state_groundtruth_estimate0" / "data.csv",
            self.mav.parent / "groundtruth.txt",
            self.mav / "groundtruth.txt",
        ):
            if cand.is_file():
                return cand
        return None

    def _raw_groundtruth(self) -> Optional[np.ndarray]:
        return body_groundtruth_at_frames(self._gt_path, self.raw_calibration.T_BC, self.raw_timestamps, self.config)

    def _read_raw(self, raw_index: int) -> RawFrame:
        path = self._left[raw_index]
        image = read_image(path)
        right = depth = None
        if self._right is not None and self.config.load_right:
            right = read_image(self._right[raw_index])
        if self._depth is not None and self.config.load_depth:
            d = read_image(self._depth[raw_index])
            depth = d.astype(np.float32) / np.float32(self.depth_scale)
        return RawFrame(image, path, right, depth)


def body_groundtruth_at_frames(gt_path: Optional[Path], T_BC: np.ndarray, timestamps: np.ndarray,
                               config: DatasetConfig) -> Optional[np.ndarray]:
    """Camera poses ``T_WC = T_WB T_BC`` at the frames' ``timestamps`` from a ground truth of the body
    (IMU) in the EuRoC csv layout (EuRoC's state estimate, TUM-VI's mocap), interpolated within
    ``config.gt_max_gap``; None without a file."""
    if gt_path is None:
        return None
    traj_WB = read_trajectory(gt_path, "euroc")
    return interpolate_poses(timestamps, traj_WB.timestamps, traj_WB.T_WC @ T_BC, config.gt_max_gap,
                             config.gt_snap_dt)


#: the noise keys of an EuRoC imu0/sensor.yaml (continuous-time densities)
IMU_NOISE_KEYS = ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
                  "accelerometer_random_walk")


def _imu_noise(data) -> Optional[dict]:
    """The positive finite noise densities of an imu0/sensor.yaml (None when it gives none)."""
    out = {}
    for key in IMU_NOISE_KEYS:
        try:
            value = float(data.get(key)) if isinstance(data, dict) and data.get(key) is not None else None
        except (TypeError, ValueError):
            value = None
        if value is not None and np.isfinite(value) and value > 0:
            out[key] = value
    return out or None


def _read_imu(csv: Path) -> ImuSamples:
    stamps, values, lines = [], [], []
    for lineno, line in read_text_lines(csv):
        parts = line.split(",")
        if len(parts) < 7:
            raise DataError(f"{csv}:{lineno}: expected 7 comma-separated values, got {len(parts)}")
        try:
            stamps.append(int(parts[0]))
            values.append([float(p) for p in parts[1:7]])
        except ValueError as exc:
            raise DataError(f"{csv}:{lineno}: not a number: {exc}") from exc
        lines.append(lineno)
    ts = np.asarray(stamps, dtype=np.int64)
    check_increasing(csv, ts, lines, "IMU timestamp")
    vals = np.asarray(values, dtype=np.float64).reshape(-1, 6)
    if not np.all(np.isfinite(vals)):
        row = int(np.flatnonzero(~np.isfinite(vals).all(1))[0])
        raise DataError(f"{csv}:{lines[row]}: non-finite IMU value ({', '.join(f'{v:g}' for v in vals[row])}); "
                        "IMU values must be finite numbers")
    return ImuSamples(ns_to_seconds(ts), vals[:, :3].copy(), vals[:, 3:].copy())
