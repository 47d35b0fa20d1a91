"""Initialisation of the IMU state (:mod:`fgslam.services.imu`): a still start from the first samples,
and the visual-inertial solve over a window of keyframes (gyroscope bias by Gauss-Newton on the
rotation residuals, then gravity, velocities and, for a monocular map, the metric scale by linear
least squares on the preintegrated velocity and position deltas, then again with ``|g|`` fixed).

Frames: ``g_W`` and the velocities are in the map's world frame (m/s^2, m/s); a window is a list of
``(t, kf_id)`` in time order with the keyframes' poses ``T_WC`` (gtsam ``Similarity3``).
"""

from __future__ import annotations

import logging
from typing import Optional, Sequence

import numpy as np

from ..factors.imu import ImuNoise, combined_params
from .imu_samples import ImuBuffer, ImuServiceConfig, StaticInit, log_so3

logger = logging.getLogger(__name__)

_MIN_STATIC_SAMPLES = 3  # samples a still start needs at least
_BIAS_STEP = 1e-6  # rad/s: forward-difference step of the gyroscope-bias Jacobian
_BIAS_CONVERGED = 1e-9  # rad/s: Gauss-Newton stops once no bias component moves more
_MIN_INTERVAL_S = 1e-3  # s: floor of the interval that weights a position row


def detect_static(buffer: ImuBuffer, config: ImuServiceConfig) -> Optional[StaticInit]:
    """A still start from the first ``init.static_window_s`` of ``buffer`` (its chunk means agree):
    gyroscope bias = mean rate, gravity in the body frame = -mean specific force; None when the window
    holds a bad interval, too few samples, or motion (logged)."""
    ic = config.init
    t0 = buffer.first_t
    sel = (buffer.t >= t0) & (buffer.t <= t0 + ic.static_window_s)
    if any(a < t0 + ic.static_window_s and b > t0 for a, b in buffer.bad) or sel.sum() < _MIN_STATIC_SAMPLES:
        return None
    g, a = buffer.gyro[sel], buffer.accel[sel]
    chunks = np.array_split(np.arange(g.shape[0]), min(ic.static_chunks, g.shape[0]))
    g_spread = float(np.std([g[c].mean(axis=0) for c in chunks], axis=0).max())
    a_spread = float(np.std([a[c].mean(axis=0) for c in chunks], axis=0).max())
    if g_spread > ic.static_gyro_std or a_spread > ic.static_accel_std:
        logger.info("IMU: the start is not still (chunk means spread %.4f rad/s, %.3f m/s^2): no static initialisation",
                    g_spread, a_spread)
        return None
    f = a.mean(axis=0)
    static = StaticInit(t=float(buffer.t[sel][-1]), gyro_bias=g.mean(axis=0),
                        gravity_B=-config.gravity * f / np.linalg.norm(f))
    logger.info("IMU: static initialisation: gyroscope bias %s rad/s, |f| %.3f m/s^2",
                np.round(static.gyro_bias, 5), float(np.linalg.norm(f)))
    return static


def spaced(window: Sequence[tuple[float, int]], spacing_s: float) -> list[tuple[float, int]]:
    """The ``(t, kf_id)`` of ``window`` at least ``spacing_s`` apart, from the newest back (time order)."""
    kept = [window[-1]]
    for item in reversed(window[:-1]):
        if kept[-1][0] - item[0] >= spacing_s:
            kept.append(item)
    return kept[::-1]


def solve_visual_inertial(window: Sequence[tuple[float, int]], poses: Sequence, T_CB, buffer: ImuBuffer,
                          config: ImuServiceConfig, noise: ImuNoise, metric: bool, static: Optional[StaticInit],
                          gravity_W: Optional[np.ndarray] = None):
    """Gravity ``g_W``, scale, velocities (n, 3) and gyroscope bias of ``window`` (list of (t, kf)) with
    the keyframes' poses ``poses`` (``T_WC`` each) and the camera-to-body ``T_CB``; ``gravity_W`` given:
    only the scale and velocities are solved. None when implausible (logged)."""
    import gtsam

    ic = config.init
    G = config.gravity
    R_WB = []
    c = []
    R_WC = []
    for S in poses:
        R = np.asarray(S.rotation().matrix())
        R_WC.append(R)
        R_WB.append(R @ np.asarray(T_CB.rotation().matrix()))
        c.append(float(S.scale()) * np.asarray(S.translation()))
    ts = [t for t, _ in window]
    n = len(window)
    # gyroscope bias: Gauss-Newton on Log(dR(bg)^T R_i^T R_j) with numeric Jacobians
    bg = static.gyro_bias.copy() if static is not None else np.zeros(3)

    def residuals(bg):
        out = []
        for i in range(n - 1):
            dR = buffer.rotation_between(ts[i], ts[i + 1], bg)
            out.append(log_so3(dR.T @ R_WB[i].T @ R_WB[i + 1]))
        return np.concatenate(out)

    for _ in range(ic.gyro_bias_iterations):
        r0 = residuals(bg)
        J = np.zeros((r0.size, 3))
        eps = _BIAS_STEP
        for k in range(3):
            d = np.zeros(3)
            d[k] = eps
            J[:, k] = (residuals(bg + d) - r0) / eps
        step = np.linalg.lstsq(J, -r0, rcond=None)[0]
        bg = bg + step
        if np.abs(step).max() < _BIAS_CONVERGED:
            break
    bias = gtsam.imuBias.ConstantBias(np.zeros(3), bg)
    t_CB = np.asarray(T_CB.translation())
    params = combined_params(np.zeros(3), noise)  # gravity is an unknown: preintegrate without it
    pims = [buffer.preintegrate(params, ts[i], ts[i + 1], bias) for i in range(n - 1)]

    def solve(g_known: Optional[np.ndarray]):
        nv = 3 * n
        cols = nv + (0 if g_known is not None else 3) + (0 if metric else 1)
        rows, rhs = [], []
        for i, pim in enumerate(pims):
            dt = pim.deltaTij()
            Ri = R_WB[i]
            dp = Ri @ np.asarray(pim.deltaPij())
            dv = Ri @ np.asarray(pim.deltaVij())
            lever = (R_WC[i + 1] - R_WC[i]) @ t_CB
            # s (c_j - c_i) - v_i dt - 0.5 g dt^2 = dp - lever ;  v_j - v_i - g dt = dv
            A1 = np.zeros((3, cols))
            A2 = np.zeros((3, cols))
            A1[:, 3 * i:3 * i + 3] = -dt * np.eye(3)
            A2[:, 3 * i:3 * i + 3] = -np.eye(3)
            A2[:, 3 * (i + 1):3 * (i + 1) + 3] = np.eye(3)
            b1 = dp - lever
            b2 = dv.copy()
            if g_known is None:
                A1[:, nv:nv + 3] = -0.5 * dt * dt * np.eye(3)
                A2[:, nv:nv + 3] = -dt * np.eye(3)
            else:
                b1 = b1 + 0.5 * dt * dt * g_known
                b2 = b2 + dt * g_known
            if metric:
                b1 = b1 - (c[i + 1] - c[i])
            else:
                A1[:, -1] = c[i + 1] - c[i]
            w = 1.0 / max(dt, _MIN_INTERVAL_S)  # position rows per unit time, like the velocity rows
            rows += [w * A1, A2]
            rhs += [w * b1, b2]
        A, b = np.vstack(rows), np.concatenate(rhs)
        x = np.linalg.lstsq(A, b, rcond=None)[0]
        v = x[:nv].reshape(n, 3)
        g = g_known if g_known is not None else x[nv:nv + 3]
        s = 1.0 if metric else float(x[-1])
        sigma_s = 0.0
        if not metric:  # least-squares standard deviation of the scale
            dof = max(A.shape[0] - A.shape[1], 1)
            var = float(np.sum((A @ x - b) ** 2)) / dof
            sigma_s = float(np.sqrt(var * np.linalg.pinv(A.T @ A)[-1, -1]))
        return v, g, s, sigma_s

    if gravity_W is not None:
        g_W = np.asarray(gravity_W, dtype=np.float64)
    elif static is not None:
        R_BsB0 = buffer.rotation_between(static.t, ts[0], bg)
        g_W = R_WB[0] @ R_BsB0.T @ static.gravity_B
    else:
        _, g_free, s_free, _ = solve(None)
        if abs(np.linalg.norm(g_free) - G) > ic.gravity_tolerance * G:
            logger.info("IMU: visual-inertial initialisation rejected: |g| = %.3f m/s^2 (scale %.4g); retrying",
                        float(np.linalg.norm(g_free)), s_free)
            return None
        g_W = G * g_free / np.linalg.norm(g_free)
    v, g_W, s, sigma_s = solve(g_W)
    if not metric and not (ic.min_scale <= s <= ic.max_scale and sigma_s < ic.max_scale_rel_sigma * s):
        logger.info("IMU: visual-inertial initialisation rejected: scale %.4g +- %.2g; retrying", s, sigma_s)
        return None
    logger.info("IMU: visual-inertial initialisation over %d keyframes (%.2f s): scale %.4f, gyroscope bias %s",
                n, ts[-1] - ts[0], s, np.round(bg, 5))
    return g_W, s, v, bg
