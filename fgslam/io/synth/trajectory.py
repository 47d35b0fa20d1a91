"""Smooth analytic body trajectories with exact velocities, accelerations and angular rates.

The body frame B (the IMU frame) has x forward, y left, z up at zero attitude; the world frame W has
z up. A trajectory is given by truncated Fourier series in time (period = sequence duration, so a
trajectory whose series has no linear term ends exactly where it starts)::

    f(t) = c0 + rate * t + sum_k a_k cos(k w t) + b_k sin(k w t),   w = 2 pi / period

for the body position ``p_WB = (x, y, z)`` and the ZYX Euler angles ``R_WB = Rz(yaw) Ry(pitch)
Rx(roll)`` (positive pitch = nose down). The yaw can instead follow the horizontal direction of
travel (``yaw = atan2(vy, vx)``, car-like). Angular rates use the exact ZYX kinematics
``w_B = [roll' - yaw' sin(pitch), pitch' cos(roll) + yaw' cos(pitch) sin(roll),
-pitch' sin(roll) + yaw' cos(pitch) cos(roll)]``.

A :class:`TimeWarp` makes the body stop and go on: the series are evaluated at a warped time
``tau(t)`` whose rate ``tau'`` ramps smoothly (smoothstep, so accelerations stay continuous) from 1
to 0, stays 0 during the stop and ramps back; velocities, accelerations and angular rates follow by
the chain rule (``v = p_tau tau'``, ``a = p_tau,tau tau'^2 + p_tau tau''``), so poses, stereo, depth
and IMU stay consistent, and at rest the IMU reads gravity only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Fourier1D:
    """Scalar truncated Fourier series plus a linear term; ``cos_coeffs[k-1]``/``sin_coeffs[k-1]``
    multiply harmonic k."""

    period: float
    c0: float = 0.0
    rate: float = 0.0
    cos_coeffs: tuple[float, ...] = ()
    sin_coeffs: tuple[float, ...] = ()

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Value, first and second time derivative at times ``t`` (float64 arrays, shape of t)."""
        t = np.asarray(t, np.float64)
        w = 2.0 * np.pi / self.period
        f = self.c0 + self.rate * t
        df = np.full_like(t, self.rate)
        ddf = np.zeros_like(t)
        n = max(len(self.cos_coeffs), len(self.sin_coeffs))
        ca = np.zeros(n)
        sb = np.zeros(n)
        ca[:len(self.cos_coeffs)] = self.cos_coeffs
        sb[:len(self.sin_coeffs)] = self.sin_coeffs
        for k in range(1, n + 1):
            a, b = ca[k - 1], sb[k - 1]
            if a == 0.0 and b == 0.0:
                continue
            kw = k * w
            c, s = np.cos(kw * t), np.sin(kw * t)
            f = f + a * c + b * s
            df = df + kw * (-a * s + b * c)
            ddf = ddf - kw * kw * (a * c + b * s)
        return f, df, ddf


@dataclass(frozen=True)
class TimeWarp:
    """Stop-and-go time warp: the body decelerates during ``[start - ramp, start]``, stands still
    for ``duration`` seconds, accelerates during ``[start + duration, start + duration + ramp]`` and
    then moves on along the path where it stopped (the motion after the stop is delayed by
    ``duration + ramp``)."""

    start: float  # seconds: the body is at rest from here
    duration: float  # seconds at rest
    ramp: float  # seconds of deceleration (and of acceleration)

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Warped time ``tau``, ``dtau/dt`` and ``d2tau/dt2`` at times ``t``."""
        t = np.asarray(t, np.float64)
        r, t0, t1 = self.ramp, self.start - self.ramp, self.start + self.duration
        x = np.clip((t - t0) / r, 0.0, 1.0)  # deceleration progress
        y = np.clip((t - t1) / r, 0.0, 1.0)  # acceleration progress
        # rate 1 - S(x) + S(y) with the smoothstep S(u) = 3u^2 - 2u^3, whose integral is u^3 - u^4 / 2
        tau = np.minimum(t, t0) + r * (x - (x ** 3 - x ** 4 / 2)) + r * (y ** 3 - y ** 4 / 2) + np.maximum(t - t1 - r, 0.0)
        dtau = 1.0 - (3 * x ** 2 - 2 * x ** 3) + (3 * y ** 2 - 2 * y ** 3)
        inside_x = (t > t0) & (t < t0 + r)
        inside_y = (t > t1) & (t < t1 + r)
        ddtau = (np.where(inside_x, -(6 * x - 6 * x ** 2), 0.0) + np.where(inside_y, 6 * y - 6 * y ** 2, 0.0)) / r
        return tau, dtau, ddtau


@dataclass(frozen=True)
class BodyState:
    """Body states at N times: ``p_WB``, ``v_WB``, ``a_WB`` (N, 3) world frame, ``R_WB`` (N, 3, 3),
    ``w_B`` (N, 3) angular velocity in the body frame (rad/s)."""

    t: np.ndarray
    p_WB: np.ndarray
    v_WB: np.ndarray
    a_WB: np.ndarray
    R_WB: np.ndarray
    w_B: np.ndarray

    def T_WB(self) -> np.ndarray:
        """(N, 4, 4) body-to-world poses."""
        T = np.tile(np.eye(4), (len(self.t), 1, 1))
        T[:, :3, :3] = self.R_WB
        T[:, :3, 3] = self.p_WB
        return T


def euler_zyx_to_R(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    R = np.empty(np.shape(yaw) + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def warped_time(warp: TimeWarp | None, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``tau(t)`` and its first two derivatives under ``warp`` (None: the identity)."""
    if warp is None:
        return t, np.ones_like(t), np.zeros_like(t)
    return warp.evaluate(t)


@dataclass(frozen=True)
class AnalyticTrajectory:
    """Body trajectory from Fourier series; ``yaw=None`` means yaw follows the direction of travel."""

    x: Fourier1D
    y: Fourier1D
    z: Fourier1D
    yaw: Fourier1D | None
    pitch: Fourier1D
    roll: Fourier1D
    warp: TimeWarp | None = None  # stop-and-go (None: the series' own time)

    def sample(self, t: np.ndarray) -> BodyState:
        t = np.asarray(t, np.float64)
        tau, dtau, ddtau = warped_time(self.warp, t)
        # derivatives with respect to tau, then the chain rule to t
        px, vx, ax = self.x.evaluate(tau)
        py, vy, ay = self.y.evaluate(tau)
        pz, vz, az = self.z.evaluate(tau)
        if self.yaw is None:
            yaw = np.arctan2(vy, vx)
            dyaw = (vx * ay - vy * ax) / (vx * vx + vy * vy)
        else:
            yaw, dyaw, _ = self.yaw.evaluate(tau)
        pitch, dpitch, _ = self.pitch.evaluate(tau)
        roll, droll, _ = self.roll.evaluate(tau)
        dyaw, dpitch, droll = dyaw * dtau, dpitch * dtau, droll * dtau
        ax, ay, az = (ax * dtau ** 2 + vx * ddtau, ay * dtau ** 2 + vy * ddtau, az * dtau ** 2 + vz * ddtau)
        vx, vy, vz = vx * dtau, vy * dtau, vz * dtau
        w_B = np.stack([
            droll - dyaw * np.sin(pitch),
            dpitch * np.cos(roll) + dyaw * np.cos(pitch) * np.sin(roll),
            -dpitch * np.sin(roll) + dyaw * np.cos(pitch) * np.cos(roll),
        ], axis=-1)
        return BodyState(t=t, p_WB=np.stack([px, py, pz], -1), v_WB=np.stack([vx, vy, vz], -1),
                         a_WB=np.stack([ax, ay, az], -1), R_WB=euler_zyx_to_R(yaw, pitch, roll),
                         w_B=w_B)


def closed_curve_fourier(points_xy: np.ndarray, n_harmonics: int, period: float
                         ) -> tuple[Fourier1D, Fourier1D]:
    """Fourier series (x(t), y(t)) of period ``period`` through a closed planar polyline sampled
    uniformly in arc length (``points_xy`` (M, 2), first point not repeated), truncated to
    ``n_harmonics``; t = 0 maps to the first point (up to the truncation)."""
    m = len(points_xy)
    out = []
    for dim in range(2):
        F = np.fft.rfft(points_xy[:, dim])
        k = np.arange(1, n_harmonics + 1)
        out.append(Fourier1D(period=period, c0=float(F[0].real / m),
                             cos_coeffs=tuple(2.0 * F[k].real / m),
                             sin_coeffs=tuple(-2.0 * F[k].imag / m)))
    return out[0], out[1]


def rounded_rectangle(half_x: float, half_y: float, radius: float, n_points: int) -> np.ndarray:
    """(n_points, 2) points uniformly in arc length around a rounded rectangle centred at the origin,
    counter-clockwise, starting at (0, -half_y) heading +x."""
    lx, ly = 2 * (half_x - radius), 2 * (half_y - radius)
    arc = 0.5 * np.pi * radius
    # segments: bottom (from the middle), corner, right, corner, top, corner, left, corner, bottom
    lengths = np.array([lx / 2, arc, ly, arc, lx, arc, ly, arc, lx / 2])
    ends = np.cumsum(lengths)
    s = np.arange(n_points) * (ends[-1] / n_points)
    pts = np.empty((n_points, 2))
    corners = [(half_x - radius, -half_y + radius, -0.5 * np.pi),
               (half_x - radius, half_y - radius, 0.0),
               (-half_x + radius, half_y - radius, 0.5 * np.pi),
               (-half_x + radius, -half_y + radius, np.pi)]
    starts = np.concatenate([[0.0], ends[:-1]])
    seg = np.searchsorted(ends, s, side="right").clip(0, 8)
    d = s - starts[seg]
    for i in range(9):
        m = seg == i
        di = d[m]
        if i == 0:
            pts[m] = np.stack([di, np.full_like(di, -half_y)], -1)
        elif i == 8:
            pts[m] = np.stack([-half_x + radius + di, np.full_like(di, -half_y)], -1)
        elif i % 2 == 1:
            cx, cy, a0 = corners[i // 2]
            ang = a0 + di / radius
            pts[m] = np.stack([cx + radius * np.cos(ang), cy + radius * np.sin(ang)], -1)
        else:
            side = i // 2 - 1  # 0 right (+y), 1 top (-x), 2 left (-y)
            if side == 0:
                pts[m] = np.stack([np.full_like(di, half_x), -half_y + radius + di], -1)
            elif side == 1:
                pts[m] = np.stack([half_x - radius - di, np.full_like(di, half_y)], -1)
            else:
                pts[m] = np.stack([np.full_like(di, -half_x), half_y - radius - di], -1)
    return pts


def _so3_exp(phi: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations ``exp([phi]x)`` of rotation vectors (N, 3) (Rodrigues)."""
    theta = np.linalg.norm(phi, axis=-1)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta ** 2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta ** 2 / 24.0, (1.0 - np.cos(safe)) / safe ** 2)
    K = np.zeros(phi.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -phi[..., 2], phi[..., 1], -phi[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = phi[..., 2], -phi[..., 1], phi[..., 0]
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def _so3_log(R: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors of rotations (N, 3, 3) with angles below pi (consecutive poses of a track)."""
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    small = theta < 1e-8
    scale = np.where(small, 0.5 + theta ** 2 / 12.0, theta / (2.0 * np.sin(np.where(small, 1.0, theta))))
    return scale[..., None] * v


_KNOT_SNAP = 1e-9  # knot intervals: a time this close to a knot is that knot (i * (1 / rate) / dt is not exactly i)


@dataclass(frozen=True, eq=False)
class PoseTrackTrajectory:
    """Body trajectory through given poses ``T_WB`` (N, 4, 4) at times ``i * dt`` (a recorded path such
    as a KITTI ground truth): position by a cubic Hermite spline with Catmull-Rom tangents
    (``(p[i+1] - p[i-1]) / 2 dt``, one-sided at the ends; continuous velocity, piecewise-linear
    acceleration), attitude by geodesic interpolation ``R_i exp(u log(R_i^T R_i+1))`` (constant body
    rate ``log(R_i^T R_i+1) / dt`` within a segment). The poses are met exactly at the knots; times
    outside ``[0, (N-1) dt]`` are clamped to the ends (at rest). Same interface as :class:`AnalyticTrajectory`."""

    T_WB_knots: np.ndarray
    dt: float
    warp: TimeWarp | None = None

    def sample(self, t: np.ndarray) -> BodyState:
        t = np.asarray(t, np.float64)
        tau, dtau, ddtau = warped_time(self.warp, t)
        P = self.T_WB_knots[:, :3, 3]
        R = self.T_WB_knots[:, :3, :3]
        n, dt = len(P), self.dt
        tangents = np.empty_like(P)
        if n > 1:
            tangents[1:-1] = (P[2:] - P[:-2]) / (2.0 * dt)
            tangents[0], tangents[-1] = (P[1] - P[0]) / dt, (P[-1] - P[-2]) / dt
        else:
            tangents[:] = 0.0
        x = np.clip(tau / dt, 0.0, n - 1)
        snapped = np.round(x)
        x = np.where(np.abs(x - snapped) < _KNOT_SNAP, snapped, x)  # frame times meet their knots exactly
        inside = (tau >= 0.0) & (tau <= (n - 1) * dt)
        i = np.floor(x).astype(np.int64)
        j = np.minimum(i + 1, n - 1)
        u = (x - i)[..., None]
        p0, p1, m0, m1 = P[i], P[j], tangents[i] * dt, tangents[j] * dt
        h00, h10, h01, h11 = 2 * u ** 3 - 3 * u ** 2 + 1, u ** 3 - 2 * u ** 2 + u, -2 * u ** 3 + 3 * u ** 2, u ** 3 - u ** 2
        p = h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1
        dp = ((6 * u ** 2 - 6 * u) * (p0 - p1) + (3 * u ** 2 - 4 * u + 1) * m0 + (3 * u ** 2 - 2 * u) * m1) / dt
        ddp = ((12 * u - 6) * (p0 - p1) + (6 * u - 4) * m0 + (6 * u - 2) * m1) / dt ** 2
        phi = _so3_log(np.einsum("nji,njk->nik", R[i], R[j]))
        R_WB = R[i] @ _so3_exp(u * phi)
        rate = inside.astype(np.float64)[..., None]  # at rest outside the track
        v = dp * dtau[..., None] * rate
        a = (ddp * dtau[..., None] ** 2 + dp * ddtau[..., None]) * rate
        w_B = phi / dt * dtau[..., None] * rate
        return BodyState(t=t, p_WB=p, v_WB=v, a_WB=a, R_WB=R_WB, w_B=w_B)
