"""Plausibility checks of a dataset's IMU stream before a visual-inertial run (docs/architecture.md section 13).

A stream in the wrong units, with swapped columns or on another clock does not fail loudly: the
initialisation just never converges, or converges to a wrong scale. :func:`check_imu_stream` looks at
the whole stream once, before the first frame, and names the likely mistake:

- **clock / time units**: the IMU samples must cover the frames' time span (``min_coverage``); a span
  ratio near 1e3 or 1e-3 points at micro- or milliseconds written as nanoseconds;
- **rate**: the median sample rate must give at least ``min_samples_per_frame`` samples per frame
  interval and lie in ``[min_rate_hz, max_rate_hz]``;
- **accelerometer units**: the median specific-force magnitude over the first ``window_s`` seconds
  (at rest it is gravity; a hand-held or flying start adds accelerations that average out) must be
  within ``gravity_tolerance`` (relative) of ``imu.gravity``; a median near 1 means g instead of m/s^2;
- **gyroscope units**: the ``gyro_percentile``-th percentile of the rate magnitude must stay below
  ``max_gyro_rate`` (beyond any hand-held or vehicle motion); far above it, with the same divided by
  57.3 plausible, means deg/s instead of rad/s;
- **swapped columns**: a gyroscope reading about gravity's magnitude and an accelerometer near zero;
- **axes** (with the camera-IMU rotation): the mean specific force of the first window (up, at rest)
  seen in the camera frame more than ``max_up_angle_deg`` from the image's up direction (``-y``): a
  camera held upside down or looking straight down, or (more often) IMU axes or ``T_BC`` wrong; a warning.

A recognised mistake raises :class:`~fgslam.core.errors.DataError` naming it (``on_mistake: error``) or is
logged as a warning (``warn``); an implausible value without a recognised cause is a warning. The
findings are returned (``summary.json`` ``inertial.input_warnings``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal, Optional

import numpy as np

from ..core.config import MAX_SCALAR, check_ranges, ranged
from ..core.errors import ConfigError, DataError

logger = logging.getLogger(__name__)

DEG_PER_RAD = 180.0 / np.pi
# span ratios (frames / IMU) of the usual time-unit mistakes: micro- or milliseconds read as nanoseconds
_TIME_UNIT_RATIOS = {
    1e3: "IMU timestamps likely in microseconds, not nanoseconds",
    1e6: "IMU timestamps likely in milliseconds, not nanoseconds",
    1e-3: "the frames' timestamps likely in microseconds, not nanoseconds (or the IMU's 1000x too large)",
}
_TIME_UNIT_TOLERANCE = 0.5  # |log10(ratio / unit ratio)| below this names the unit mistake


@dataclass
class ImuCheckConfig:
    """Plausibility checks of the IMU stream before a run (YAML ``imu.checks``; module docstring)."""

    enabled: bool = True  # run the checks before the run (false: trust the IMU stream as it is)
    on_mistake: Literal["error", "warn"] = "error"  # a recognised mistake (units, swapped columns, clock): error or warning
    window_s: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # s: the first seconds of samples the magnitude checks read
    gravity_tolerance: float = ranged(0.25, gt=0, lt=1)  # relative: median |a| of the window within this of imu.gravity
    g_units_tolerance: float = ranged(0.25, gt=0, lt=1)  # relative: median |a| within this of 1 reads as "in g"
    max_gyro_rate: float = ranged(15.0, gt=0, le=MAX_SCALAR)  # rad/s: beyond any hand-held or vehicle motion (~860 deg/s)
    gyro_percentile: float = ranged(99.0, gt=0, le=100)  # percentile of |w| over the stream compared with max_gyro_rate
    swapped_accel_max: float = ranged(2.0, ge=0, le=MAX_SCALAR)  # m/s^2: an "accelerometer" this quiet beside a gravity-sized "gyroscope": swapped
    min_coverage: float = ranged(0.5, gt=0, le=1)  # share of the frames' time span the IMU samples must cover
    min_samples_per_frame: float = ranged(2.0, gt=0, le=MAX_SCALAR)  # IMU samples per frame interval (median rates)
    max_up_angle_deg: float = ranged(60.0, gt=0, le=180)  # deg between the measured up direction (camera frame) and the image's up (a camera pitched further is warned about)
    min_rate_hz: float = ranged(20.0, gt=0, le=MAX_SCALAR)  # Hz: the lowest plausible IMU rate
    max_rate_hz: float = ranged(10000.0, gt=0, le=MAX_SCALAR)  # Hz: the highest plausible IMU rate

    def validate(self) -> None:
        check_ranges(self)
        if self.min_rate_hz > self.max_rate_hz:
            raise ConfigError(f"imu.checks: min_rate_hz ({self.min_rate_hz:g}) must be <= max_rate_hz "
                              f"({self.max_rate_hz:g})")


@dataclass(frozen=True)
class ImuFinding:
    """One check's result: which check, whether it names a recognised mistake, the message."""

    check: str
    mistake: bool
    message: str


def _median_rate(t: np.ndarray) -> Optional[float]:
    dt = np.diff(t)
    dt = dt[dt > 0]
    return None if dt.size == 0 else float(1.0 / np.median(dt))


def find_imu_problems(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, frame_t: np.ndarray,
                      config: ImuCheckConfig, gravity: float, R_CB: Optional[np.ndarray] = None) -> list[ImuFinding]:
    """The findings of every check (module docstring) on samples ``t`` (s), ``gyro`` (rad/s),
    ``accel`` (m/s^2) against frame times ``frame_t`` (s), with the body-to-camera rotation ``R_CB``
    (None: no axes check); empty when the stream looks right."""
    out: list[ImuFinding] = []
    t = np.asarray(t, np.float64)
    gyro = np.asarray(gyro, np.float64).reshape(-1, 3)
    accel = np.asarray(accel, np.float64).reshape(-1, 3)
    frame_t = np.asarray(frame_t, np.float64)
    if t.size < 2:
        return [ImuFinding("rate", True, f"{t.size} IMU sample(s): too few for a visual-inertial run")]
    # clock and rate
    if frame_t.size >= 2:
        f0, f1 = float(frame_t[0]), float(frame_t[-1])
        overlap = max(0.0, min(f1, float(t[-1])) - max(f0, float(t[0])))
        coverage = overlap / (f1 - f0) if f1 > f0 else 1.0
        if coverage < config.min_coverage:
            ratio = (f1 - f0) / max(float(t[-1] - t[0]), 1e-12)
            unit = next((name for r, name in _TIME_UNIT_RATIOS.items()
                         if abs(np.log10(ratio / r)) < _TIME_UNIT_TOLERANCE), None)
            hint = (f"; the frames span {ratio:.3g}x the IMU's time: {unit}"
                    if unit else "; IMU and camera timestamps are likely on different clocks or in different units")
            out.append(ImuFinding("clock", True, f"the IMU samples ({t[0]:.3f}..{t[-1]:.3f} s) cover "
                                  f"{100 * coverage:.0f} % of the frames' time span ({f0:.3f}..{f1:.3f} s){hint}"))
        rate = _median_rate(t)
        frame_rate = _median_rate(frame_t)
        if rate is not None and frame_rate is not None and rate < config.min_samples_per_frame * frame_rate:
            out.append(ImuFinding("rate", False, f"IMU rate {rate:.1f} Hz (median sample interval) gives "
                                  f"{rate / frame_rate:.2f} samples per frame interval at {frame_rate:.1f} Hz "
                                  f"(at least {config.min_samples_per_frame:g} expected): a subsampled stream or "
                                  "wrong timestamps; preintegration between keyframes will be coarse"))
        if rate is not None and not config.min_rate_hz <= rate <= config.max_rate_hz:
            out.append(ImuFinding("rate", False, f"IMU rate {rate:.1f} Hz outside the plausible "
                                  f"{config.min_rate_hz:g}..{config.max_rate_hz:g} Hz: timestamps in the wrong unit?"))
    # magnitudes over the first window_s seconds
    first = t <= t[0] + config.window_s
    a_norm = float(np.median(np.linalg.norm(accel[first], axis=1)))
    w_norm_first = float(np.median(np.linalg.norm(gyro[first], axis=1)))
    w_high = float(np.percentile(np.linalg.norm(gyro, axis=1), config.gyro_percentile))
    if abs(w_norm_first - gravity) < config.gravity_tolerance * gravity and a_norm < config.swapped_accel_max:
        out.append(ImuFinding("axes", True, f"the gyroscope reads {w_norm_first:.2f} (about gravity's {gravity:g} "
                              f"m/s^2) and the accelerometer {a_norm:.2f} over the first {config.window_s:g} s: "
                              "gyroscope and accelerometer columns are likely swapped (expected "
                              "t, w_x, w_y, w_z [rad/s], a_x, a_y, a_z [m/s^2])"))
        return out
    if abs(a_norm - gravity) > config.gravity_tolerance * gravity:
        if abs(a_norm - 1.0) < config.g_units_tolerance:
            out.append(ImuFinding("accel_units", True, f"median specific force {a_norm:.3f} over the first "
                                  f"{config.window_s:g} s (gravity is {gravity:g} m/s^2): the accelerometer is "
                                  f"likely in g, not m/s^2 (multiply by {gravity:g})"))
        else:
            out.append(ImuFinding("accel_units", False, f"median specific force {a_norm:.3f} m/s^2 over the first "
                                  f"{config.window_s:g} s, far from gravity ({gravity:g} m/s^2, tolerance "
                                  f"{100 * config.gravity_tolerance:.0f} %): wrong accelerometer scale or units, or a "
                                  "start in free fall or under strong acceleration"))
    up_B = accel[first].mean(axis=0)
    if R_CB is not None and np.linalg.norm(up_B) > 0:
        up_C = np.asarray(R_CB, np.float64) @ up_B
        angle = float(np.degrees(np.arccos(np.clip(-up_C[1] / np.linalg.norm(up_C), -1.0, 1.0))))
        if angle > config.max_up_angle_deg:
            out.append(ImuFinding("axes", False, f"the mean specific force of the first {config.window_s:g} s "
                                  f"(up, at rest) is {angle:.0f} deg from the image's up direction in the camera "
                                  "frame: IMU axes or the camera-IMU transform T_BC likely wrong (or the camera "
                                  "starts upside down or looking straight down)"))
    if w_high > config.max_gyro_rate:
        as_rad = w_high / DEG_PER_RAD
        likely = (f": the gyroscope is likely in deg/s, not rad/s ({as_rad:.2f} rad/s if so)"
                  if as_rad <= config.max_gyro_rate else ": wrong gyroscope scale or units")
        out.append(ImuFinding("gyro_units", as_rad <= config.max_gyro_rate,
                              f"gyroscope rate {w_high:.1f} rad/s ({config.gyro_percentile:g}th percentile) beyond "
                              f"any hand-held or vehicle motion ({config.max_gyro_rate:g} rad/s){likely}"))
    return out


def check_imu_stream(imu, frame_t: np.ndarray, config: ImuCheckConfig, gravity: float,
                     where: str = "the dataset", T_BC: Optional[np.ndarray] = None) -> list[str]:
    """Run :func:`find_imu_problems` on ``imu`` (:class:`fgslam.io.frame.ImuSamples`; ``T_BC`` the
    calibration's camera-to-body transform, None: no axes check): a recognised
    mistake raises DataError with ``on_mistake: error``; the other findings are logged as warnings.
    Returns the messages (nothing when ``config.enabled`` is off or there is no stream)."""
    if not config.enabled or imu is None:
        return []
    R_CB = None if T_BC is None else np.asarray(T_BC, np.float64)[:3, :3].T
    findings = find_imu_problems(imu.timestamps, imu.gyro, imu.accel, frame_t, config, gravity, R_CB)
    mistakes = [f for f in findings if f.mistake]
    if mistakes and config.on_mistake == "error":
        raise DataError(f"the IMU stream of {where} looks wrong: " + "; ".join(f.message for f in mistakes)
                        + " (imu.checks.on_mistake=warn runs anyway)")
    for f in findings:
        logger.warning("IMU input (%s): %s", f.check, f.message)
    return [f.message for f in findings]
