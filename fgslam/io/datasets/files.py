"""Reading a dataset's files for the loaders of :mod:`fgslam.io.datasets`: folders and files that
must exist, text tables of numbers and times (errors name the file and the line), and images decoded
with OpenCV, checked for truncation first (a missing, cut-short or undecodable image is a
:class:`~fgslam.io.frame.FrameReadError` naming the file).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ...core.errors import DataError
from ..frame import FrameReadError
from ..trajectory import read_times_file


def require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        raise DataError(f"{path}: missing {what} folder")
    return path


def require_file(path: Path, what: str) -> Path:
    if not path.is_file():
        raise DataError(f"{path}: missing {what} file")
    return path


def read_text_lines(path: Path) -> list[tuple[int, str]]:
    """Non-blank, non-``#`` lines of a text file as ``(1-based line number, stripped text)``."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read file: {exc}") from exc
    out = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            out.append((lineno, line))
    return out


def read_number_table(path: Path, ncols: int, sep: Optional[str] = None, min_cols: bool = False) -> np.ndarray:
    """Parse a table of numbers (``ncols`` per line, or at least that many with ``min_cols``)."""
    rows = []
    for lineno, line in read_text_lines(path):
        tokens = line.split(sep) if sep else line.split()
        if len(tokens) != ncols and not (min_cols and len(tokens) >= ncols):
            raise DataError(f"{path}:{lineno}: expected {ncols} values, got {len(tokens)}")
        try:
            rows.append([float(t) for t in tokens[:ncols]])
        except ValueError as exc:
            raise DataError(f"{path}:{lineno}: not a number: {exc}") from exc
    return np.asarray(rows, dtype=np.float64).reshape(-1, ncols)


def check_increasing(path: Path, values: np.ndarray, line_numbers: list[int], what: str = "timestamp") -> None:
    """DataError naming ``path`` and the line of the first value not above the previous one."""
    values = np.asarray(values)
    if values.size > 1:
        bad = np.flatnonzero(np.diff(values) <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise DataError(
                f"{path}:{line_numbers[i]}: {what} {values[i]} is not after the previous one ({values[i - 1]} on "
                f"line {line_numbers[i - 1]}); {what}s must be strictly increasing"
            )


def read_times(path: Path) -> np.ndarray:
    """A times file: one time (seconds) per line, strictly increasing (errors name file and line)."""
    out, lines = read_times_file(path)
    check_increasing(path, out, lines, "time")
    return out


# Markers that end a complete file: JPEG's end-of-image (after the last start-of-scan marker FFDA:
# entropy-coded data never contains either, so a file cut short has none after its last scan) and
# the type of PNG's final chunk.
JPEG_SOI, JPEG_SOS, JPEG_EOI = b"\xff\xd8", b"\xff\xda", b"\xff\xd9"
PNG_SIGNATURE, PNG_IEND = b"\x89PNG\r\n\x1a\n", b"IEND"


def truncation_reason(data: bytes) -> Optional[str]:
    """Why the bytes of a JPEG or PNG file are cut short (None: complete, or another format).

    Decoders return a partly grey image for a truncated JPEG (with only a warning on stderr), so
    completeness is checked on the bytes: a JPEG needs an end-of-image marker after its last scan,
    a PNG its IEND chunk.
    """
    if data.startswith(JPEG_SOI):
        if data.find(JPEG_EOI, max(data.rfind(JPEG_SOS), 0)) < 0:
            return "truncated JPEG (no end-of-image marker after the last scan)"
    elif data.startswith(PNG_SIGNATURE):
        if data.rfind(PNG_IEND) < 0:
            return "truncated PNG (no IEND chunk)"
    return None


def read_image(path: Path, flags: Optional[int] = None) -> np.ndarray:
    """Decode an image file with OpenCV; FrameReadError (naming the file) when it is missing,
    unreadable, truncated (see :func:`truncation_reason`) or not decodable."""
    import cv2  # deferred: OpenCV

    if not path.exists():
        raise FrameReadError(f"{path}: missing file")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise FrameReadError(f"{path}: cannot read image: {exc}") from exc
    reason = truncation_reason(data)
    if reason is not None:
        raise FrameReadError(f"{path}: {reason}")
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED if flags is None else flags) if data else None
    if img is None or img.size == 0:
        raise FrameReadError(f"{path}: unreadable or corrupt image")
    return img


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image file (reads it)."""
    img = read_image(path)
    return int(img.shape[1]), int(img.shape[0])


def to_grey_and_rgb(img: np.ndarray, want_rgb: bool, path: Optional[Path]) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """uint8 grey ``(H, W)`` and (optionally) RGB ``(H, W, 3)`` from an OpenCV image."""
    import cv2  # deferred: OpenCV

    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise FrameReadError(f"{path}: unsupported image type {img.dtype}")
    if img.ndim == 2:
        return img, None
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if img.ndim != 3 or img.shape[2] != 3:
        raise FrameReadError(f"{path}: unsupported image shape {img.shape}")
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return grey, (cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if want_rgb else None)

