"""Live capture: ``camera:SPEC``, any source OpenCV's ``VideoCapture`` opens (a webcam or video device
``camera:0``, an RTSP or HTTP stream ``camera:rtsp://host/stream``, a file ``camera:/path/clip.mp4``),
with a calibration YAML (``DatasetConfig.calibration_file``; keys in :mod:`fgslam.io.calibration`).

Frames are read in order as the source gives them (no seeking). A frame's timestamp: for a file, its
position in the file (``CAP_PROP_POS_MSEC``), so that a live run replays it at its own rate through the
same capture path; for a device or a stream, the time since the first frame was read, in seconds, on
this machine's monotonic clock. A live source has no end known
ahead: the run takes at most ``dataset.end`` frames (default :data:`DEFAULT_CAPTURE_FRAMES`, the number a
run reports as its total) and ends earlier when the source ends or on Ctrl-C. A frame the source fails
to deliver ends the capture. ``dataset.start`` and ``dataset.stride`` do not apply (a live source cannot
skip ahead), nor does re-reading a frame (``--save-map`` of a capture: record a video file first).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import numpy as np

from ...core.config import MS_PER_S
from ...core.errors import ConfigError, DataError
from ..calibration import Calibration
from .common import CALIBRATION_OVERRIDE, Dataset, DatasetConfig, RawFrame
from .files import require_file

PREFIX = "camera:"
#: frames a capture takes when ``dataset.end`` is not set: ten minutes at 30 Hz (its memory is estimated for them)
DEFAULT_CAPTURE_FRAMES = 18_000
_NOMINAL_RATE_HZ = 30.0  # the frame rate assumed ahead (memory estimate) when the source reports none
_MIN_STEP_S = 1e-6  # consecutive capture times are at least this far apart (the frame times must increase)


def is_capture(path: str | Path) -> bool:
    """Whether ``path`` names a live capture (``camera:SPEC``)."""
    return str(path).startswith(PREFIX)


class CaptureDataset(Dataset):
    """A live OpenCV capture (module docstring)."""

    format = "camera"

    def __init__(self, root: Path | str, config: Optional[DatasetConfig] = None) -> None:
        import cv2  # deferred: OpenCV

        spec = str(root)[len(PREFIX):]
        super().__init__(Path(str(root)), config)
        config = self.config
        self.name = spec or "camera"
        if config.start != 0 or config.stride != 1:
            raise ConfigError(f"{root}: dataset.start and dataset.stride do not apply to a live capture "
                              "(it cannot skip ahead); use dataset.end to stop after N frames")
        if not config.calibration_file:
            raise ConfigError(f"{root}: a live capture needs its calibration: {CALIBRATION_OVERRIDE} "
                              "(a calibration YAML: width, height, intrinsics, distortion)")
        path = require_file(Path(config.calibration_file), "calibration YAML")
        calib = Calibration.from_yaml(path)
        if calib.right is not None:
            raise DataError(f"{path}: a capture is monocular; remove 'right' / 'T_CLCR'")
        self.raw_calibration, self.calibration_source = calib, str(path)
        try:
            cap = cv2.VideoCapture(int(spec) if spec.isdecimal() and spec.isascii() else spec)  # a device number
        except (cv2.error, OverflowError, ValueError) as exc:
            raise DataError(f"{root}: OpenCV cannot open this capture: {exc}") from exc
        if not cap.isOpened():
            raise DataError(f"{root}: OpenCV cannot open this capture (a device number, a stream URL or a video file)")
        self._cap = cap
        device = spec.isdecimal() and spec.isascii()
        self.is_file = not device and Path(spec).is_file()  # a recording: its own times (module docstring)
        if not self.is_file:  # a device or stream: no backlog of old frames (where the backend supports it)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        n = config.end if config.end is not None else DEFAULT_CAPTURE_FRAMES
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        rate = fps if np.isfinite(fps) and fps > 0 else _NOMINAL_RATE_HZ
        self.raw_timestamps = np.arange(n, dtype=np.float64) / rate  # replaced by the capture times as frames come
        self._step_s = 1.0 / rate  # a file's frame interval when its position does not advance
        self._t0: Optional[float] = None
        self._t_read: Optional[float] = None  # the time of the last frame read
        self._first: Optional[tuple[np.ndarray, float]] = None  # a file's first frame and time, read at open
        try:
            self._setup()
        except BaseException:
            cap.release()
            raise
        # a device's frame read at open is stale by the time the run starts: its clock starts again
        self._t0 = self._t0 if self.is_file else None
        self._t_read = None

    def _read_raw(self, raw_index: int) -> RawFrame:
        from ..frame import FrameReadError

        if self._first is not None:  # a file's first frame, read at open: delivered now with its own time
            (img, t), self._first = self._first, None
        else:
            ok, img = self._cap.read()
            if not ok or img is None:
                raise StopCapture(f"{self.root}: the source delivered no frame {raw_index}")
            t = self._time()
            if self._t_read is None and self.is_file:  # at open (the size check): kept for the run's first frame
                self._first = (img, t)
        self._t_read = t
        self.raw_timestamps[raw_index] = t
        if img.ndim not in (2, 3):
            raise FrameReadError(f"{self.root}: frame {raw_index} is not an image")
        return RawFrame(img, None)

    def _time(self) -> float:
        """The time of the frame just read (module docstring), after the previous one's."""
        import cv2  # deferred: OpenCV

        now = self._cap.get(cv2.CAP_PROP_POS_MSEC) / MS_PER_S if self.is_file else time.monotonic()
        if self._t0 is None:
            self._t0 = now
        t = now - self._t0
        if self._t_read is not None and not t > self._t_read:  # a position that does not advance (or NaN), a tie
            t = self._t_read + (self._step_s if self.is_file else _MIN_STEP_S)
        return t

    def __iter__(self):  # the capture's end is the run's end (no skipping, no seeking)
        try:
            yield from super().__iter__()
        except StopCapture:
            return

    def __getitem__(self, index: int):
        raise DataError(f"{self.root}: a live capture is read in order; its frames cannot be read again")

    def close(self) -> None:
        """Release the capture."""
        self._cap.release()


class StopCapture(DataError):
    """The source ended (or failed to deliver a frame): the capture's end."""
