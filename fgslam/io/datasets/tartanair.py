"""TartanAir loader.

Layout: ``SEQ/image_left/NNNNNN_left.png``, optional ``SEQ/image_right/NNNNNN_right.png``,
optional ``SEQ/depth_left/NNNNNN_left_depth.npy`` (float32 z-depth in metres), optional
``SEQ/pose_left.txt`` (``tx ty tz qx qy qz qw`` per frame).  Fixed pinhole camera
``fx = fy = 320, cx = 320, cy = 240`` at 640x480, rectified stereo baseline 0.25 m.
TartanAir stores no timestamps: frame ``i`` gets ``i / NOMINAL_RATE_HZ``.

Pose convention: ``pose_left.txt`` gives the left camera *body* in NED axes (x forward, y right,
z down) in an NED world.  The camera optical frame C (x right, y down, z forward) is the body frame
with permuted axes, ``X_in_body = P @ X_in_C`` with ``P = [[0,0,1],[1,0,0],[0,1,0]]``, and the
world is re-expressed with the same permutation, so ``T_WC = P^T @ T_ned @ P`` (P as a 4x4).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ...core.errors import DataError
from ..calibration import Calibration
from ..frame import FrameReadError
from ..trajectory import quaternion_xyzw_to_rotation
from .common import Dataset, DatasetConfig, RawFrame
from .files import read_image, read_number_table, require_dir
from .kitti import list_images

TARTANAIR_K = (320.0, 320.0, 320.0, 240.0)  # fx, fy, cx, cy of every TartanAir camera
TARTANAIR_SIZE = (640, 480)
TARTANAIR_BASELINE = 0.25  # m
NOMINAL_RATE_HZ = 10.0  # TartanAir has no timestamps; frames are indexed at this nominal rate
NED_TO_OPTICAL = np.array([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)  # P


class TartanAirDataset(Dataset):
    """TartanAir sequence (see the module docstring)."""

    format = "tartanair"

    def __init__(self, root: Path, config: Optional[DatasetConfig] = None) -> None:
        super().__init__(root, config)
        config = self.config
        self._left = list_images(require_dir(self.root / "image_left", "TartanAir image_left"))
        n = len(self._left)
        self._right: Optional[list[Path]] = None
        if (self.root / "image_right").is_dir():
            self._right = list_images(self.root / "image_right")
            if len(self._right) != n:
                raise DataError(f"{self.root}: stereo streams of different lengths: image_left has {n}, image_right has {len(self._right)}")
            self._has_stereo = True
        self._depth: Optional[list[Path]] = None
        if (self.root / "depth_left").is_dir():
            self._depth = sorted((self.root / "depth_left").glob("*.npy"))
            if len(self._depth) != n:
                raise DataError(f"{self.root / 'depth_left'}: {len(self._depth)} depth maps for {n} images")
            self._has_depth = True
        calib = Calibration(*TARTANAIR_SIZE, TARTANAIR_K)
        if self._has_stereo:
            T_CLCR = np.eye(4)
            T_CLCR[0, 3] = TARTANAIR_BASELINE
            calib.right, calib.T_CLCR = Calibration(*TARTANAIR_SIZE, TARTANAIR_K), T_CLCR
        self.calibration_source = "built-in TartanAir calibration"
        self.raw_calibration = calib
        self.raw_timestamps = np.arange(n, dtype=np.float64) / NOMINAL_RATE_HZ
        self._setup()

    def _raw_groundtruth(self) -> Optional[np.ndarray]:
        path = Path(self.config.groundtruth_file) if self.config.groundtruth_file else self.root / "pose_left.txt"
        if not path.is_file():
            return None
        vals = read_number_table(path, 7)
        n = self.raw_timestamps.size
        if vals.shape[0] != n:
            raise DataError(f"{path}: {vals.shape[0]} poses for {n} frames")
        T_ned = np.tile(np.eye(4), (n, 1, 1))
        T_ned[:, :3, :3] = quaternion_xyzw_to_rotation(vals[:, 3:7])
        T_ned[:, :3, 3] = vals[:, :3]
        return NED_TO_OPTICAL.T @ T_ned @ NED_TO_OPTICAL

    def _read_raw(self, raw_index: int) -> RawFrame:
        path = self._left[raw_index]
        right = depth = None
        if self._right is not None and self.config.load_right:
            right = read_image(self._right[raw_index])
        if self._depth is not None and self.config.load_depth:
            dpath = self._depth[raw_index]
            try:
                depth = np.load(dpath, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise FrameReadError(f"{dpath}: unreadable depth map: {exc}") from exc
        return RawFrame(read_image(path), path, right, depth)
