"""Decoding the ROS messages of a bag for :mod:`.rosbag`: header stamps and IMU samples read straight
from the serialized bytes (ROS 1 or ROS 2 CDR, no deserializing), and OpenCV images, depth maps and
raw calibrations from deserialized ``sensor_msgs`` messages (the module docstring of :mod:`.rosbag`).

The deserialized messages are the objects of the ``rosbags`` typestore, whose classes are generated
per bag (ROS 1 ``CameraInfo`` spells ``D``, ``K``, ``R``, ``P``; ROS 2 ``d``, ``k``, ``r``, ``p``), so
they are typed ``Any`` here.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from ...core.errors import DataError
from ..calibration import Calibration
from ..frame import FrameReadError
from .common import CALIBRATION_OVERRIDE
from .files import truncation_reason

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMU = "sensor_msgs/msg/Imu"
COLOUR_ENCODINGS = ("mono8", "mono16", "rgb8", "bgr8", "rgba8", "bgra8", "8UC1", "8UC3")
DEPTH_ENCODINGS = ("16UC1", "32FC1")
DEPTH_MM_PER_M = 1000.0  # 16UC1 depth is in millimetres (REP 118)
DEPTH_U16_INVALID = 65535  # besides 0 (saturated / no return), as the 7-Scenes folder loader
DISTORTION_MODELS = {"plumb_bob": "radtan", "rational_polynomial": "radtan", "equidistant": "equidistant",
                     "fisheye": "equidistant"}
RADTAN_BASE = 5  # k1 k2 p1 p2 k3; rational_polynomial adds k4 k5 k6 (OpenCV's rational model)


def header_stamp_ns(raw: bytes | memoryview, ros2: bool) -> int:
    """Header stamp (ns) of a serialized message that starts with ``std_msgs/Header``.

    ROS 1: ``uint32 seq, uint32 sec, uint32 nsec``; ROS 2 (CDR): 4-byte encapsulation header (byte 1:
    1 little-endian, 0 big-endian), then ``int32 sec, uint32 nanosec``.
    """
    if ros2:
        endian = "<" if raw[1] == 1 else ">"
        sec, nsec = struct.unpack_from(endian + "iI", raw, 4)
    else:
        sec, nsec = struct.unpack_from("<II", raw, 4)
    return int(sec) * 1_000_000_000 + int(nsec)


IMU_DOUBLES = 4 + 9 + 3 + 9 + 3  # orientation, its covariance, angular velocity, its covariance, linear acceleration
GYRO_AT, ACCEL_AT = 13, 25  # index of angular_velocity.x / linear_acceleration.x among those doubles


def imu_from_raw(raw: bytes | memoryview, ros2: bool) -> tuple[int, tuple[float, ...]]:
    """``(stamp ns, (wx, wy, wz, ax, ay, az))`` of a serialized ``sensor_msgs/Imu`` without deserializing.

    ROS 1: header (``seq, sec, nsec``, frame_id as uint32 length + bytes), then packed float64s. ROS 2
    (CDR): after the 4-byte encapsulation header, ``sec, nanosec``, frame_id (uint32 length with
    the NUL + bytes), then float64s aligned to 8 bytes (relative to the end of the encapsulation header).
    """
    endian = ("<" if raw[1] == 1 else ">") if ros2 else "<"
    sec, nsec, n = struct.unpack_from(endian + "iII" if ros2 else "<III", raw, 4)  # ROS 1: after the uint32 seq
    off = 16 + n
    if ros2:
        off += (-(off - 4)) % 8
    values = struct.unpack_from(f"{endian}{IMU_DOUBLES}d", raw, off)
    return int(sec) * 1_000_000_000 + int(nsec), values[GYRO_AT:GYRO_AT + 3] + values[ACCEL_AT:ACCEL_AT + 3]



def image_from_message(msg: Any, msgtype: str, topic: str, depth: bool) -> np.ndarray:
    """OpenCV image (uint8/uint16 grey or BGR) or float32 depth (metres) of an Image / CompressedImage."""
    import cv2  # deferred: OpenCV

    if msgtype == COMPRESSED:
        fmt = str(msg.format)
        data = bytes(np.asarray(msg.data, dtype=np.uint8))
        if "compressedDepth" in fmt:
            raise FrameReadError(f"{topic}: unsupported CompressedImage format {fmt!r} (compressedDepth)")
        reason = truncation_reason(data)
        if reason is not None:
            raise FrameReadError(f"{topic}: {reason}")
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
        if img is None or img.size == 0:
            raise FrameReadError(f"{topic}: CompressedImage ({fmt!r}) not decodable")
        if depth:
            if img.dtype != np.uint16 or img.ndim != 2:
                raise FrameReadError(f"{topic}: compressed depth must decode to 16-bit single-channel, got {img.dtype} {img.shape}")
            return _depth_u16(img)
        return img
    enc, h, w, step = str(msg.encoding), int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if enc not in COLOUR_ENCODINGS + DEPTH_ENCODINGS:
        raise FrameReadError(f"{topic}: unknown image encoding {enc!r} (supported: "
                             f"{', '.join(COLOUR_ENCODINGS + DEPTH_ENCODINGS)})")
    if depth != (enc in DEPTH_ENCODINGS):
        raise FrameReadError(f"{topic}: encoding {enc!r} is not a {'depth' if depth else 'colour or grey'} encoding")
    channels = {"rgb8": 3, "bgr8": 3, "8UC3": 3, "rgba8": 4, "bgra8": 4}.get(enc, 1)
    itemsize = 2 if enc in ("mono16", "16UC1") else 4 if enc == "32FC1" else 1
    if h <= 0 or w <= 0 or step < w * channels * itemsize or data.size < step * h:
        raise FrameReadError(f"{topic}: Image of {w}x{h} ({enc}) with step {step} holds {data.size} bytes "
                             f"(needs {step * h})")
    rows = data[: step * h].reshape(h, step)[:, : w * channels * itemsize]
    if itemsize > 1:
        dtype = np.dtype({2: np.uint16, 4: np.float32}[itemsize]).newbyteorder(">" if msg.is_bigendian else "<")
        rows = np.ascontiguousarray(rows).view(dtype).astype(dtype.newbyteorder("="))
    img = rows.reshape(h, w, channels) if channels > 1 else rows.reshape(h, w)
    if enc == "rgb8":
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif enc == "rgba8":
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGR)
    elif enc == "bgra8":
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if enc == "16UC1":
        return _depth_u16(img)
    if enc == "32FC1":
        return img.astype(np.float32)
    return np.ascontiguousarray(img)


def _depth_u16(img: np.ndarray) -> np.ndarray:
    depth = img.astype(np.float32) / np.float32(DEPTH_MM_PER_M)
    depth[img == DEPTH_U16_INVALID] = 0.0
    return depth


def calibration_from_camera_info(msg: Any, topic: str) -> Calibration:
    """Raw calibration (no extrinsics) of one CameraInfo message."""
    model = DISTORTION_MODELS.get(str(msg.distortion_model))
    D = np.asarray(msg.D if hasattr(msg, "D") else msg.d, dtype=np.float64).reshape(-1)
    K = np.asarray(msg.K if hasattr(msg, "K") else msg.k, dtype=np.float64).reshape(-1)
    if model is None and not (D.size == 0 or not np.any(D)):
        raise DataError(f"{topic}: CameraInfo distortion_model {msg.distortion_model!r} not supported "
                        "(plumb_bob, rational_polynomial, equidistant); give a calibration YAML with "
                        f"{CALIBRATION_OVERRIDE}")
    if K.size != 9 or K[0] <= 0 or K[4] <= 0:
        raise DataError(f"{topic}: CameraInfo K is not a calibrated camera matrix ({K.tolist()}); "
                        f"give a calibration YAML with {CALIBRATION_OVERRIDE}")
    if not np.any(D):
        model, D = "none", np.zeros(0)
    elif model == "radtan":
        if D.size > RADTAN_BASE and np.any(D[RADTAN_BASE:]):
            raise DataError(f"{topic}: rational_polynomial with non-zero k4..k6 ({D.tolist()}) is not supported; "
                            f"give a calibration YAML with {CALIBRATION_OVERRIDE}")
        D = D[:RADTAN_BASE]
        if D.size == RADTAN_BASE and D[4] == 0:  # plumb_bob with k3 = 0 is the 4-coefficient model
            D = D[:4]
    return Calibration(int(msg.width), int(msg.height), [K[0], K[4], K[2], K[5]], model, D)


def camera_info_rectification(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3, 3), P (3, 4))``: the rectifying rotation and projection matrix of a CameraInfo message."""
    R = np.asarray(msg.R if hasattr(msg, "R") else msg.r, dtype=np.float64).reshape(3, 3)
    P = np.asarray(msg.P if hasattr(msg, "P") else msg.p, dtype=np.float64).reshape(3, 4)
    return R, P
