"""Timestamped position files (GPS-like): one ``t x y z`` per line.

``t`` is in seconds on the dataset's clock (the frames' timestamps), ``x y z`` in metres in any
fixed frame. Blank lines and lines starting with ``#`` are skipped. Errors name the file and line:
a line without exactly four numbers, a non-finite value, times that are not strictly increasing,
and (:meth:`PositionTrack.check_overlap`) times that do not overlap a run's frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import DataError, FormatError
from .datasets.files import check_increasing, read_text_lines

POSITION_COLUMNS = 4  # t x y z


@dataclass(frozen=True)
class PositionTrack:
    """Positions ``p`` (N, 3) at strictly increasing times ``t`` (N,), read from ``path`` (``lines``: the
    1-based line of each sample, for error messages)."""

    path: Path
    t: np.ndarray
    p: np.ndarray
    lines: tuple[int, ...]

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def check_overlap(self, t_first: float, t_last: float) -> None:
        """DataError naming the file and the lines of its first and last samples when no sample lies in
        ``[t_first, t_last]`` (the run's first and last frame times)."""
        inside = (self.t >= t_first) & (self.t <= t_last)
        if not np.any(inside):
            raise DataError(
                f"{self.path}:{self.lines[0]}-{self.lines[-1]}: position times {self.t[0]:.6f} (line {self.lines[0]}) to "
                f"{self.t[-1]:.6f} (line {self.lines[-1]}) do not overlap the run's frames {t_first:.6f} to {t_last:.6f} "
                "(seconds on the dataset's clock)"
            )

    def interpolate(self, t: float) -> np.ndarray:
        """Position at ``t``: linear between the samples around it, the end sample outside them."""
        return np.array([np.interp(t, self.t, self.p[:, k]) for k in range(3)])


def read_positions(path: str | Path) -> PositionTrack:
    """Read a positions file (see the module docstring).

    Raises:
        DataError: the file cannot be read, or its times are not strictly increasing.
        FormatError: a malformed line (not four numbers), a non-finite value, or no samples.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: positions file not found")
    rows, lines = [], []
    for lineno, line in read_text_lines(path):
        tokens = line.replace(",", " ").split()
        if len(tokens) != POSITION_COLUMNS:
            raise FormatError(f"{path}:{lineno}: expected {POSITION_COLUMNS} numbers 't x y z', got {len(tokens)}")
        try:
            values = [float(tok) for tok in tokens]
        except ValueError as exc:
            raise FormatError(f"{path}:{lineno}: not a number: {exc}") from exc
        if not np.all(np.isfinite(values)):
            raise FormatError(f"{path}:{lineno}: non-finite value (NaN or infinity) in '{line}'")
        rows.append(values)
        lines.append(lineno)
    if not rows:
        raise FormatError(f"{path}: no positions found (expected lines 't x y z')")
    table = np.asarray(rows, dtype=np.float64)
    check_increasing(path, table[:, 0], lines, "time")
    return PositionTrack(path=path, t=table[:, 0].copy(), p=table[:, 1:].copy(), lines=tuple(lines))
