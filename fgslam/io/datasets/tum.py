"""TUM RGB-D loader.

Layout: ``SEQ/rgb.txt`` and ``SEQ/depth.txt`` (``timestamp filename`` per line), ``SEQ/rgb/``,
``SEQ/depth/`` (16-bit PNG, 5000 units per metre, 0 = invalid), optional ``SEQ/groundtruth.txt``
(TUM format ``t tx ty tz qx qy qz qw``, pose of the colour camera's optical centre in the world).

Each rgb image is associated with the nearest depth image within ``association_max_dt`` (greedy on
increasing time difference, each depth used once, as the benchmark's ``associate.py``); rgb images
without a depth partner are dropped.  Camera: the published Freiburg 1/2/3 colour calibrations,
chosen by ``DatasetConfig.tum_camera`` or the folder name (``..._freiburg2_...``), default fr1;
``DatasetConfig.calibration_file`` overrides them.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Optional

import numpy as np

from ...core.errors import DataError
from ..calibration import Calibration
from ..trajectory import read_trajectory
from .common import Dataset, DatasetConfig, RawFrame, interpolate_poses
from .files import read_image, read_text_lines, require_file

logger = logging.getLogger(__name__)

DEPTH_SCALE = 5000.0  # TUM RGB-D depth PNG units per metre (benchmark definition)
TUM_SIZE = (640, 480)  # Kinect image size of every TUM RGB-D sequence
# Published colour-camera calibrations (TUM RGB-D "file formats" page): fx, fy, cx, cy; radtan d0..d4
TUM_CAMERAS = {
    "fr1": ([517.3, 516.5, 318.6, 255.3], [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]),
    "fr2": ([520.9, 521.0, 325.1, 249.7], [0.2312, -0.7849, -0.0033, -0.0001, 0.9172]),
    "fr3": ([535.4, 539.2, 320.1, 247.6], []),
}


def tum_camera_name(folder: Path) -> str:
    """``fr1|fr2|fr3`` from a folder name such as ``rgbd_dataset_freiburg2_desk`` (default fr1)."""
    m = re.search(r"(?:freiburg|fr)([123])", folder.name.lower())
    return f"fr{m.group(1)}" if m else "fr1"


def _read_list(path: Path) -> tuple[np.ndarray, list[str]]:
    times, names = [], []
    for lineno, line in read_text_lines(require_file(path, "TUM list")):
        parts = line.split()
        if len(parts) < 2:
            raise DataError(f"{path}:{lineno}: expected 'timestamp filename', got {line!r}")
        try:
            times.append(float(parts[0]))
        except ValueError as exc:
            raise DataError(f"{path}:{lineno}: bad timestamp {parts[0]!r}") from exc
        names.append(parts[1])
    return np.asarray(times, dtype=np.float64), names


def associate(t_a: np.ndarray, t_b: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """Greedy one-to-one association of two time lists by increasing ``|t_a - t_b| <= max_dt``."""
    order_b = np.argsort(t_b)
    tb = t_b[order_b]
    cands = []
    for i, t in enumerate(t_a):
        lo, hi = np.searchsorted(tb, t - max_dt, "left"), np.searchsorted(tb, t + max_dt, "right")
        cands.extend((abs(t - tb[k]), i, int(order_b[k])) for k in range(lo, hi))
    cands.sort()
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


class TumDataset(Dataset):
    """TUM RGB-D sequence (see the module docstring)."""

    format = "tum"

    def __init__(self, root: Path, config: Optional[DatasetConfig] = None) -> None:
        super().__init__(root, config)
        config = self.config
        t_rgb, rgb_names = _read_list(self.root / "rgb.txt")
        self._rgb = [self.root / n for n in rgb_names]
        self._depth: Optional[list[Path]] = None
        times = t_rgb
        depth_list = self.root / "depth.txt"
        if depth_list.is_file():
            t_depth, depth_names = _read_list(depth_list)
            pairs = associate(t_rgb, t_depth, config.association_max_dt)
            if len(pairs) < len(t_rgb):
                logger.info("%s: %d of %d rgb images have no depth within %.3f s and are dropped",
                            self.root, len(t_rgb) - len(pairs), len(t_rgb), config.association_max_dt)
            self._rgb = [self.root / rgb_names[i] for i, _ in pairs]
            self._depth = [self.root / depth_names[j] for _, j in pairs]
            times = np.array([t_rgb[i] for i, _ in pairs])
            self._has_depth = True
        if config.calibration_file:
            calib = Calibration.from_yaml(config.calibration_file)
            self.calibration_source = config.calibration_file
        else:
            cam = config.tum_camera or tum_camera_name(self.root)
            K, dist = TUM_CAMERAS[cam]
            calib = Calibration(*TUM_SIZE, K, "radtan" if dist else "none", dist)
            self.calibration_source = f"built-in TUM {cam} calibration"
        self.raw_calibration = calib
        self.raw_timestamps = times
        self._gt_path = Path(config.groundtruth_file) if config.groundtruth_file else self.root / "groundtruth.txt"
        if config.groundtruth_file:
            require_file(self._gt_path, "ground-truth")
        self._setup()

    def _raw_groundtruth(self) -> Optional[np.ndarray]:
        if not self._gt_path.is_file():
            return None
        traj = read_trajectory(self._gt_path, "tum")
        return interpolate_poses(self.raw_timestamps, traj.timestamps, traj.T_WC, self.config.gt_max_gap, self.config.gt_snap_dt)

    def _read_raw(self, raw_index: int) -> RawFrame:
        path = self._rgb[raw_index]
        depth = None
        if self._depth is not None and self.config.load_depth:
            depth = read_image(self._depth[raw_index]).astype(np.float32) / np.float32(DEPTH_SCALE)
        return RawFrame(read_image(path), path, None, depth)
