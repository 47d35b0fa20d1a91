"""KITTI odometry loader.

Layout: ``SEQ/image_0/NNNNNN.png`` (left grey, required), ``SEQ/image_1/`` (right grey, optional),
``SEQ/calib.txt`` (``P0: 12 numbers`` ... row-major 3x4 rectified projection matrices; a file
whose lines carry no labels, as some copies ship it, is read row by row as P0, P1, P2, P3, Tr with
a log line), ``SEQ/times.txt`` (one time in seconds per frame, strictly increasing).  Ground truth (3x4 row-major camera-to-world of
the left camera per frame, KITTI format): ``DatasetConfig.groundtruth_file``, else
``SEQ/poses.txt``, else ``SEQ/../../poses/<SEQ name>.txt`` (the benchmark's own layout).

Images are already rectified: the calibration has no distortion, ``K`` comes from ``P0`` and the
stereo baseline from ``P1[0, 3] = -fx * b`` (so ``T_CLCR`` is the translation ``[b, 0, 0]``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional

import numpy as np

from ...core.errors import DataError
from ..calibration import Calibration
from ..trajectory import read_trajectory
from .common import Dataset, DatasetConfig, RawFrame
from .files import image_size, read_image, read_text_lines, read_times, require_dir, require_file

logger = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
CALIB_ROWS = ("P0", "P1", "P2", "P3", "Tr")  # the rows of an odometry calib.txt, in file order


def _is_label(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return True
    return False


def list_images(folder: Path) -> list[Path]:
    """Image files of a folder, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file())


def read_kitti_calib(path: Path) -> dict[str, np.ndarray]:
    """``{"P0": (3, 4), ...}`` from a KITTI ``calib.txt`` (labelled lines, or unlabelled rows in
    the order of ``CALIB_ROWS``; see the module docstring)."""
    lines = read_text_lines(require_file(path, "KITTI calib.txt"))
    labelled = [":" in line for _, line in lines]
    if lines and not any(labelled):
        if len(lines) > len(CALIB_ROWS):
            raise DataError(
                f"{path}:{lines[len(CALIB_ROWS)][0]}: no line has a label ('P0: ...') and there are {len(lines)} rows; "
                f"unlabelled rows are read as {', '.join(CALIB_ROWS)}"
            )
        entries = [(lineno, name, line) for (lineno, line), name in zip(lines, CALIB_ROWS)]
        logger.info("%s: no 'P0:' labels; reading the %d rows in order as %s", path, len(lines),
                    ", ".join(CALIB_ROWS[: len(lines)]))
    elif not all(labelled):
        lineno = lines[labelled.index(False)][0]
        raise DataError(f"{path}:{lineno}: line has no label ('P0: 12 numbers'); label every line or none")
    else:
        entries = []
        for lineno, line in lines:
            key, _, rest = line.partition(":")
            entries.append((lineno, key.strip(), rest))
    out = {}
    for lineno, key, rest in entries:
        tokens = rest.split()
        try:
            vals = np.array([float(v) for v in tokens])
        except ValueError as exc:
            hint = f" (a label needs a colon: '{tokens[0]}: ...')" if tokens and _is_label(tokens[0]) else ""
            raise DataError(f"{path}:{lineno}: not a number: {exc}{hint}") from exc
        if vals.size != 12:
            raise DataError(f"{path}:{lineno}: {key} must have 12 values, got {vals.size}")
        out[key] = vals.reshape(3, 4)
    if "P0" not in out:
        raise DataError(f"{path}: no P0 line")
    return out


class KittiDataset(Dataset):
    """KITTI odometry sequence (see the module docstring)."""

    format = "kitti"

    def __init__(self, root: Path, config: Optional[DatasetConfig] = None) -> None:
        super().__init__(root, config)
        config = self.config
        self._left = list_images(require_dir(self.root / "image_0", "KITTI image_0"))
        if not self._left:
            raise DataError(f"{self.root / 'image_0'}: empty sequence (no images)")
        calib_path = self.root / "calib.txt"
        P = read_kitti_calib(calib_path)
        self.calibration_source = str(calib_path)
        times_path = require_file(self.root / "times.txt", "KITTI times.txt")
        times = read_times(times_path)
        if times.size != len(self._left):
            raise DataError(f"{times_path}: {times.size} times for {len(self._left)} images in {self.root / 'image_0'}")
        width, height = image_size(self._left[0])
        P0 = P["P0"]
        calib = Calibration(width, height, [P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2]])
        self._right: Optional[list[Path]] = None
        if (self.root / "image_1").is_dir():
            self._right = list_images(self.root / "image_1")
            if len(self._right) != len(self._left):
                raise DataError(
                    f"{self.root}: stereo streams of different lengths: image_0 has {len(self._left)} images, "
                    f"image_1 has {len(self._right)}"
                )
            if "P1" not in P:
                raise DataError(f"{calib_path}: image_1 present but no P1 line")
            P1 = P["P1"]
            baseline = -(P1[0, 3] - P0[0, 3]) / P1[0, 0]
            T_CLCR = np.eye(4)
            T_CLCR[0, 3] = baseline
            calib.right = Calibration(width, height, [P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2]])
            calib.T_CLCR = T_CLCR
            self._has_stereo = True
        self.raw_calibration = calib
        self.raw_timestamps = times
        self._gt_path = self._find_groundtruth()
        self._setup()

    def _find_groundtruth(self) -> Optional[Path]:
        if self.config.groundtruth_file:
            return require_file(Path(self.config.groundtruth_file), "ground-truth")
        for cand in (self.root / "poses.txt", self.root.parent.parent / "poses" / f"{self.root.name}.txt"):
            if cand.is_file():
                return cand
        return None

    def _raw_groundtruth(self) -> Optional[np.ndarray]:
        if self._gt_path is None:
            return None
        poses = read_trajectory(self._gt_path, "kitti").T_WC
        n = self.raw_timestamps.size
        if poses.shape[0] < n:
            logger.warning("%s: %d poses for %d frames; the last frames have no ground truth", self._gt_path, poses.shape[0], n)
        out = np.full((n, 4, 4), np.nan)
        m = min(n, poses.shape[0])
        out[:m] = poses[:m]
        return out

    def _read_raw(self, raw_index: int) -> RawFrame:
        path = self._left[raw_index]
        right = None
        if self._right is not None and self.config.load_right:
            right = read_image(self._right[raw_index])
        return RawFrame(read_image(path), path, right)
