"""Microsoft 7-Scenes loader.

Layout: ``SCENE/seq-NN/frame-NNNNNN.color.{png,jpg}``, ``.depth.png`` (uint16 millimetres;
0 and 65535 invalid), ``.pose.txt`` (4x4 camera-to-world; non-finite = no pose; the stored rotation
blocks are orthonormal only to ~3e-4 and are replaced by the nearest rotation), optional
``camera-intrinsics.txt`` (3x3 K) in the scene or sequence folder, else ``fx = fy = 585``,
``cx = 320``, ``cy = 240`` (the depth camera; colour is only approximately registered).
These intrinsics serve both the colour image and the depth map, which is used unregistered: a
photometric check on redkitchen (depth back-projected with 585, warped by the ground-truth poses
into the colour images) favours a colour focal length near 525 (the Kinect v1 colour camera), yet
monocular patch SLAM with 525 was not more accurate (600 frames: Sim(3) ATE 0.069 vs 0.060 m), and
RGB-D patch SLAM with depth resampled into a 525 / 555 px colour camera reaches 0.044 / 0.029 m
SE(3) vs 0.033 m at 585 (docs/benchmarks/presets.md: a focal fitted on the evaluation clip is no
calibration), so the file's values stay.
``SCENE`` may also be a ``seq-NN`` folder itself; with several sequences ``DatasetConfig.sequence``
picks one (default: the first).  7-Scenes stores no timestamps: frame ``i`` gets ``i / RATE_HZ``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional

import numpy as np

from ...core.errors import DataError
from ..calibration import Calibration
from ..frame import FrameReadError
from .common import Dataset, DatasetConfig, RawFrame, nearest_rotation
from .files import read_image, read_number_table, require_dir

logger = logging.getLogger(__name__)

RATE_HZ = 30.0  # Kinect v1 frame rate of the 7-Scenes recordings
DEFAULT_K = (585.0, 585.0, 320.0, 240.0)  # the dataset's published intrinsics
SIZE = (640, 480)
DEPTH_UNITS_PER_M = 1000.0  # millimetres
DEPTH_INVALID = 65535  # besides 0


def is_sequence_dir(path: Path) -> bool:
    return path.is_dir() and any(path.glob("frame-*.color.*"))


class SevenScenesDataset(Dataset):
    """7-Scenes sequence (see the module docstring)."""

    format = "7scenes"

    def __init__(self, root: Path, config: Optional[DatasetConfig] = None) -> None:
        super().__init__(root, config)
        config = self.config
        require_dir(self.root, "7-Scenes")
        if is_sequence_dir(self.root):
            seq = self.root
        else:
            seqs = sorted(p for p in self.root.glob("seq-*") if is_sequence_dir(p))
            if config.sequence:
                seq = require_dir(self.root / config.sequence, "7-Scenes sequence")
            elif not seqs:
                raise DataError(f"{self.root}: no seq-NN folder with frame-*.color.* images")
            else:
                seq = seqs[0]
                if len(seqs) > 1:
                    logger.info("%s: %d sequences, using %s (set 'sequence' to choose)", self.root, len(seqs), seq.name)
        self.seq = seq
        self.name = f"{self.root.name}/{seq.name}" if seq != self.root else seq.name
        self._color = sorted(seq.glob("frame-*.color.*"))
        if not self._color:
            raise DataError(f"{seq}: empty sequence (no frame-*.color.* images)")
        self._stems = [p.name.split(".")[0] for p in self._color]
        self._has_depth = any(seq.glob("frame-*.depth.png"))
        K = DEFAULT_K
        self.calibration_source = "built-in 7-Scenes intrinsics"
        for cand in (seq / "camera-intrinsics.txt", seq.parent / "camera-intrinsics.txt"):
            if cand.is_file():
                M = read_number_table(cand, 3)
                if M.shape != (3, 3):
                    raise DataError(f"{cand}: expected a 3x3 matrix, got {M.shape[0]} rows")
                K = (M[0, 0], M[1, 1], M[0, 2], M[1, 2])
                self.calibration_source = str(cand)
                break
        self.raw_calibration = Calibration(*SIZE, K)
        self.raw_timestamps = np.arange(len(self._color), dtype=np.float64) / RATE_HZ
        self._setup()

    def _raw_groundtruth(self) -> Optional[np.ndarray]:
        if not any(self.seq.glob("frame-*.pose.txt")):
            return None
        out = np.full((len(self._stems), 4, 4), np.nan)
        for i, stem in enumerate(self._stems):
            path = self.seq / f"{stem}.pose.txt"
            if not path.is_file():
                continue
            M = read_number_table(path, 4)
            if M.shape != (4, 4):
                raise DataError(f"{path}: expected a 4x4 matrix, got {M.shape[0]} rows")
            if np.all(np.isfinite(M)):
                out[i] = M
        ok = np.all(np.isfinite(out), axis=(1, 2))
        out[ok, :3, :3] = nearest_rotation(out[ok, :3, :3])
        return out

    def _read_raw(self, raw_index: int) -> RawFrame:
        path = self._color[raw_index]
        depth = None
        if self._has_depth and self.config.load_depth:
            dpath = self.seq / f"{self._stems[raw_index]}.depth.png"
            raw = read_image(dpath)
            if raw.dtype != np.uint16 or raw.ndim != 2:
                raise FrameReadError(f"{dpath}: expected a 16-bit single-channel depth image, got {raw.dtype} {raw.shape}")
            depth = raw.astype(np.float32) / np.float32(DEPTH_UNITS_PER_M)
            depth[raw == DEPTH_INVALID] = 0.0
        return RawFrame(read_image(path), path, None, depth)
