"""Write a :class:`~.sequence.SynthSequence` in the EuRoC (ASL) layout plus the ``depth0`` extension.

``ROOT/mav0/``:

- ``cam0``, ``cam1``: ``data/<ts_ns>.png`` (8-bit grey, or 8-bit BGR when ``camera.colour``),
  ``data.csv`` (``#timestamp [ns],filename``), ``sensor.yaml`` (EuRoC keys; ``T_BS`` = camera-to-body,
  ``intrinsics: [fu, fv, cu, cv]``, ``distortion_model: radial-tangential`` with the coefficients
  ``camera.distortion`` (zero unless the preset renders distorted raw images); the pair is rectified
  before distortion, cam1 = cam0 shifted by ``baseline`` along cam0's x axis).
- ``depth0``: ``data/<ts_ns>.png`` 16-bit z-depth of cam0 in units of ``1/depth_scale`` m
  (0 = no surface or beyond 65535 units), ``data.csv``, ``sensor.yaml`` (cam0's keys + ``depth_scale``).
- ``imu0``: ``data.csv`` (EuRoC columns, rad/s and m/s^2 in the body frame), ``sensor.yaml``
  (``T_BS`` = identity: body = IMU; noise densities).
- ``state_groundtruth_estimate0/data.csv``: at every IMU time, ``p_RS_R`` (m), ``q_RS`` (w, x, y, z)
  of ``T_WB`` (sign-continuous along the sequence), ``v_RS_R`` (m/s, world), true gyro bias
  ``b_w`` and accelerometer bias ``b_a``.
- ``body.yaml``; ``ROOT/synth_config.yaml`` records the full configuration.

Timestamps are ``start_time_ns + i * period_ns`` (integers), so camera and IMU stamps coincide
whenever the rates allow.

:func:`write_tumvi_sequence` writes the same sequence in the TUM-VI ``dataset-*_512_16`` layout
(:mod:`fgslam.io.datasets.tumvi`): 16-bit PNGs in ``mav0/cam0``, ``mav0/cam1``, ``mav0/imu0/data.csv``,
``mav0/mocap0/data.csv`` (``T_WB``: position and quaternion), ``dso/camchain.yaml`` (Kalibr: intrinsics,
``distortion_model`` and ``distortion_coeffs``, ``T_cam_imu``, cam1's ``T_cn_cnm1``) and
``dso/imu_config.yaml`` (noise densities); no depth. Give it a sequence rendered with
``camera.distortion_model: equidistant`` for TUM-VI's fisheye images.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import yaml

from ...core.config import to_dict
from ...core.errors import DataError
from .sequence import SynthSequence

logger = logging.getLogger(__name__)

_UINT16_MAX = 65535
_UINT8_TO_UINT16 = 257  # 8-bit grey to the 16-bit range (255 -> 65535; the loaders read the high byte back)
#: camera.distortion_model -> the distortion_model name of the EuRoC sensor.yaml / Kalibr camchain
_SENSOR_MODEL_NAMES = {"radtan": "radial-tangential", "equidistant": "equidistant"}
_IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
               "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")


@dataclass(frozen=True)
class WriteSummary:
    root: Path
    frames: int
    imu_samples: int
    duration_s: float
    path_length_m: float


def rotation_to_quaternion_wxyz(R: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions (w, x, y, z), w >= 0, of rotation matrices (N, 3, 3)."""
    R = np.asarray(R, np.float64)
    tr = np.trace(R, axis1=-2, axis2=-1)
    r = R
    cand = np.stack([
        np.stack([1 + tr, r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], -1),
        np.stack([r[:, 2, 1] - r[:, 1, 2], 1 + 2 * r[:, 0, 0] - tr, r[:, 0, 1] + r[:, 1, 0],
                  r[:, 0, 2] + r[:, 2, 0]], -1),
        np.stack([r[:, 0, 2] - r[:, 2, 0], r[:, 0, 1] + r[:, 1, 0], 1 + 2 * r[:, 1, 1] - tr,
                  r[:, 1, 2] + r[:, 2, 1]], -1),
        np.stack([r[:, 1, 0] - r[:, 0, 1], r[:, 0, 2] + r[:, 2, 0], r[:, 1, 2] + r[:, 2, 1],
                  1 + 2 * r[:, 2, 2] - tr], -1),
    ], axis=1)  # (N, 4 candidates, 4); candidate k is 4 q_k q scaled, best conditioned for largest q_k
    diag = np.stack([1 + tr, 1 + 2 * R[:, 0, 0] - tr, 1 + 2 * R[:, 1, 1] - tr, 1 + 2 * R[:, 2, 2] - tr], -1)
    best = np.argmax(diag, axis=-1)
    q = cand[np.arange(len(R)), best]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q


def continuous_quaternions(q: np.ndarray) -> np.ndarray:
    """Flip signs of (N, 4) quaternions so consecutive ones lie in the same hemisphere (q . q_prev >= 0),
    keeping the sign of the first; the rotations are unchanged."""
    if len(q) < 2:
        return q.copy()
    flips = np.where(np.einsum("ni,ni->n", q[1:], q[:-1]) < 0, -1.0, 1.0)
    signs = np.concatenate([[1.0], np.cumprod(flips)])
    return q * signs[:, None]


def _matrix_yaml(T: np.ndarray) -> str:
    vals = ", ".join(f"{v:.12g}" for v in np.asarray(T, np.float64).ravel())
    return f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{vals}]\n"


def _camera_yaml(seq: SynthSequence, T_BS: np.ndarray, comment: str, extra: str = "") -> str:
    cam = seq.cfg.camera
    fx, fy, cx, cy = seq.K
    return ("%YAML:1.0\n"
            "sensor_type: camera\n"
            f"comment: {comment}\n\n"
            "# Sensor extrinsics wrt. the body-frame.\n"
            + _matrix_yaml(T_BS) +
            f"\nrate_hz: {cam.rate_hz:g}\n"
            f"resolution: [{cam.width}, {cam.height}]\n"
            "camera_model: pinhole\n"
            f"intrinsics: [{fx:.12g}, {fy:.12g}, {cx:.12g}, {cy:.12g}] #fu, fv, cu, cv\n"
            f"distortion_model: {_SENSOR_MODEL_NAMES[cam.distortion_model]}\n"
            f"distortion_coefficients: [{', '.join(repr(float(c)) for c in cam.distortion)}]\n" + extra)


def _imu_yaml(seq: SynthSequence) -> str:
    c = seq.cfg.imu
    return ("%YAML:1.0\n"
            "sensor_type: imu\n"
            "comment: fgslam synthetic IMU\n\n"
            + _matrix_yaml(np.eye(4)) +
            f"rate_hz: {c.rate_hz:g}\n\n"
            f"gyroscope_noise_density: {c.gyroscope_noise_density:.6g}     # [ rad / s / sqrt(Hz) ]\n"
            f"gyroscope_random_walk: {c.gyroscope_random_walk:.6g}       # [ rad / s^2 / sqrt(Hz) ]\n"
            f"accelerometer_noise_density: {c.accelerometer_noise_density:.6g}  # [ m / s^2 / sqrt(Hz) ]\n"
            f"accelerometer_random_walk: {c.accelerometer_random_walk:.6g}    # [ m / s^3 / sqrt(Hz) ]\n"
            f"gravity_magnitude: {c.gravity:.6g}  # [ m / s^2 ] along -z of the world\n")


def depth_to_png16(depth: np.ndarray, depth_scale: float) -> np.ndarray:
    """uint16 depth image: round(depth * scale); 0 for no surface or values above 65535."""
    units = np.rint(depth.astype(np.float64) * depth_scale)
    units[(units > _UINT16_MAX) | ~np.isfinite(units) | (depth <= 0)] = 0
    return units.astype(np.uint16)


def _to_uint8(img: np.ndarray) -> np.ndarray:
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    if out.ndim == 3:
        out = out[..., ::-1]  # RGB -> BGR for OpenCV
    return np.ascontiguousarray(out)


def _write_png(path: Path, img: np.ndarray) -> None:
    if not cv2.imwrite(str(path), img):
        raise DataError(f"could not write image {path}")


def write_sequence(seq: SynthSequence, root: str | Path,
                   progress: Callable[[int, int], None] | None = None) -> WriteSummary:
    """Render every frame of ``seq`` and write the EuRoC-style sequence under ``root``."""
    cfg = seq.cfg
    root = Path(root)
    mav0 = root / "mav0"
    dirs = {name: mav0 / name for name in ("cam0", "cam1", "depth0", "imu0", "state_groundtruth_estimate0")}
    try:
        for name in ("cam0", "cam1", "depth0"):
            (dirs[name] / "data").mkdir(parents=True, exist_ok=True)
        for name in ("imu0", "state_groundtruth_estimate0"):
            dirs[name].mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"cannot create output folders under {root}: {exc}") from exc

    cam_period_ns = int(round(1e9 / cfg.camera.rate_hz))
    n = cfg.frames
    cam_ns = cfg.start_time_ns + np.arange(n, dtype=np.int64) * cam_period_ns
    names = [f"{ts}.png" for ts in cam_ns]
    for name in ("cam0", "cam1", "depth0"):
        lines = ["#timestamp [ns],filename"] + [f"{ts},{fn}" for ts, fn in zip(cam_ns, names)]
        (dirs[name] / "data.csv").write_text("\n".join(lines) + "\n")

    for i in range(n):
        fr = seq.frame(i)
        _write_png(dirs["cam0"] / "data" / names[i], _to_uint8(fr.image0))
        _write_png(dirs["cam1"] / "data" / names[i], _to_uint8(fr.image1))
        _write_png(dirs["depth0"] / "data" / names[i], depth_to_png16(fr.depth0, cfg.camera.depth_scale))
        if progress is not None:
            progress(i + 1, n)

    imu = seq.imu
    imu_ns = _write_imu(seq, dirs["imu0"] / "data.csv")

    st = seq.states(imu.t)
    q = continuous_quaternions(rotation_to_quaternion_wxyz(st.R_WB))
    gt = np.hstack([st.p_WB, q, st.v_WB, imu.bias_gyro, imu.bias_accel])
    header = ("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
              "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
              "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
              "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]")
    rows = [f"{ts}," + ",".join(f"{v:.12g}" for v in row) for ts, row in zip(imu_ns, gt)]
    (dirs["state_groundtruth_estimate0"] / "data.csv").write_text("\n".join([header] + rows) + "\n")

    (dirs["cam0"] / "sensor.yaml").write_text(_camera_yaml(seq, seq.T_BS0, "fgslam synthetic left camera"))
    (dirs["cam1"] / "sensor.yaml").write_text(_camera_yaml(seq, seq.T_BS1, "fgslam synthetic right camera"))
    (dirs["depth0"] / "sensor.yaml").write_text(_camera_yaml(
        seq, seq.T_BS0, "fgslam synthetic z-depth of cam0 (16-bit PNG, 0 = invalid)",
        extra=f"depth_scale: {cfg.camera.depth_scale:g}  # PNG units per metre\n"))
    (dirs["imu0"] / "sensor.yaml").write_text(_imu_yaml(seq))
    (mav0 / "body.yaml").write_text("%YAML:1.0\ncomment: fgslam synthetic body (= IMU frame)\n")
    (root / "synth_config.yaml").write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))

    return _summary(seq, root)


def _summary(seq: SynthSequence, root: Path) -> WriteSummary:
    n = seq.cfg.frames
    p = seq.states(seq.frame_times()).p_WB
    length = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if n > 1 else 0.0
    logger.info("wrote %d frames and %d IMU samples to %s", n, len(seq.imu.t), root)
    return WriteSummary(root=root, frames=n, imu_samples=len(seq.imu.t),
                        duration_s=(n - 1) / seq.cfg.camera.rate_hz, path_length_m=length)


def _write_imu(seq: SynthSequence, path: Path) -> np.ndarray:
    """``imu0/data.csv`` (EuRoC / TUM-VI columns); the sample stamps (ns)."""
    cfg, imu = seq.cfg, seq.imu
    imu_ns = cfg.start_time_ns + np.arange(len(imu.t), dtype=np.int64) * int(round(1e9 / cfg.imu.rate_hz))
    rows = [f"{ts}," + ",".join(f"{v:.12g}" for v in row)
            for ts, row in zip(imu_ns, np.hstack([imu.gyro, imu.accel]))]
    path.write_text("\n".join([_IMU_HEADER] + rows) + "\n")
    return imu_ns


def _kalibr_rows(T: np.ndarray, indent: str = "  ") -> str:
    return "".join(f"{indent}- [{', '.join(f'{v:.12g}' for v in row)}]\n" for row in np.asarray(T, np.float64))


def _kalibr_camera(seq: SynthSequence, T_cam_imu: np.ndarray, T_cn_cnm1: np.ndarray | None = None) -> str:
    cam = seq.cfg.camera
    out = "  T_cam_imu:\n" + _kalibr_rows(T_cam_imu, "  ")
    if T_cn_cnm1 is not None:
        out += "  T_cn_cnm1:\n" + _kalibr_rows(T_cn_cnm1, "  ")
    return (out + "  camera_model: pinhole\n"
            f"  distortion_coeffs: [{', '.join(repr(float(c)) for c in cam.distortion)}]\n"
            f"  distortion_model: {_SENSOR_MODEL_NAMES[cam.distortion_model]}\n"
            f"  intrinsics: [{', '.join(f'{k:.12g}' for k in seq.K)}]\n"
            f"  resolution: [{cam.width}, {cam.height}]\n")


def write_tumvi_sequence(seq: SynthSequence, root: str | Path,
                         progress: Callable[[int, int], None] | None = None) -> WriteSummary:
    """Render every frame of ``seq`` and write it under ``root`` in the TUM-VI layout (module docstring)."""
    cfg = seq.cfg
    if cfg.camera.colour:
        raise DataError("TUM-VI sequences are grey: render with camera.colour: false")
    root = Path(root)
    mav0, dso = root / "mav0", root / "dso"
    try:
        for name in ("cam0", "cam1"):
            (mav0 / name / "data").mkdir(parents=True, exist_ok=True)
        for folder in (mav0 / "imu0", mav0 / "mocap0", dso):
            folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"cannot create output folders under {root}: {exc}") from exc
    n = cfg.frames
    cam_ns = cfg.start_time_ns + np.arange(n, dtype=np.int64) * int(round(1e9 / cfg.camera.rate_hz))
    names = [f"{ts}.png" for ts in cam_ns]
    for name in ("cam0", "cam1"):
        lines = ["#timestamp [ns],filename"] + [f"{ts},{fn}" for ts, fn in zip(cam_ns, names)]
        (mav0 / name / "data.csv").write_text("\n".join(lines) + "\n")
    for i in range(n):
        fr = seq.frame(i)
        for name, img in (("cam0", fr.image0), ("cam1", fr.image1)):
            _write_png(mav0 / name / "data" / names[i], _to_uint8(img).astype(np.uint16) * np.uint16(_UINT8_TO_UINT16))
        if progress is not None:
            progress(i + 1, n)
    imu_ns = _write_imu(seq, mav0 / "imu0" / "data.csv")
    st = seq.states(seq.imu.t)
    q = continuous_quaternions(rotation_to_quaternion_wxyz(st.R_WB))
    rows = [f"{ts}," + ",".join(f"{v:.12g}" for v in row) for ts, row in zip(imu_ns, np.hstack([st.p_WB, q]))]
    header = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"
    (mav0 / "mocap0" / "data.csv").write_text("\n".join([header] + rows) + "\n")
    T_C0I = np.linalg.inv(seq.T_BS0)
    T_C1I = np.linalg.inv(seq.T_BS1)
    (dso / "camchain.yaml").write_text("cam0:\n" + _kalibr_camera(seq, T_C0I) + "  rostopic: /cam0/image_raw\n"
                                       "cam1:\n" + _kalibr_camera(seq, T_C1I, T_C1I @ seq.T_BS0)
                                       + "  rostopic: /cam1/image_raw\n")
    c = cfg.imu
    (dso / "imu_config.yaml").write_text(
        f"accelerometer_noise_density: {c.accelerometer_noise_density:.6g}\n"
        f"accelerometer_random_walk: {c.accelerometer_random_walk:.6g}\n"
        f"gyroscope_noise_density: {c.gyroscope_noise_density:.6g}\n"
        f"gyroscope_random_walk: {c.gyroscope_random_walk:.6g}\n"
        "rostopic: /imu0\n"
        f"update_rate: {c.rate_hz:g}\n")
    (root / "synth_config.yaml").write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))
    return _summary(seq, root)
