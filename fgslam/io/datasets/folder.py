"""Image-folder and video loaders with a calibration YAML.

Image folder: ``DIR/*.{png,jpg,jpeg}`` (sorted by name) plus a calibration YAML
(``DatasetConfig.calibration_file``, else ``DIR/calibration.yaml`` or ``DIR/calib.yaml``; keys in
:mod:`fgslam.io.calibration`).  Timestamps: ``DIR/timestamps.txt`` (one time in seconds per image)
when present, else ``index / rate_hz`` with ``rate_hz`` from the YAML or ``default_rate_hz``.

Video: any file OpenCV's ``VideoCapture`` opens, plus a calibration YAML
(``calibration_file``, else ``<video stem>.yaml`` or ``calibration.yaml`` next to the video).
Timestamps are ``index / fps`` of the container.  Frames are decoded sequentially; a random access
seeks (``CAP_PROP_POS_FRAMES``).  Only the decoder state is held, never decoded frames.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ...core.errors import DataError
from ..calibration import Calibration, read_yaml_file
from ..frame import FrameReadError
from .common import CALIBRATION_OVERRIDE, Dataset, DatasetConfig, RawFrame
from .files import read_image, read_times, require_dir, require_file
from .kitti import list_images

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg")


def _calibration(candidates: list[Path], config: DatasetConfig, where: Path) -> tuple[Calibration, Optional[float], str]:
    """Calibration, optional ``rate_hz`` and the file they came from."""
    if config.calibration_file:
        path = require_file(Path(config.calibration_file), "calibration YAML")
    else:
        path = next((c for c in candidates if c.is_file()), None)
        if path is None:
            raise DataError(f"{where}: missing calibration YAML (looked for {', '.join(c.name for c in candidates)}; "
                            f"or give one with {CALIBRATION_OVERRIDE})")
    data = read_yaml_file(path)
    rate = data.get("rate_hz")
    if rate is not None and (not isinstance(rate, (int, float)) or rate <= 0):
        raise DataError(f"{path}: rate_hz must be a positive number, got {rate!r}")
    return Calibration.from_dict(data, str(path)), None if rate is None else float(rate), str(path)


class FolderDataset(Dataset):
    """A folder of images plus a calibration YAML (see the module docstring)."""

    format = "folder"

    def __init__(self, root: Path, config: Optional[DatasetConfig] = None) -> None:
        super().__init__(root, config)
        config = self.config
        self._images = list_images(require_dir(self.root, "image"))
        if not self._images:
            raise DataError(f"{self.root}: empty sequence (no .png/.jpg images)")
        calib, rate, source = _calibration([self.root / "calibration.yaml", self.root / "calib.yaml"], config, self.root)
        if calib.right is not None:
            raise DataError(f"{source}: image folders are monocular; remove 'right' / 'T_CLCR'")
        self.raw_calibration, self.calibration_source = calib, source
        times_path = self.root / "timestamps.txt"
        if times_path.is_file():
            times = read_times(times_path)
            if times.size != len(self._images):
                raise DataError(f"{times_path}: {times.size} times for {len(self._images)} images")
        else:
            times = np.arange(len(self._images), dtype=np.float64) / (rate or config.default_rate_hz)
        self.raw_timestamps = times
        self._setup()

    def _read_raw(self, raw_index: int) -> RawFrame:
        path = self._images[raw_index]
        return RawFrame(read_image(path), path)


class VideoDataset(Dataset):
    """A video file plus a calibration YAML (see the module docstring)."""

    format = "video"

    def __init__(self, root: Path, config: Optional[DatasetConfig] = None) -> None:
        import cv2  # deferred: OpenCV

        super().__init__(root, config)
        config = self.config
        require_file(self.root, "video")
        self.name = self.root.stem
        calib, _, source = _calibration(
            [self.root.with_suffix(".yaml"), self.root.parent / "calibration.yaml"], config, self.root
        )
        if calib.right is not None:
            raise DataError(f"{source}: videos are monocular; remove 'right' / 'T_CLCR'")
        self.raw_calibration, self.calibration_source = calib, source
        cap = cv2.VideoCapture(str(self.root))
        if not cap.isOpened():
            raise DataError(f"{self.root}: OpenCV cannot open this video")
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        if fps <= 0 or not np.isfinite(fps):
            raise DataError(f"{self.root}: video reports no frame rate")
        self._cap = cap
        self._next = 0  # index of the frame the capture decodes next
        self.raw_timestamps = np.arange(max(n, 0), dtype=np.float64) / fps
        self._setup()

    def _read_raw(self, raw_index: int) -> RawFrame:
        import cv2  # deferred: OpenCV

        if raw_index != self._next:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, raw_index)
        ok, img = self._cap.read()
        self._next = raw_index + 1 if ok else -1
        if not ok or img is None:
            raise FrameReadError(f"{self.root}: cannot decode frame {raw_index}")
        return RawFrame(img, None)

    def close(self) -> None:
        """Release the decoder."""
        self._cap.release()
