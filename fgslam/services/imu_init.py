"""Initialisation of the IMU state (:mod:`fgslam.services.imu`): a still start from the first samples,
and the visual-inertial solve over a window of keyframes (gyroscope bias by Gauss-Newton on the
rotation residuals, then gravity, velocities and, for a monocular map, the metric scale by linear
least squares on the preintegrated velocity and position deltas, then again with ``|g|`` fixed).

Frames: ``g_W`` and the velocities are in the map's world frame (m/s^2, m/s); a window is a list of
``(t, kf_id)`` in time order with the keyframes' poses ``T_WC`` (gtsam ``Similarity3``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from ..backend.solver import NonlinearProblem, levenberg_marquardt
from ..factors.imu import ImuNoise, body_pose, combined_params
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
    import gtsam  # deferred: gtsam

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


# ----------------------------------------------------------------------------------------- inertial-only


def rotation_to_gravity_frame(gravity_W: np.ndarray) -> np.ndarray:
    """The smallest rotation ``R_GW`` taking the direction of ``gravity_W`` to ``-z`` (the gravity
    frame G of the inertial-only optimisation, where gravity is ``(0, 0, -|g|)``)."""
    a = np.asarray(gravity_W, dtype=np.float64) / np.linalg.norm(gravity_W)
    b = np.array([0.0, 0.0, -1.0])
    axis = np.cross(a, b)
    sin, cos = float(np.linalg.norm(axis)), float(a @ b)
    if sin < _BIAS_CONVERGED:  # parallel (or opposite: a half turn about x)
        return np.eye(3) if cos > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / sin
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + sin * K + (1 - cos) * K @ K


def inertial_only_factor(keys: tuple[int, int, int, int, int], pim, T_WB_i, T_WB_j, centres: tuple):
    """A factor on ``(log_scale, R_GW, v_i, v_j, b)`` (``Vector`` (1,), ``Rot3``, ``Point3`` velocities
    in the gravity frame G, one ``ConstantBias``) for the inertial-only optimisation: the error of
    gtsam's ``CombinedImuFactor(pim)`` (gravity ``-z`` of G in ``pim``'s params) at the body poses
    ``T_GB_k = Pose3(R_GW) * T_WB_k(s)`` with ``T_WB_k(s)`` the fixed visual pose whose camera centre
    is scaled: ``p_WB_k(s) = s c_k + R_WC_k t_CB`` (``s = exp(log_scale)``), biases ``b_i = b_j = b``.

    ``T_WB_i``, ``T_WB_j``: the body poses at scale 1 (``gtsam.Pose3``); ``t_CB_scaled``: the camera
    centres ``(c_i, c_j)`` in map units. Jacobians (chained through gtsam's): right perturbations,
    ``R_GW Exp(w)`` moves ``T_GB`` by ``Ad(T_WB^-1) [w, 0]``; ``d log_scale`` moves its position by
    ``s c`` in W, ``R_WB^T s c`` in the body frame (tested against finite differences)."""
    import gtsam  # deferred: gtsam

    inner = gtsam.CombinedImuFactor(0, 1, 2, 3, 4, 5, pim)
    unit = gtsam.noiseModel.Unit.Create(15)
    kl, kr, kvi, kvj, kb = (int(k) for k in keys)
    c_i, c_j = (np.asarray(c, dtype=np.float64) for c in centres)
    R_i, R_j = np.asarray(T_WB_i.rotation().matrix()), np.asarray(T_WB_j.rotation().matrix())
    p_i, p_j = np.asarray(T_WB_i.translation()), np.asarray(T_WB_j.translation())

    def body(R_GW, R_WB, p_WB, c, s):
        return gtsam.Pose3(R_GW, np.zeros(3)).compose(gtsam.Pose3(gtsam.Rot3(R_WB), p_WB + (s - 1.0) * c))

    def error(this, values, H):
        s = float(np.exp(values.atVector(kl)[0]))
        R_GW = values.atRot3(kr)
        bias = values.atConstantBias(kb)
        local = gtsam.Values()
        local.insert(0, body(R_GW, R_i, p_i, c_i, s))
        local.insert(1, values.atPoint3(kvi))
        local.insert(2, body(R_GW, R_j, p_j, c_j, s))
        local.insert(3, values.atPoint3(kvj))
        local.insert(4, bias)
        local.insert(5, bias)
        if H is None:
            return np.asarray(inner.whitenedError(local), dtype=np.float64)
        A, b = inner.linearize(local).jacobian()
        A = np.asarray(A)
        A_pi, A_pj = A[:, 0:6], A[:, 9:15]
        J_i, J_j = np.zeros((6, 1)), np.zeros((6, 1))
        J_i[3:, 0] = R_i.T @ (s * c_i)
        J_j[3:, 0] = R_j.T @ (s * c_j)
        Ad_i = np.asarray(gtsam.Pose3(gtsam.Rot3(R_i), p_i + (s - 1.0) * c_i).inverse().AdjointMap())[:, :3]
        Ad_j = np.asarray(gtsam.Pose3(gtsam.Rot3(R_j), p_j + (s - 1.0) * c_j).inverse().AdjointMap())[:, :3]
        H[0] = A_pi @ J_i + A_pj @ J_j
        H[1] = A_pi @ Ad_i + A_pj @ Ad_j
        H[2] = A[:, 6:9]
        H[3] = A[:, 15:18]
        H[4] = A[:, 18:24] + A[:, 24:30]
        return -np.asarray(b, dtype=np.float64)

    return gtsam.CustomFactor(unit, [kl, kr, kvi, kvj, kb], error)


@dataclass(frozen=True)
class InertialOnlyResult:
    """The inertial-only optimisation's estimate: the scale to apply to the map (``s``, map units -> m)
    with the marginal standard deviation of ``log s``, gravity in the map frame, the velocities (n, 3)
    of the window's keyframes (m/s, map frame, after the rescale) and the one bias; ``cost`` before/after."""

    scale: float
    log_scale_sigma: float
    gravity_W: np.ndarray
    velocities: np.ndarray
    bias: object
    initial_cost: float
    final_cost: float


def solve_inertial_only(window: Sequence[tuple[float, int]], poses: Sequence, T_CB, buffer: ImuBuffer,
                        config: ImuServiceConfig, noise: ImuNoise, metric: bool, gravity_W: np.ndarray,
                        velocities_W: np.ndarray, bias, settings) -> Optional["InertialOnlyResult"]:
    """ORB-SLAM3's inertial-only optimisation over ``window`` (list of (t, kf)) with the keyframes'
    visual poses ``poses`` (``T_WC`` Similarity3 each) held: the log-scale (held by a tight prior on a
    metric map), the gravity direction (``R_GW``, its yaw about gravity held by ``gauge_sigma``), the
    velocities and one bias (prior ``init.inertial_only_*_bias_sigma`` about ``bias``), with gtsam's preintegrated
    ``CombinedImuFactor`` (:func:`inertial_only_factor`) between consecutive keyframes, solved by the
    one LM loop with ``settings``. ``velocities_W`` (n, 3): the start (m/s, map frame). None when
    the window is too short or the solve fails (logged)."""
    import gtsam  # deferred: gtsam

    ic = config.init
    n = len(window)
    if n < 3:
        return None
    G = config.gravity
    params = combined_params(np.array([0.0, 0.0, -G]), noise)
    ts = [t for t, _ in window]
    T_WB = [body_pose(S, T_CB) for S in poses]
    c = [float(S.scale()) * np.asarray(S.translation(), dtype=np.float64) for S in poses]
    R_GW = rotation_to_gravity_frame(gravity_W)
    L, RG, B = gtsam.symbol("l", 0), gtsam.symbol("g", 0), gtsam.symbol("b", 0)
    V = [gtsam.symbol("v", i) for i in range(n)]
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    values.insert(L, np.zeros(1))
    values.insert(RG, gtsam.Rot3(R_GW))
    values.insert(B, bias)
    for i in range(n):
        values.insert(V[i], R_GW @ np.asarray(velocities_W[i], dtype=np.float64))
    for i in range(n - 1):
        pim = buffer.preintegrate(params, ts[i], ts[i + 1], bias)
        graph.add(inertial_only_factor((L, RG, V[i], V[i + 1], B), pim, T_WB[i], T_WB[i + 1], (c[i], c[i + 1])))
    bias_sigmas = np.array([ic.inertial_only_accel_bias_sigma] * 3 + [ic.inertial_only_gyro_bias_sigma] * 3)
    graph.add(gtsam.PriorFactorConstantBias(B, bias, gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas)))
    # gauge: the yaw about gravity is unobservable; R_GW Exp(w) turns about G's z by (R_GW^T e_z) . w
    up = R_GW.T @ np.array([0.0, 0.0, 1.0])
    info = np.outer(up, up) / ic.inertial_only_gauge_sigma ** 2 + np.eye(3) * ic.inertial_only_gravity_prior ** -2
    graph.add(gtsam.PriorFactorRot3(RG, gtsam.Rot3(R_GW), gtsam.noiseModel.Gaussian.Information(info)))
    log_scale_sigma = ic.inertial_only_gauge_sigma if metric else ic.inertial_only_log_scale_prior
    graph.add(gtsam.PriorFactorVector(L, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, log_scale_sigma)))
    problem = NonlinearProblem(graph, values)
    report = levenberg_marquardt(problem, settings)
    out = problem.values
    try:
        sigma = float(np.sqrt(gtsam.Marginals(graph, out).marginalCovariance(L)[0, 0]))
    except RuntimeError as exc:  # indeterminate system: no uncertainty, no result
        logger.info("IMU: inertial-only optimisation: no marginal of the scale (%s)", exc)
        return None
    R = np.asarray(out.atRot3(RG).matrix())
    s = float(np.exp(out.atVector(L)[0]))
    v_W = np.array([R.T @ np.asarray(out.atPoint3(V[i])) for i in range(n)])
    return InertialOnlyResult(scale=s, log_scale_sigma=sigma, gravity_W=R.T @ np.array([0.0, 0.0, -G]),
                              velocities=v_W, bias=out.atConstantBias(B), initial_cost=float(report.initial_cost),
                              final_cost=float(report.final_cost))
