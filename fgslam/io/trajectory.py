"""Camera trajectories and their file formats (TUM, KITTI, EuRoC).

Conventions
-----------
- A :class:`Trajectory` holds ``timestamps`` ``(N,)`` float64 seconds, sorted (non-decreasing:
  real ground-truth files such as TUM fr2/desk repeat a rounded timestamp now and then), and
  ``T_WC`` ``(N, 4, 4)`` float64 camera-to-world poses: ``X_in_W = R_WC @ X_in_C + t_WC``.
- Quaternions are Hamilton, unit norm, and map the body/camera frame to the world frame. Files
  store them in two orders: TUM uses ``qx qy qz qw``, EuRoC uses ``qw qx qy qz``. A quaternion read
  from a file is normalised (``q`` and ``-q`` give the same rotation); one written to a file is
  unit norm with ``qw >= 0``.

Formats
-------
- ``tum``: one pose per line ``t tx ty tz qx qy qz qw`` (t in seconds, whitespace separated).
- ``kitti``: one pose per line, the 12 numbers of the 3x4 matrix ``[R_WC | t_WC]`` row-major. The
  format has no timestamps: they come from an optional times file (one time in seconds per line,
  as KITTI's ``times.txt``), else they are the frame index ``0, 1, 2, ...``.
- ``euroc``: comma (or whitespace) separated ``timestamp, px, py, pz, qw, qx, qy, qz[, ...]`` with
  the timestamp in **nanoseconds**; this covers both the ground-truth state csv
  (``#timestamp [ns], p_RS_R_x [m], ..., q_RS_w [], ...`` followed by velocity and bias columns,
  which are ignored) and the plain 8-column estimate csv.

In every format, lines that are blank or start with ``#`` are skipped; any other line that does not
parse raises :class:`~fgslam.core.errors.FormatError` naming the file and the line number.

Time units are checked, since a file read in the wrong format can still parse: stamps in seconds
(``tum``, KITTI times files) above ``MAX_PLAUSIBLE_SECONDS`` are milli-, micro- or nanoseconds, and
EuRoC nanosecond stamps whose median interval is below ``MIN_PLAUSIBLE_INTERVAL_S`` are seconds
(a TUM file read as ``euroc``). Both raise a FormatError naming the file and the likely format.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import DataError, FormatError

logger = logging.getLogger(__name__)

FORMATS = ("tum", "kitti", "euroc")
# Numbers on a data line (EuRoC: at least that many; later columns are ignored).
_NUMBERS_PER_LINE = {"tum": 8, "kitti": 12, "euroc": 8}

# Largest accepted max-abs entry of R^T R - I: files store 6-9 significant digits, so a valid
# rotation read from disk is orthonormal to ~1e-6; anything beyond this is not a rotation.
ROTATION_ORTHONORMAL_TOL = 1e-4
# Quaternions with a norm below this cannot be normalised meaningfully (degenerate input).
QUATERNION_MIN_NORM = 1e-6
NS_PER_S = 1_000_000_000  # nanoseconds per second (EuRoC timestamps are integer nanoseconds)
# Time-unit plausibility (see the module docstring): ~3,170 years in seconds (Unix time is ~1.7e9 s,
# the same instant in milliseconds ~1.7e12), and a median pose interval of one microsecond (pose
# streams run at 1 kHz at most; seconds read as nanoseconds give intervals of ~3e-11 s at 30 Hz).
MAX_PLAUSIBLE_SECONDS = 1e11
MIN_PLAUSIBLE_INTERVAL_S = 1e-6


@dataclass(frozen=True)
class Trajectory:
    """A timed sequence of camera-to-world poses.

    Attributes:
        timestamps: ``(N,)`` float64, seconds, non-decreasing.
        T_WC: ``(N, 4, 4)`` float64 camera-to-world rigid transforms; last row ``[0, 0, 0, 1]``,
            ``R_WC = T_WC[:, :3, :3]`` orthonormal with det +1 (within ``ROTATION_ORTHONORMAL_TOL``).

    Raises:
        DataError: wrong shapes, non-finite values, timestamps that decrease, or a
            rotation block that is not a rotation.
    """

    timestamps: np.ndarray
    T_WC: np.ndarray

    def __post_init__(self) -> None:
        timestamps = np.array(self.timestamps, dtype=np.float64, copy=True)
        T_WC = np.array(self.T_WC, dtype=np.float64, copy=True)
        if timestamps.ndim != 1:
            raise DataError(f"Trajectory: timestamps must have shape (N,), got {timestamps.shape}")
        n = timestamps.shape[0]
        if T_WC.shape != (n, 4, 4):
            raise DataError(f"Trajectory: T_WC must have shape ({n}, 4, 4), got {T_WC.shape}")
        if not np.all(np.isfinite(timestamps)):
            raise DataError(f"Trajectory: non-finite timestamp at index {_first_bad(~np.isfinite(timestamps))}")
        if not np.all(np.isfinite(T_WC)):
            raise DataError(f"Trajectory: non-finite pose at index {_first_bad(~np.isfinite(T_WC).all(axis=(1, 2)))}")
        if n > 1 and not np.all(np.diff(timestamps) >= 0):
            bad = _first_bad(np.diff(timestamps) < 0) + 1
            raise DataError(
                f"Trajectory: timestamps must be sorted; index {bad} has "
                f"{timestamps[bad]:.9f} after {timestamps[bad - 1]:.9f}"
            )
        bottom_ok = np.all(T_WC[:, 3, :] == np.array([0.0, 0.0, 0.0, 1.0]), axis=1)
        if not np.all(bottom_ok):
            raise DataError(f"Trajectory: pose {_first_bad(~bottom_ok)} has last row != [0, 0, 0, 1]")
        bad_rot = ~_is_rotation(T_WC[:, :3, :3])
        if np.any(bad_rot):
            raise DataError(
                f"Trajectory: pose {_first_bad(bad_rot)} has a rotation block that is not a rotation "
                f"(tolerance {ROTATION_ORTHONORMAL_TOL})"
            )
        timestamps.setflags(write=False)
        T_WC.setflags(write=False)
        object.__setattr__(self, "timestamps", timestamps)
        object.__setattr__(self, "T_WC", T_WC)

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def t_WC(self) -> np.ndarray:
        """Camera positions in the world frame, ``(N, 3)``."""
        return self.T_WC[:, :3, 3]

    @property
    def R_WC(self) -> np.ndarray:
        """Camera-to-world rotations, ``(N, 3, 3)``."""
        return self.T_WC[:, :3, :3]

    @classmethod
    def from_position_quaternion(
        cls, timestamps: np.ndarray, t_WC: np.ndarray, q_WC_xyzw: np.ndarray
    ) -> Trajectory:
        """Build from positions ``(N, 3)`` and quaternions ``(N, 4)`` in ``x y z w`` order (normalised here)."""
        t_WC = np.asarray(t_WC, dtype=np.float64)
        T_WC = np.tile(np.eye(4), (t_WC.shape[0], 1, 1))
        T_WC[:, :3, :3] = quaternion_xyzw_to_rotation(q_WC_xyzw)
        T_WC[:, :3, 3] = t_WC
        return cls(timestamps, T_WC)

    def quaternions_xyzw(self) -> np.ndarray:
        """Unit quaternions of ``R_WC``, ``(N, 4)`` in ``x y z w`` order with ``w >= 0``."""
        return rotation_to_quaternion_xyzw(self.R_WC)

    def path_length(self) -> float:
        """Length of the polyline through the camera positions, metres."""
        return float(np.linalg.norm(np.diff(self.t_WC, axis=0), axis=1).sum())

    def write(self, path: str | Path, fmt: str = "tum") -> None:
        """Write the poses to ``path`` as ``tum`` (``t tx ty tz qx qy qz qw``), ``kitti`` (3x4 rows; the times
        beside it in ``<stem>_times.txt``) or ``euroc`` (:func:`write_trajectory`)."""
        path = Path(path)
        times = path.with_name(f"{path.stem}_times.txt") if fmt == "kitti" else None
        write_trajectory(path, self, fmt, times)

    def subset(self, indices: np.ndarray) -> Trajectory:
        """The poses at ``indices`` (must keep the timestamps sorted)."""
        return Trajectory(self.timestamps[indices], self.T_WC[indices])


def _first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _is_rotation(R: np.ndarray) -> np.ndarray:
    """Per-matrix test ``(N, 3, 3) -> (N,)`` bool: orthonormal and det > 0 within tolerance."""
    gram_err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-1, -2))
    return (gram_err <= ROTATION_ORTHONORMAL_TOL) & (np.linalg.det(R) > 0)


def quaternion_xyzw_to_rotation(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of Hamilton quaternions ``(..., 4)`` in ``x y z w`` order.

    The quaternions are normalised first, so ``q`` and ``c * q`` (any ``c != 0``, including -1) give
    the same matrix. Raises ``DataError`` for a norm below ``QUATERNION_MIN_NORM`` or non-finite input.
    """
    q = np.asarray(q_xyzw, dtype=np.float64)
    if q.shape[-1] != 4:
        raise DataError(f"quaternions must have a last dimension of 4, got shape {q.shape}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(q)) or np.any(norm < QUATERNION_MIN_NORM):
        raise DataError("quaternion with non-finite entries or (near-)zero norm")
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rotation_to_quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` (``x y z w``, ``w >= 0``) of rotation matrices ``(..., 3, 3)``.

    Row ``b`` of the symmetric matrix ``K`` below equals ``4 q_b (w, x, y, z)``; the row of the
    largest diagonal entry (largest ``|q_b|``) is normalised, which is stable for every rotation
    (Shepperd's method).
    """
    R = np.asarray(R, dtype=np.float64)
    M = R.reshape(-1, 3, 3)
    trace = np.trace(M, axis1=1, axis2=2)
    m = {(r, c): M[:, r, c] for r in range(3) for c in range(3)}
    K = np.stack(
        [
            np.stack([1 + trace, m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]], axis=-1),
            np.stack([m[2, 1] - m[1, 2], 1 + 2 * m[0, 0] - trace, m[0, 1] + m[1, 0], m[0, 2] + m[2, 0]], axis=-1),
            np.stack([m[0, 2] - m[2, 0], m[0, 1] + m[1, 0], 1 + 2 * m[1, 1] - trace, m[1, 2] + m[2, 1]], axis=-1),
            np.stack([m[1, 0] - m[0, 1], m[0, 2] + m[2, 0], m[1, 2] + m[2, 1], 1 + 2 * m[2, 2] - trace], axis=-1),
        ],
        axis=1,
    )
    best = np.argmax(np.diagonal(K, axis1=1, axis2=2), axis=1)
    q_wxyz = K[np.arange(K.shape[0]), best]
    q_wxyz /= np.linalg.norm(q_wxyz, axis=1, keepdims=True)
    q_wxyz[q_wxyz[:, 0] < 0] *= -1.0
    return q_wxyz[:, [1, 2, 3, 0]].reshape(R.shape[:-2] + (4,))


# --------------------------------------------------------------------------------------------- reading


def read_trajectory(
    path: str | Path, fmt: str, times_path: str | Path | None = None, unique_timestamps: bool = False
) -> Trajectory:
    """Read a trajectory file.

    Args:
        path: the file.
        fmt: ``"tum"``, ``"kitti"`` or ``"euroc"`` (see the module docstring).
        times_path: KITTI only: a file of one timestamp (seconds) per line, one per pose; without
            it KITTI poses get their frame index as timestamp.
        unique_timestamps: a repeated timestamp is an error (estimates: one pose per instant)
            instead of a warning (ground truth such as TUM fr2/desk repeats rounded stamps).

    Raises:
        FormatError: unknown format, malformed line (names file and line), empty file, bad
            rotation, decreasing (or, with ``unique_timestamps``, repeated) timestamps, times file
            of the wrong length, time stamps implausible for the format's unit.
        DataError: the file cannot be read.
    """
    path = Path(path)
    if fmt not in FORMATS:
        raise FormatError(f"{path}: unknown trajectory format {fmt!r} (expected one of {', '.join(FORMATS)})")
    if times_path is not None and fmt != "kitti":
        raise FormatError(f"{path}: a times file is only used with the kitti format, not {fmt!r}")
    rows = _read_rows(path, fmt)
    if not rows:
        raise FormatError(f"{path}: no poses found")
    line_numbers = [lineno for lineno, _ in rows]
    values = np.array([vals for _, vals in rows], dtype=np.float64)
    time_path, time_lines = path, line_numbers  # where each timestamp was read (named in errors)
    if fmt == "tum":
        timestamps = values[:, 0]
        _check_seconds(path, line_numbers, timestamps, "tum")
        t_WC, q_xyzw = values[:, 1:4], values[:, 4:8]
    elif fmt == "euroc":
        timestamps = values[:, 0]
        _check_nanoseconds(path, timestamps)
        t_WC, q_xyzw = values[:, 1:4], values[:, [5, 6, 7, 4]]
    else:
        T_WC = np.tile(np.eye(4), (values.shape[0], 1, 1))
        T_WC[:, :3, :] = values.reshape(-1, 3, 4)
        if times_path is not None:
            time_path = Path(times_path)
            timestamps, time_lines = _read_times(time_path, len(rows), path)
        else:
            timestamps = np.arange(len(rows), dtype=np.float64)
        return _build(path, line_numbers, timestamps, T_WC, time_path, time_lines, unique_timestamps)
    norms = np.linalg.norm(q_xyzw, axis=1)
    bad = norms < QUATERNION_MIN_NORM
    if np.any(bad):
        raise FormatError(f"{path}:{line_numbers[_first_bad(bad)]}: quaternion has (near-)zero norm")
    T_WC = np.tile(np.eye(4), (values.shape[0], 1, 1))
    T_WC[:, :3, :3] = quaternion_xyzw_to_rotation(q_xyzw)
    T_WC[:, :3, 3] = t_WC
    return _build(path, line_numbers, timestamps, T_WC, path, line_numbers, unique_timestamps)


def _check_seconds(path: Path, line_numbers: list[int], timestamps: np.ndarray, fmt: str) -> None:
    """FormatError when stamps that should be seconds are too large to be (ms, us or ns)."""
    big = np.abs(timestamps) > MAX_PLAUSIBLE_SECONDS
    if np.any(big):
        i = _first_bad(big)
        hint = " (the euroc format has nanosecond stamps: --format euroc)" if fmt == "tum" else ""
        raise FormatError(
            f"{path}:{line_numbers[i]}: timestamp {timestamps[i]:.6g} is not plausible in seconds as the {fmt} "
            f"format requires (over {MAX_PLAUSIBLE_SECONDS:.0e} s): milli-, micro- or nanoseconds?{hint}"
        )


def _check_nanoseconds(path: Path, timestamps: np.ndarray) -> None:
    """FormatError when EuRoC stamps (nanoseconds, already converted to seconds) were seconds."""
    steps = np.diff(timestamps)
    steps = steps[steps > 0]
    if steps.size and np.median(steps) < MIN_PLAUSIBLE_INTERVAL_S:
        raise FormatError(
            f"{path}: the euroc format has nanosecond timestamps, but read so the poses are "
            f"{np.median(steps) * NS_PER_S:.3g} ns apart (median): the stamps look like seconds; "
            f"the file is probably in the tum format (t tx ty tz qx qy qz qw, t in s): --format tum"
        )


def _build(
    path: Path,
    line_numbers: list[int],
    timestamps: np.ndarray,
    T_WC: np.ndarray,
    time_path: Path,
    time_lines: list[int],
    unique_timestamps: bool,
) -> Trajectory:
    """Construct the Trajectory, turning validation failures into FormatErrors that name the line
    (of ``path`` for poses, of ``time_path`` / ``time_lines`` for timestamps)."""
    if len(timestamps) > 1:
        step = np.diff(timestamps)
        if np.any(step < 0):
            i = _first_bad(step < 0) + 1
            raise FormatError(
                f"{time_path}:{time_lines[i]}: timestamp {timestamps[i]:.9f} is before the previous one "
                f"({timestamps[i - 1]:.9f}); timestamps must be sorted"
            )
        repeated = int(np.count_nonzero(step == 0))
        if repeated:
            i = _first_bad(step == 0) + 1
            if unique_timestamps:
                raise FormatError(
                    f"{time_path}:{time_lines[i]}: timestamp {timestamps[i]:.9f} repeats the one on line "
                    f"{time_lines[i - 1]} ({repeated} repeated in all); an estimate needs one pose per timestamp"
                )
            logger.warning("%s: %d repeated timestamp(s), first at line %d", time_path, repeated, time_lines[i])
    bad_rot = ~_is_rotation(T_WC[:, :3, :3])
    if np.any(bad_rot):
        raise FormatError(f"{path}:{line_numbers[_first_bad(bad_rot)]}: rotation block is not a rotation matrix")
    try:
        traj = Trajectory(timestamps, T_WC)
    except DataError as exc:
        raise FormatError(f"{path}: {exc}") from exc
    logger.debug("read %d poses from %s", len(traj), path)
    return traj


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read trajectory file: {exc}") from exc


def _read_rows(path: Path, fmt: str) -> list[tuple[int, list[float]]]:
    """Parse the data lines of ``path`` into ``(line number, numbers)`` (1-based line numbers)."""
    expected = _NUMBERS_PER_LINE[fmt]
    rows = []
    for lineno, raw in enumerate(_read_lines(path), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tokens = line.replace(",", " ").split() if fmt == "euroc" else line.split()
        if (fmt == "euroc" and len(tokens) < expected) or (fmt != "euroc" and len(tokens) != expected):
            qualifier = "at least " if fmt == "euroc" else ""
            raise FormatError(
                f"{path}:{lineno}: expected {qualifier}{expected} numbers for the {fmt} format, got {len(tokens)}"
            )
        try:
            if fmt == "euroc":
                numbers = [_parse_ns_as_seconds(tokens[0])] + [float(tok) for tok in tokens[1:8]]
            else:
                numbers = [float(tok) for tok in tokens]
        except ValueError as exc:
            raise FormatError(f"{path}:{lineno}: not a number: {exc}") from exc
        if not all(np.isfinite(numbers)):
            raise FormatError(f"{path}:{lineno}: non-finite value")
        rows.append((lineno, numbers))
    return rows


def _parse_ns_as_seconds(token: str) -> float:
    """Integer nanoseconds (optionally written with a zero fraction, e.g. ``123.000``) -> seconds.

    The integer part is split into whole seconds and the remainder before the float conversion so
    that no precision is lost beyond float64's own resolution at the magnitude of the result.
    """
    whole, dot, frac = token.partition(".")
    if dot and frac.strip("0") == "" and whole.lstrip("+-").isdigit():
        token = whole
    if token.lstrip("+-").isdigit():
        ns = int(token)
        sec, rem = divmod(ns, NS_PER_S)
        return float(sec) + rem / NS_PER_S
    return float(token) / NS_PER_S


def read_times_file(path: Path) -> tuple[np.ndarray, list[int]]:
    """A times file (one time per line, seconds; blank and ``#`` lines skipped): the times and their
    1-based line numbers. Errors name the file and the line."""
    times, lines = [], []
    for lineno, raw in enumerate(_read_lines(path), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tokens = line.split()
        if len(tokens) != 1:
            raise FormatError(f"{path}:{lineno}: expected one time per line, got {len(tokens)} values")
        try:
            value = float(tokens[0])
        except ValueError as exc:
            raise FormatError(f"{path}:{lineno}: not a number: {exc}") from exc
        if not np.isfinite(value):
            raise FormatError(f"{path}:{lineno}: non-finite time")
        times.append(value)
        lines.append(lineno)
    return np.array(times, dtype=np.float64), lines


def _read_times(times_path: Path, n_poses: int, poses_path: Path) -> tuple[np.ndarray, list[int]]:
    """Timestamps (seconds) of a KITTI times file and their 1-based line numbers."""
    out, lines = read_times_file(times_path)
    if len(out) != n_poses:
        raise FormatError(f"{times_path}: has {len(out)} timestamps but {poses_path} has {n_poses} poses")
    _check_seconds(times_path, lines, out, "kitti times")
    return out, lines


# --------------------------------------------------------------------------------------------- writing


def write_trajectory(path: str | Path, traj: Trajectory, fmt: str, times_path: str | Path | None = None) -> None:
    """Write ``traj`` to ``path`` in ``fmt`` (``tum``, ``kitti`` or ``euroc``).

    Numbers are written with enough digits to round-trip float64 (``%.17g`` for TUM/KITTI values;
    EuRoC timestamps are rounded to integer nanoseconds). KITTI has no timestamps: pass
    ``times_path`` to also write them (one per line, seconds) next to the poses.
    """
    path = Path(path)
    if fmt not in FORMATS:
        raise FormatError(f"{path}: unknown trajectory format {fmt!r} (expected one of {', '.join(FORMATS)})")
    if times_path is not None and fmt != "kitti":
        raise FormatError(f"{path}: a times file is only written with the kitti format, not {fmt!r}")
    q_xyzw = traj.quaternions_xyzw()
    lines: list[str] = []
    if fmt == "tum":
        lines.append("# timestamp tx ty tz qx qy qz qw")
        for t, p, q in zip(traj.timestamps, traj.t_WC, q_xyzw):
            lines.append(" ".join(_g(v) for v in (t, *p, *q)))
    elif fmt == "kitti":
        for T in traj.T_WC:
            lines.append(" ".join(_g(v) for v in T[:3, :].ravel()))
    else:
        lines.append("#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []")
        for t, p, q in zip(traj.timestamps, traj.t_WC, q_xyzw):
            ns = _seconds_to_ns(float(t))
            lines.append(",".join([str(ns)] + [_g(v) for v in (*p, q[3], q[0], q[1], q[2])]))
    _write_text(path, "\n".join(lines) + "\n")
    if times_path is not None:
        _write_text(Path(times_path), "\n".join(_g(t) for t in traj.timestamps) + "\n")
    logger.debug("wrote %d poses to %s (%s)", len(traj), path, fmt)


def _g(value: float) -> str:
    return f"{float(value):.17g}"


def _seconds_to_ns(t: float) -> int:
    sec = np.floor(t)
    return int(sec) * NS_PER_S + int(round((t - sec) * NS_PER_S))


def _write_text(path: Path, text: str) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    except OSError as exc:
        raise DataError(f"{path}: cannot write: {exc}") from exc
