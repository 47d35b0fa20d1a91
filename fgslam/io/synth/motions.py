"""Body motions of the synthetic generator's presets (:mod:`.scenarios`): :func:`build_trajectory`.

The analytic motions are truncated Fourier series (:class:`.trajectory.AnalyticTrajectory`) whose
wobble comes from the harmonic tables of ``data/motions.yaml`` (:func:`.tables.motion_tables`), scaled
by the preset's ``jitter``; rotation-sweep's roll / pitch / yaw table is scaled to the mean angular
speed ``rotation_speed_deg_s`` (:func:`sweep_rotation_scale`). kitti00-drive plays the poses of a KITTI
ground-truth file (:func:`kitti_camera_poses`, read when the trajectory or the scene is built).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from ...core.errors import ConfigError, DataError
from ..trajectory import read_trajectory
from .scenarios import KittiDriveConfig, PanelRoomConfig, RotationSweepConfig, SynthConfig, camera_mount
from .tables import Harmonics, motion_tables
from .trajectory import (AnalyticTrajectory, Fourier1D, PoseTrackTrajectory, TimeWarp, closed_curve_fourier,
                         rounded_rectangle)

_ROAD_SAMPLES = 8192  # arc-length samples of the rounded rectangle fitted by the Fourier road
_SWEEP_SPEED_SAMPLES = 4096     # samples of one period for scaling the sweep to its mean angular speed
_SWEEP_SPEED_ITERATIONS = 50    # fixed-point steps of that scale at most
_SWEEP_SPEED_TOLERANCE = 1e-13  # relative error of the mean angular speed accepted
_SWEEP_MAX_SCALE = 10.0         # largest scale of the base amplitudes (angles beyond it wrap the attitude)
_MIN_TURN_DEG = 1e-3            # panel-room: a smaller turn_deg is treated as this (the ellipse period stays finite)
_ROOM_YAW_OFFSET = 0.5 * np.pi + 0.6  # rad: view direction relative to the radial direction at t=0
_ROOM_MEAN_PITCH = 0.1                # rad, slightly looking down (positive pitch = nose down)
_SWEEP_MEAN_PITCH = 0.15  # rad, nose down
# world frame of the drive from KITTI's: KITTI's world is its first camera frame (x right, y down, z forward);
# ours has z up: x = KITTI z (forward at the start), y = -KITTI x, z = -KITTI y (the nominal camera mount)
R_W_KITTI = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def kitti_poses_path(kc: KittiDriveConfig) -> Path:
    """The pose file of ``kc.poses`` ("": the repository's ``../shared/data/kitti_gt/00.txt``)."""
    if kc.poses:
        return Path(kc.poses).expanduser()
    return Path(__file__).resolve().parents[4] / "shared" / "data" / "kitti_gt" / "00.txt"


def load_kitti_poses(path: Path) -> np.ndarray:
    """(N, 4, 4) ``T_K0Ci`` of a KITTI pose file (12 numbers per line: the 3x4 camera-to-world matrix),
    read by :func:`fgslam.io.trajectory.read_trajectory` (its format errors name the file and line)."""
    if not path.is_file():
        raise DataError(f"kitti_drive.poses: KITTI pose file {path} not found (the kitti00-drive preset follows "
                        "a KITTI ground-truth path: set kitti_drive.poses=FILE, e.g. kitti_gt/00.txt of the shared data)")
    T = read_trajectory(path, "kitti").T_WC
    if len(T) < 2:
        raise DataError(f"{path}: expected at least 2 KITTI poses, got {len(T)}")
    return T


def kitti_camera_poses(cfg: SynthConfig) -> np.ndarray:
    """(N, 4, 4) ``T_WC`` of every row of the preset's pose file in the generator's world (z up, the
    road under the first camera at z = 0): ``T_WC = T_WK T_K0Ci`` with ``T_WK = [R_W_KITTI | (0, 0,
    camera_height)]``; a ConfigError when ``frames`` exceeds the rows."""
    kc = cfg.kitti_drive
    T_KC = load_kitti_poses(kitti_poses_path(kc))
    if cfg.frames > len(T_KC):
        raise ConfigError(f"frames: {cfg.frames} frames asked but {kitti_poses_path(kc)} has {len(T_KC)} poses")
    T_WK = np.eye(4)
    T_WK[:3, :3] = R_W_KITTI
    T_WK[2, 3] = kc.camera_height
    return T_WK @ T_KC


def _coeffs(terms: Harmonics, scale: float = 1.0, base: Harmonics | None = None) -> tuple[float, ...]:
    """Coefficient tuple (harmonics 1..K) from {k: amplitude} (times ``scale``) plus ``base``."""
    merged = {k: scale * a for k, a in terms.items()}
    for k, a in (base or {}).items():
        merged[k] = merged.get(k, 0.0) + a
    out = [0.0] * max(merged, default=0)
    for k, a in merged.items():
        out[k - 1] = a
    return tuple(out)


def build_trajectory(cfg: SynthConfig) -> AnalyticTrajectory | PoseTrackTrajectory:
    """Body trajectory of the preset (deterministic; period = the preset's loop duration), with the
    stop of ``stop_frame`` / ``stop_frames`` / ``stop_ramp_s`` as a time warp when ``stop_frames > 0``."""
    trajectory = _preset_trajectory(cfg)
    if cfg.stop_frames == 0:
        return trajectory
    rate = cfg.camera.rate_hz
    return replace(trajectory, warp=TimeWarp(start=cfg.stop_frame / rate, duration=cfg.stop_frames / rate,
                                             ramp=cfg.stop_ramp_s))


def _preset_trajectory(cfg: SynthConfig) -> AnalyticTrajectory | PoseTrackTrajectory:
    if cfg.preset == "kitti00-drive":  # the body carries cam0 at camera_mount: T_WB = T_WC T_BS0^-1
        T_WB = kitti_camera_poses(cfg) @ np.linalg.inv(camera_mount(cfg.camera))
        return PoseTrackTrajectory(T_WB_knots=T_WB, dt=1.0 / cfg.camera.rate_hz)
    T = cfg.loop_duration_s()
    turn = 2 * np.pi / T  # one full turn of yaw per loop
    if cfg.preset in ("room-loop", "low-texture"):
        rc, w = (cfg.room if cfg.preset == "room-loop" else cfg.low_texture), motion_tables()["room"]
        j = rc.jitter
        rx, ry = rc.path_radii
        return AnalyticTrajectory(
            x=Fourier1D(T, cos_coeffs=_coeffs(w["x_cos"], j, {1: rx}), sin_coeffs=_coeffs(w["x_sin"], j)),
            y=Fourier1D(T, cos_coeffs=_coeffs(w["y_cos"], j), sin_coeffs=_coeffs(w["y_sin"], j, {1: ry})),
            z=Fourier1D(T, c0=rc.height, sin_coeffs=_coeffs(w["z_sin"], j)),
            yaw=Fourier1D(T, c0=_ROOM_YAW_OFFSET, rate=turn, cos_coeffs=_coeffs(w["yaw_cos"], j),
                          sin_coeffs=_coeffs(w["yaw_sin"], j)),
            pitch=Fourier1D(T, c0=_ROOM_MEAN_PITCH, sin_coeffs=_coeffs(w["pitch_sin"], j)),
            roll=Fourier1D(T, cos_coeffs=_coeffs(w["roll_cos"], j), sin_coeffs=_coeffs(w["roll_sin"], j)),
        )
    if cfg.preset == "panel-room":
        return _panel_room_trajectory(cfg.panel_room)
    if cfg.preset == "rotation-sweep":
        rs = cfg.rotation_sweep
        scale = sweep_rotation_scale(rs)
        return _sweep_trajectory(rs, scale)
    if cfg.preset == "street-loop":
        sc, w = cfg.street, motion_tables()["street"]
        j = sc.jitter
        pts = rounded_rectangle(sc.half_size[0], sc.half_size[1], sc.corner_radius, _ROAD_SAMPLES)
        fx, fy = closed_curve_fourier(pts, sc.harmonics, T)
        return AnalyticTrajectory(
            x=fx, y=fy,
            z=Fourier1D(T, c0=sc.camera_height - cfg.camera.t_BS[2], sin_coeffs=_coeffs(w["z_sin"], j)),
            yaw=None, pitch=Fourier1D(T, sin_coeffs=_coeffs(w["pitch_sin"], j)),
            roll=Fourier1D(T, cos_coeffs=_coeffs(w["roll_cos"], j)),
        )
    if cfg.preset == "highway":
        hc, w = cfg.highway, motion_tables()["highway"]
        j = hc.jitter
        # y(t) = A (1 - cos(2 pi t / T)) with x = speed t: the centre line of highway_centre_line
        return AnalyticTrajectory(
            x=Fourier1D(T, rate=hc.speed),
            y=Fourier1D(T, c0=hc.bend_amplitude, cos_coeffs=(-hc.bend_amplitude,)),
            z=Fourier1D(T, c0=hc.camera_height - cfg.camera.t_BS[2], sin_coeffs=_coeffs(w["z_sin"], j)),
            yaw=None, pitch=Fourier1D(T, sin_coeffs=_coeffs(w["pitch_sin"], j)),
            roll=Fourier1D(T, cos_coeffs=_coeffs(w["roll_cos"], j)),
        )
    oc, w = cfg.orbit, motion_tables()["orbit"]
    j = oc.jitter
    pitch = float(np.arctan2(oc.height - oc.target_height, oc.radius))
    return AnalyticTrajectory(
        x=Fourier1D(T, cos_coeffs=_coeffs(w["xy_radial"], j, {1: oc.radius})),
        y=Fourier1D(T, sin_coeffs=_coeffs(w["xy_radial"], j, {1: oc.radius})),
        z=Fourier1D(T, c0=oc.height, sin_coeffs=_coeffs(w["z_sin"], j)),
        yaw=Fourier1D(T, c0=np.pi, rate=turn, sin_coeffs=_coeffs(w["yaw_sin"], j)),
        pitch=Fourier1D(T, c0=pitch, sin_coeffs=_coeffs(w["pitch_sin"], j)),
        roll=Fourier1D(T),
    )


def _panel_room_trajectory(pc: PanelRoomConfig) -> AnalyticTrajectory:
    """Body on the ellipse ``(rx cos phi, ry sin phi)`` with ``phi = phi0 + turn * t / duration`` (one
    full-ellipse period ``T = duration * 360 / turn``), radial / tangential / height / attitude wobble,
    yaw = the outward normal of the ellipse plus ``view_offset_deg``. The outward normal direction of
    ``(rx cos, ry sin)`` is not a Fourier series in phi, so the yaw follows the angle phi itself
    (exact for a circle; within a few degrees of the normal for the default ellipse)."""
    w = motion_tables()["panel_room"]
    j = pc.jitter
    turn = np.deg2rad(max(pc.turn_deg, _MIN_TURN_DEG))
    T = pc.duration_s * 2.0 * np.pi / turn
    phi0 = np.deg2rad(pc.start_angle_deg)
    rx, ry = pc.path_radii
    c, s = np.cos(phi0), np.sin(phi0)
    # r(phi) (cos phi, sin phi)-like wobble: radial terms along (cos phi, sin phi) are approximated by x / y terms
    # of the same harmonics (the wobble is small; its shape is what matters)
    return AnalyticTrajectory(
        x=Fourier1D(T, cos_coeffs=_coeffs(w["radial"], j, {1: rx * c}), sin_coeffs=_coeffs(w["tangential"], j, {1: -rx * s})),
        y=Fourier1D(T, cos_coeffs=_coeffs(w["tangential"], j, {1: ry * s}), sin_coeffs=_coeffs(w["radial"], j, {1: ry * c})),
        z=Fourier1D(T, c0=pc.height, sin_coeffs=_coeffs(w["z_sin"], j)),
        yaw=Fourier1D(T, c0=phi0 + np.deg2rad(pc.view_offset_deg), rate=2.0 * np.pi / T,
                      sin_coeffs=_coeffs(w["yaw_sin"], j)),
        pitch=Fourier1D(T, c0=np.deg2rad(pc.mean_pitch_deg), sin_coeffs=_coeffs(w["pitch_sin"], j)),
        roll=Fourier1D(T, sin_coeffs=_coeffs(w["roll_sin"], j)),
    )


def _shifted(terms: Harmonics, other: Harmonics, shift: float, cos_part: bool) -> Harmonics:
    """Coefficients of ``sum_k a_k cos(k w (t + s)) + b_k sin(k w (t + s))`` in cos (``cos_part``) or sin
    terms of ``k w t``, with ``s = shift * period`` (``terms``: the a_k when cos_part else the b_k)."""
    a_terms, b_terms = (terms, other) if cos_part else (other, terms)
    out = {}
    for k in set(a_terms) | set(b_terms):
        a, b, phi = a_terms.get(k, 0.0), b_terms.get(k, 0.0), 2.0 * np.pi * k * shift
        out[k] = a * np.cos(phi) + b * np.sin(phi) if cos_part else b * np.cos(phi) - a * np.sin(phi)
    return out


def _sweep_trajectory(rs: RotationSweepConfig, scale: float) -> AnalyticTrajectory:
    """Roll / pitch / yaw sweep of the ``sweep_rotation`` table times ``scale`` about a fixed heading, started
    ``phase`` into its period, body on a horizontal circle of ``translation_radius`` (once per period)
    with a height wobble."""
    T = rs.loop_duration_s
    w = motion_tables()["sweep_rotation"]
    r = rs.translation_radius

    def series(name: str, c0: float = 0.0) -> Fourier1D:
        cos_t, sin_t = w.get(f"{name}_cos", {}), w.get(f"{name}_sin", {})
        return Fourier1D(T, c0=c0, cos_coeffs=_coeffs(_shifted(cos_t, sin_t, rs.phase, True), scale),
                         sin_coeffs=_coeffs(_shifted(sin_t, cos_t, rs.phase, False), scale))

    return AnalyticTrajectory(
        x=Fourier1D(T, cos_coeffs=(r,)), y=Fourier1D(T, sin_coeffs=(r,)),
        z=Fourier1D(T, c0=rs.height, sin_coeffs=_coeffs(motion_tables()["sweep_height"]["z_sin"], rs.jitter)),
        yaw=series("yaw", np.deg2rad(rs.yaw_deg)), pitch=series("pitch", _SWEEP_MEAN_PITCH), roll=series("roll"),
    )


def sweep_mean_angular_speed(rs: RotationSweepConfig, scale: float) -> float:
    """Mean of |w_B| (deg/s) over one period of the sweep with amplitudes times ``scale``."""
    t = np.arange(_SWEEP_SPEED_SAMPLES) * (rs.loop_duration_s / _SWEEP_SPEED_SAMPLES)
    w_B = _sweep_trajectory(rs, scale).sample(t).w_B
    return float(np.rad2deg(np.linalg.norm(w_B, axis=1).mean()))


def sweep_rotation_scale(rs: RotationSweepConfig) -> float:
    """Amplitude scale of the ``sweep_rotation`` table whose mean angular speed is ``rotation_speed_deg_s``:
    the mean speed is nearly proportional to the scale, so ``scale *= target / speed(scale)`` converges
    in a few steps (to a relative ``_SWEEP_SPEED_TOLERANCE``)."""
    target = rs.rotation_speed_deg_s
    if target == 0:
        return 0.0
    scale = 1.0
    for _ in range(_SWEEP_SPEED_ITERATIONS):
        speed = sweep_mean_angular_speed(rs, scale)
        if abs(speed - target) <= _SWEEP_SPEED_TOLERANCE * target:
            return scale
        scale *= target / speed
        if scale > _SWEEP_MAX_SCALE:
            raise ConfigError(f"rotation_sweep.rotation_speed_deg_s: {target} deg/s needs the sweep's angles scaled "
                              f"by more than {_SWEEP_MAX_SCALE:g}")
    raise ConfigError(f"rotation_sweep.rotation_speed_deg_s: no sweep of {target} deg/s mean angular speed found")
