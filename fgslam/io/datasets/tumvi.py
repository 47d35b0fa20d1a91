"""TUM-VI loader (the exported ``dataset-<name>_512_16`` layout: EuRoC-style streams, Kalibr calibration).

Layout (``ROOT`` is the ``dataset-*`` folder; ``ROOT/mav0`` may also be given when ``ROOT/dso`` exists)::

    mav0/cam0/data.csv, cam0/data/<ts_ns>.png     (required; 20 Hz, 512x512 fisheye, 16-bit PNG)
    mav0/cam1/data.csv, cam1/data/<ts_ns>.png     (optional: stereo)
    mav0/imu0/data.csv                            (optional: IMU, 200 Hz; ``ts_ns, w_xyz rad/s, a_xyz m/s^2``)
    mav0/mocap0/data.csv                          (optional: ground truth ``ts_ns, p_xyz, q_wxyz`` of the IMU)
    dso/camchain.yaml                             (required: Kalibr camchain)
    dso/imu_config.yaml                           (optional: IMU noise densities, Kalibr keys)

``dso/camchain.yaml`` (Kalibr): per camera ``camN: {camera_model: pinhole, distortion_model:
equidistant, distortion_coeffs: [k1..k4], intrinsics: [fx, fy, cx, cy], resolution: [w, h],
T_cam_imu: 4x4 rows}``, and for cam1 ``T_cn_cnm1`` (cam0 -> cam1: ``X_C1 = T_cn_cnm1 X_C0``).
So ``T_BC = T_cam_imu(cam0)^-1`` (body = IMU), ``T_CLCR = T_cn_cnm1^-1`` (from ``T_cam_imu`` of both
cameras when ``T_cn_cnm1`` is absent). The equidistant (Kannala-Brandt) images are undistorted and
the pair rectified to pinhole by :class:`~fgslam.io.undistort.Undistorter` (OpenCV ``cv2.fisheye``).
Ground truth (``mocap0``, the motion-capture pose of the IMU ``T_WB``) gives ``T_WC = T_WB T_BC``;
mocap covers only part of most TUM-VI sequences (frames outside it have no ground truth).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional

import numpy as np

from ...core.errors import DataError
from ..calibration import Calibration, read_yaml_file
from .common import Dataset, DatasetConfig, RawFrame, ns_to_seconds
from .euroc import DISTORTION_NAMES, _imu_noise, _match, _read_imu, _read_stream, body_groundtruth_at_frames
from .files import read_image, require_dir, require_file

logger = logging.getLogger(__name__)

CAMCHAIN = Path("dso") / "camchain.yaml"
IMU_CONFIG = Path("dso") / "imu_config.yaml"


def tumvi_root(path: Path) -> Optional[Path]:
    """The ``dataset-*`` folder of a TUM-VI sequence at ``path`` (it or its ``mav0``), else None."""
    for cand in (path, path.parent):
        if (cand / CAMCHAIN).is_file() and (cand / "mav0" / "cam0").is_dir():
            return cand
    return None


def _matrix(value, what: str, source: Path) -> np.ndarray:
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{source}: {what} is not a 4x4 matrix of numbers: {exc}") from exc
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DataError(f"{source}: {what} must be a 4x4 matrix (4 rows of 4 numbers), got shape {T.shape}")
    return T


def kalibr_camera(data: dict, name: str, source: Path) -> tuple[Calibration, np.ndarray]:
    """Calibration (no extrinsics) and ``T_cam_imu`` of camera ``name`` of a Kalibr camchain."""
    cam = data.get(name)
    if not isinstance(cam, dict):
        raise DataError(f"{source}: missing camera {name!r}")
    for key in ("resolution", "intrinsics", "T_cam_imu"):
        if key not in cam:
            raise DataError(f"{source}: {name}: missing key {key!r}")
    if cam.get("camera_model", "pinhole") != "pinhole":
        raise DataError(f"{source}: {name}: camera_model {cam['camera_model']!r} not supported (pinhole with "
                        "equidistant or radtan distortion)")
    model = DISTORTION_NAMES.get(str(cam.get("distortion_model", "none")))
    if model is None:
        raise DataError(f"{source}: {name}: unknown distortion_model {cam['distortion_model']!r}")
    try:
        width, height = (int(v) for v in cam["resolution"])
        calib = Calibration(width, height, np.asarray(cam["intrinsics"], dtype=np.float64), model,
                            np.asarray(cam.get("distortion_coeffs", []) or [], dtype=np.float64))
    except (TypeError, ValueError) as exc:
        raise DataError(f"{source}: {name}: malformed camera values: {exc}") from exc
    return calib.validate(f"{source} ({name})"), _matrix(cam["T_cam_imu"], f"{name}.T_cam_imu", source)


class TumviDataset(Dataset):
    """TUM-VI sequence (see the module docstring)."""

    format = "tumvi"

    def __init__(self, root: Path, config: Optional[DatasetConfig] = None) -> None:
        super().__init__(root, config)
        config = self.config
        base = tumvi_root(self.root)
        if base is None:
            raise DataError(f"{self.root}: missing TUM-VI files {CAMCHAIN} and mav0/cam0")
        self.base = base
        self.name = base.name
        mav = base / "mav0"
        camchain = require_file(base / CAMCHAIN, "Kalibr camchain")
        chain = read_yaml_file(camchain)
        self.calibration_source = str(camchain)
        calib, T_C0I = kalibr_camera(chain, "cam0", camchain)
        calib.T_BC = np.linalg.inv(T_C0I)

        cam0 = require_dir(mav / "cam0", "cam0")
        ts0, names0 = _read_stream(cam0 / "data.csv")
        self._left = [cam0 / "data" / n for n in names0]

        imu_csv = mav / "imu0" / "data.csv"
        if imu_csv.is_file():
            if (base / IMU_CONFIG).is_file():
                imu_yaml = read_yaml_file(base / IMU_CONFIG)
                self.imu_noise = _imu_noise(imu_yaml.get("imu0", imu_yaml))
            if config.load_imu:
                self.imu = _read_imu(imu_csv)

        self._right: Optional[list[Path]] = None
        cam1 = mav / "cam1"
        if (cam1 / "data.csv").is_file() and "cam1" in chain:
            ts1, names1 = _read_stream(cam1 / "data.csv")
            right, T_C1I = kalibr_camera(chain, "cam1", camchain)
            max_dt_ns = int(round(config.stereo_max_dt * 1e9))
            j = _match(ts0, ts1, max_dt_ns, "cam1", cam0 / "data.csv", cam1 / "data.csv")
            self._right = [cam1 / "data" / names1[k] for k in j]
            T_C1C0 = (_matrix(chain["cam1"]["T_cn_cnm1"], "cam1.T_cn_cnm1", camchain)
                      if "T_cn_cnm1" in chain["cam1"] else T_C1I @ np.linalg.inv(T_C0I))
            calib.right = right
            calib.T_CLCR = np.linalg.inv(T_C1C0)
            self._has_stereo = True
        elif (cam1 / "data.csv").is_file():
            logger.warning("%s: mav0/cam1 present but the camchain has no cam1: monocular", camchain)

        self.raw_calibration = calib
        self.raw_timestamps = ns_to_seconds(ts0)
        self._gt_path = self._find_groundtruth(mav)
        self._setup()

    def _find_groundtruth(self, mav: Path) -> Optional[Path]:
        if self.config.groundtruth_file:
            return require_file(Path(self.config.groundtruth_file), "ground-truth")
        gt = mav / "mocap0" / "data.csv"
        return gt if gt.is_file() else None

    def _raw_groundtruth(self) -> Optional[np.ndarray]:
        return body_groundtruth_at_frames(self._gt_path, self.raw_calibration.T_BC, self.raw_timestamps, self.config)

    def _read_raw(self, raw_index: int) -> RawFrame:
        path = self._left[raw_index]
        image = read_image(path)
        right = None
        if self._right is not None and self.config.load_right:
            right = read_image(self._right[raw_index])
        return RawFrame(image, path, right, None)
