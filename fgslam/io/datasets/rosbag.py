"""ROS 1 ``.bag`` files and ROS 2 bag folders (sqlite3 or mcap storage) as datasets.

Read with the pure-Python ``rosbags`` package (optional extra ``fgslam[bag]``; no ROS install).

Topics and roles: ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` topics are image
candidates; an Image topic whose first message has a depth encoding (``16UC1`` millimetres, ``32FC1``
metres) or a CompressedImage topic with ``depth`` in its name is a depth candidate, any other
image topic a colour one; a colour topic whose name contains ``right`` or ``cam1`` is a right
candidate, the others left candidates. ``sensor_msgs/Imu`` topics are IMU candidates.
``DatasetConfig.topics.{left,right,depth,imu}`` choose; a role left unset is filled automatically
when it has exactly one candidate (two left candidates without a choice: DataError naming them).

Time: the header stamp (integer nanoseconds) of each message. Frames are the left topic's
messages; right and depth messages are matched to them by stamp within ``stereo_max_dt`` (a left
frame without a partner is dropped with a warning naming the topic). Header stamps of each used
topic must be strictly increasing (DataError naming the topic and the message otherwise).

Calibration: ``DatasetConfig.calibration_file`` (calibration YAML) when given, else the first
``sensor_msgs/CameraInfo`` message in the image topic's namespace (``/cam0/image_raw`` ->
``/cam0/camera_info``, ``/cam/image_raw/compressed`` -> ``/cam/camera_info``; ``topics.left_info`` / ``topics.right_info`` choose), with
``plumb_bob`` / ``rational_polynomial`` (``radtan``; all-zero coefficients: ``none``) or
``equidistant`` distortion. A stereo pair's two camera_infos give its rectification as recorded
(``R`` and ``P`` of both, ROS convention: ``P_right[0, 3] = -fx * baseline``), used as is instead of
``cv2.stereoRectify``. Camera-to-IMU extrinsics: ``DatasetConfig.T_BC`` (or the calibration YAML's).

Lazy reading: opening reads every used topic's messages once to index them (header stamp parsed
from the raw bytes, nothing kept but ``(stamp, connection, log time, ordinal)``); a frame is read
by a per-topic cursor over the bag (sequential reads never seek back; a backward jump restarts
the cursor at that message's log time). IMU messages are read in full at open (small).
"""

from __future__ import annotations

import bisect
import logging
import sqlite3
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any, Iterator, Optional

import numpy as np

from ...core.errors import ConfigError, DataError
from ..calibration import Calibration
from ..frame import FrameReadError, FrameSizeError, ImuSamples
from .common import CALIBRATION_OVERRIDE, Dataset, DatasetConfig, RawFrame, ns_to_seconds
from .ros_messages import (CAMERA_INFO, COMPRESSED, DEPTH_ENCODINGS, IMAGE, IMU, calibration_from_camera_info,
                           camera_info_rectification, header_stamp_ns, image_from_message, imu_from_raw)

if TYPE_CHECKING:  # the optional rosbags package (fgslam[bag]), imported when a bag is opened
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import Connection
    from rosbags.typesys import Stores
    from rosbags.typesys.store import Typestore

logger = logging.getLogger(__name__)

BAG_EXTRA = "bag"  # the pyproject optional extra that installs rosbags
ROS1_SUFFIX = ".bag"
ROS2_METADATA = "metadata.yaml"
ROS2_STORAGE_SUFFIXES = (".db3", ".mcap")  # a ROS 2 bag's storage files (sqlite3, mcap), beside its metadata.yaml
COMPRESSED_SUFFIX = "/compressed"  # image_transport: <image topic>/compressed
RIGHT_NAME_HINTS = ("right", "cam1")
DEPTH_NAME_HINT = "depth"
ROLES = ("left", "right", "depth", "imu")


def import_rosbags() -> tuple[type[AnyReader], type[Stores], Callable[[Stores], Typestore]]:
    """The ``rosbags`` names used here; DataError naming the extra when it is not installed."""
    try:
        from rosbags.highlevel import AnyReader  # deferred: optional rosbags
        from rosbags.typesys import Stores, get_typestore  # deferred: optional rosbags
    except ImportError as exc:
        raise DataError(f"reading ROS bags needs the rosbags package: pip install 'fgslam[{BAG_EXTRA}]' "
                        f"({exc})") from exc
    return AnyReader, Stores, get_typestore


def is_bag(path: Path) -> bool:
    """A ROS 1 ``.bag`` file or a ROS 2 bag folder (holds ``metadata.yaml``)."""
    return (path.is_file() and path.suffix == ROS1_SUFFIX) or (path.is_dir() and (path / ROS2_METADATA).is_file())


def check_ros2_bag_parts(path: Path) -> None:
    """DataError for what looks like part of a ROS 2 bag but cannot be opened as one: a folder holding
    storage files (``*.db3``, ``*.mcap``) without its ``metadata.yaml``, or one such storage file given
    instead of its folder; nothing for anything else."""
    if path.is_dir() and not (path / ROS2_METADATA).is_file():
        storage = sorted(p.name for p in path.iterdir() if p.suffix.lower() in ROS2_STORAGE_SUFFIXES and p.is_file())
        if storage:
            raise DataError(f"{path}: looks like a ROS 2 bag ({', '.join(storage)}) but its {ROS2_METADATA} is "
                            f"missing: a ROS 2 bag folder needs it (`ros2 bag reindex {path}` writes it again)")
    elif path.is_file() and path.suffix.lower() in ROS2_STORAGE_SUFFIXES:
        raise DataError(f"{path}: a ROS 2 bag's storage file: give the bag's folder (with its {ROS2_METADATA})")


def _reader_errors() -> tuple[type[BaseException], ...]:
    out: list[type[BaseException]] = [sqlite3.Error, struct.error, KeyError, ValueError, EOFError, OSError,
                                      IndexError, AssertionError]
    try:
        from rosbags.highlevel import AnyReaderError  # deferred: optional rosbags
        from rosbags.rosbag1 import ReaderError as Reader1Error  # deferred: optional rosbags
        from rosbags.rosbag2 import ReaderError as Reader2Error  # deferred: optional rosbags
        out += [AnyReaderError, Reader1Error, Reader2Error]
    except ImportError:  # pragma: no cover - import_rosbags reports it first
        pass
    return tuple(out)


@dataclass
class TopicIndex:
    """The messages of one used topic: header stamps, log times and per-connection ordinals."""

    topic: str
    msgtype: str
    connection: Connection | None  # None in a pickled copy until the bag is opened again
    stamps_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    log_ns: list[int] = field(default_factory=list)  # log time of each message, in reader order


class _Cursor:
    """Sequential reader of one connection's messages (restarted on a backward jump)."""

    def __init__(self, reader: AnyReader, index: TopicIndex) -> None:
        self.reader, self.index = reader, index
        self.gen: Optional[Iterator[tuple[Connection, int, bytes]]] = None
        self.next_ordinal = 0

    def read(self, ordinal: int) -> bytes:
        if self.gen is None or ordinal < self.next_ordinal:
            start = self.index.log_ns[ordinal]
            self.gen = self.reader.messages(connections=[self.index.connection], start=start)
            self.next_ordinal = bisect.bisect_left(self.index.log_ns, start)
        for _, _, raw in self.gen:
            current = self.next_ordinal
            self.next_ordinal += 1
            if current == ordinal:
                return raw
        self.gen = None
        raise FrameReadError(f"{self.index.topic}: message {ordinal} missing from the bag (truncated?)")


class RosbagDataset(Dataset):
    """A ROS 1 or ROS 2 bag (see the module docstring)."""

    format = "rosbag"

    def __init__(self, root: Path, config: Optional[DatasetConfig] = None) -> None:
        super().__init__(root, config)
        config = self.config
        check_ros2_bag_parts(self.root)
        self.name = self.root.stem if self.root.is_file() else self.root.name
        self._ros2 = not self.root.is_file()
        self._typestore = self._make_typestore()
        self._lock = threading.Lock()
        self._reader: Optional[AnyReader] = None
        self._cursors: dict[str, _Cursor] = {}
        with self._guard("cannot open the bag"):
            reader = self._open_reader()
            self.topic_counts = {c.topic: 0 for c in reader.connections}
            for c in reader.connections:
                self.topic_counts[c.topic] += c.msgcount
            self.topic_types = {c.topic: c.msgtype for c in reader.connections}
            self.duration_s = reader.duration / 1e9 if reader.message_count else 0.0
            self.roles = self._choose_topics(reader)
            self._indices_by_role = {role: self._index_topic(reader, topic) for role, topic in self.roles.items()
                                     if role != "imu"}
            if "imu" in self.roles and config.load_imu:
                self.imu = self._read_imu(reader, self.roles["imu"])
        self._frame_ordinals = self._match_frames()
        self.raw_timestamps = ns_to_seconds(self._frame_stamps)
        self._has_stereo = "right" in self.roles
        self._has_depth = "depth" in self.roles
        self.raw_calibration = self._calibration()
        self._check_first_images()
        self._setup()

    # ------------------------------------------------------------ reader plumbing
    def _open_reader(self) -> AnyReader:
        if self._reader is None:
            reader_class, _, _ = import_rosbags()
            reader = reader_class([self.root], default_typestore=self._typestore)
            reader.open()
            self._reader = reader
        return self._reader

    def _guard(self, what: str, topic: Optional[str] = None, error: type[Exception] = DataError):
        dataset = self

        class Guard:
            def __enter__(self):
                return self

            def __exit__(self, exc_type, exc, tb):
                if exc is None or isinstance(exc, (DataError, ConfigError)):
                    return False
                if isinstance(exc, _reader_errors()):
                    where = f"{dataset.root}" + (f" topic {topic}" if topic else "")
                    raise error(f"{where}: {what}: {type(exc).__name__}: {exc} (truncated or corrupt bag?)") from exc
                return False

        return Guard()

    def _make_typestore(self) -> Typestore:
        """Message types for bags without embedded definitions (ROS 2 Humble / ROS 1 Noetic)."""
        _, Stores, get_typestore = import_rosbags()
        return get_typestore(Stores.ROS2_HUMBLE if self._ros2 else Stores.ROS1_NOETIC)

    def __getstate__(self) -> dict:
        """Picklable: the open reader, cursors, lock and typestore are made again after unpickling."""
        state = dict(self.__dict__)
        state["_reader"], state["_cursors"], state["_lock"], state["_typestore"] = None, {}, None, None
        state["_indices_by_role"] = {role: TopicIndex(ix.topic, ix.msgtype, None, ix.stamps_ns, ix.log_ns)
                                     for role, ix in self._indices_by_role.items()}
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()
        self._typestore = self._make_typestore()
        reader = self._open_reader()
        for index in self._indices_by_role.values():
            index.connection = next(c for c in reader.connections if c.topic == index.topic)

    def _deserialize(self, raw: bytes, msgtype: str) -> Any:  # a message of the bag's typestore
        if self._ros2:
            return self._typestore.deserialize_cdr(raw, msgtype)
        return self._typestore.deserialize_ros1(raw, msgtype)

    def _first_message(self, reader: AnyReader, topic: str) -> Any:  # a message of the bag's typestore
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in reader.messages(connections=conns):
            return self._deserialize(raw, conn.msgtype)
        raise DataError(f"{self.root}: topic {topic} has no messages")

    # ------------------------------------------------------------ topics
    def _choose_topics(self, reader: AnyReader) -> dict[str, str]:
        cfg = self.config.topics
        types = self.topic_types
        images = sorted(t for t, ty in types.items() if ty in (IMAGE, COMPRESSED) and self.topic_counts[t])
        listing = ", ".join(f"{t} ({ty})" for t, ty in sorted(types.items())) or "none"
        for role in ROLES + ("left_info", "right_info"):
            chosen = getattr(cfg, role)
            if chosen is None:
                continue
            if chosen not in types:
                raise DataError(f"{self.root}: dataset.topics.{role}={chosen} is not a topic of the bag (topics: {listing})")
            want = (IMU,) if role == "imu" else (CAMERA_INFO,) if role.endswith("_info") else (IMAGE, COMPRESSED)
            if types[chosen] not in want:
                raise DataError(f"{self.root}: dataset.topics.{role}={chosen} is a {types[chosen]}, not a {' or '.join(want)}")
        if not images:
            raise DataError(f"{self.root}: no image topics (sensor_msgs/Image or CompressedImage) in the bag; "
                            f"topics: {listing}")
        depth_cands, right_cands, left_cands = [], [], []
        self.depth_topics: set[str] = set()
        for topic in images:
            if self._is_depth_topic(reader, topic):
                depth_cands.append(topic)
                self.depth_topics.add(topic)
            elif any(h in topic.lower() for h in RIGHT_NAME_HINTS):
                right_cands.append(topic)
            else:
                left_cands.append(topic)
        imu_cands = sorted(t for t, ty in types.items() if ty == IMU and self.topic_counts[t])
        roles: dict[str, str] = {}
        for role, cands in (("left", left_cands), ("right", right_cands), ("depth", depth_cands), ("imu", imu_cands)):
            chosen = getattr(cfg, role)
            if chosen is not None:
                roles[role] = chosen
            elif len(cands) == 1:
                roles[role] = cands[0]
            elif len(cands) > 1 and role == "left":
                raise DataError(f"{self.root}: {len(cands)} candidate topics for the left images ({', '.join(cands)}); "
                                f"choose one with dataset.topics.left")
            elif len(cands) > 1:
                logger.warning("%s: %d candidate topics for the %s role (%s) and no dataset.topics.%s: %s not used",
                               self.root, len(cands), role, ", ".join(cands), role, role)
        if "left" not in roles:
            raise DataError(f"{self.root}: no colour or grey image topic for the left images (image topics: "
                            f"{', '.join(images)}); choose one with dataset.topics.left")
        if roles.get("right") == roles["left"] or roles.get("depth") == roles["left"]:
            raise DataError(f"{self.root}: topic {roles['left']} chosen for two roles")
        if not self.config.load_right:
            roles.pop("right", None)
        if not self.config.load_depth:
            roles.pop("depth", None)
        return roles

    def _is_depth_topic(self, reader: AnyReader, topic: str) -> bool:
        if self.config.topics.depth == topic:
            return True
        if topic in (self.config.topics.left, self.config.topics.right):
            return False
        if self.topic_types[topic] == COMPRESSED:
            return DEPTH_NAME_HINT in topic.lower()
        return str(self._first_message(reader, topic).encoding) in DEPTH_ENCODINGS

    def _index_topic(self, reader: AnyReader, topic: str) -> TopicIndex:
        conns = [c for c in reader.connections if c.topic == topic]
        if len(conns) != 1:
            raise DataError(f"{self.root}: topic {topic} has {len(conns)} connections (one expected)")
        index = TopicIndex(topic, conns[0].msgtype, conns[0])
        stamps = []
        with self._guard("cannot index the messages", topic):
            for _, log_ns, raw in reader.messages(connections=conns):
                stamps.append(header_stamp_ns(raw, self._ros2))
                index.log_ns.append(int(log_ns))
        index.stamps_ns = np.asarray(stamps, dtype=np.int64)
        if index.stamps_ns.size == 0:
            raise DataError(f"{self.root}: topic {topic} has no messages")
        _check_increasing(self.root, topic, index.stamps_ns)
        return index

    def _read_imu(self, reader: AnyReader, topic: str) -> ImuSamples:
        conns = [c for c in reader.connections if c.topic == topic]
        stamps, values = [], []
        with self._guard("cannot read the IMU messages", topic):
            for conn, _, raw in reader.messages(connections=conns):
                if not stamps:  # the raw layout agrees with the deserializer (else: the message type differs)
                    m = self._deserialize(raw, conn.msgtype)
                    w, a = m.angular_velocity, m.linear_acceleration
                    expected = (m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec,
                                (w.x, w.y, w.z, a.x, a.y, a.z))
                    if imu_from_raw(raw, self._ros2) != expected:
                        raise DataError(f"{self.root}: topic {topic}: IMU message layout not understood")
                stamp, vals = imu_from_raw(raw, self._ros2)
                stamps.append(stamp)
                values.append(vals)
        ts = np.asarray(stamps, dtype=np.int64)
        _check_increasing(self.root, topic, ts)
        vals = np.asarray(values, dtype=np.float64).reshape(-1, 6)
        if not np.all(np.isfinite(vals)):
            bad = int(np.flatnonzero(~np.isfinite(vals).all(1))[0])
            raise DataError(f"{self.root}: topic {topic}: non-finite IMU value in message {bad}")
        return ImuSamples(ns_to_seconds(ts), vals[:, :3].copy(), vals[:, 3:].copy())

    def _match_frames(self) -> dict[str, np.ndarray]:
        """Ordinal per used frame of each image role; drops left frames without partner (warning)."""
        left = self._indices_by_role["left"]
        keep = np.ones(left.stamps_ns.size, dtype=bool)
        partners = {}
        max_dt_ns = int(round(self.config.stereo_max_dt * 1e9))
        for role in ("right", "depth"):
            if role not in self._indices_by_role:
                continue
            other = self._indices_by_role[role].stamps_ns
            j = np.clip(np.searchsorted(other, left.stamps_ns), 0, other.size - 1)
            lo = np.clip(j - 1, 0, other.size - 1)
            best = np.where(np.abs(other[lo] - left.stamps_ns) < np.abs(other[j] - left.stamps_ns), lo, j)
            ok = np.abs(other[best] - left.stamps_ns) <= max_dt_ns
            if not np.all(ok):
                logger.warning("%s: %d of %d frames of %s have no %s message on %s within %g s: dropped",
                               self.root, int((~ok).sum()), ok.size, left.topic, role,
                               self._indices_by_role[role].topic, self.config.stereo_max_dt)
            keep &= ok
            partners[role] = best
        if not np.any(keep):
            raise DataError(f"{self.root}: no frame of {left.topic} has all its partner messages "
                            f"({', '.join(self._indices_by_role[r].topic for r in partners)})")
        self._frame_stamps = left.stamps_ns[keep]
        out = {"left": np.flatnonzero(keep)}
        out.update({role: best[keep] for role, best in partners.items()})
        return out

    # ------------------------------------------------------------ calibration
    def _info_topic(self, role: str) -> Optional[str]:
        chosen = getattr(self.config.topics, f"{role}_info")
        if chosen is not None:
            return chosen
        topic = self.roles[role]
        base = topic[: -len(COMPRESSED_SUFFIX)] if topic.endswith(COMPRESSED_SUFFIX) else topic
        namespace = PurePosixPath(base).parent
        cands = [t for t, ty in self.topic_types.items()
                 if ty == CAMERA_INFO and PurePosixPath(t).parent == namespace and self.topic_counts[t]]
        if len(cands) > 1:
            raise DataError(f"{self.root}: {len(cands)} CameraInfo topics for {self.roles[role]} ({', '.join(cands)}); "
                            f"choose one with dataset.topics.{role}_info")
        return cands[0] if cands else None

    def _calibration(self) -> Calibration:
        cfg = self.config
        if cfg.calibration_file:
            calib = Calibration.from_yaml(cfg.calibration_file)
            self.calibration_source = cfg.calibration_file
        else:
            info_topic = self._info_topic("left")
            if info_topic is None:
                raise DataError(f"{self.root}: no CameraInfo topic for {self.roles['left']} (looked in its namespace "
                                f"{PurePosixPath(self.roles['left']).parent}); choose it with -o dataset.topics.left_info=TOPIC "
                                f"or give a calibration YAML with {CALIBRATION_OVERRIDE}")
            with self._guard("cannot read the CameraInfo", info_topic):
                left_msg = self._first_message(self._open_reader(), info_topic)
            calib = calibration_from_camera_info(left_msg, info_topic)
            self.calibration_source = f"{self.root} topic {info_topic}"
            if "right" in self.roles:
                right_topic = self._info_topic("right")
                if right_topic is None:
                    raise DataError(f"{self.root}: no CameraInfo topic for the right images {self.roles['right']}; choose "
                                    "it with -o dataset.topics.right_info=TOPIC or give a calibration YAML with "
                                    f"{CALIBRATION_OVERRIDE}")
                with self._guard("cannot read the CameraInfo", right_topic):
                    right_msg = self._first_message(self._open_reader(), right_topic)
                calib.right = calibration_from_camera_info(right_msg, right_topic)
                (R1, P1), (R2, P2) = camera_info_rectification(left_msg), camera_info_rectification(right_msg)
                if P2[0, 0] <= 0 or P2[0, 3] == 0:
                    raise DataError(f"{right_topic}: CameraInfo P has no baseline (P[0,3] = {P2[0, 3]}); a stereo pair "
                                    f"needs rectified camera_infos or a calibration YAML ({CALIBRATION_OVERRIDE})")
                baseline = -P2[0, 3] / P2[0, 0]
                T_CLCR = np.eye(4)  # X_CL = R1^T (R2 X_CR + [b, 0, 0])
                T_CLCR[:3, :3] = R1.T @ R2
                T_CLCR[:3, 3] = R1.T @ np.array([baseline, 0.0, 0.0])
                calib.T_CLCR = T_CLCR
                self.stereo_rectification = (R1, R2, P1[:, :3].copy(), P2)
                self.calibration_source += f" + {right_topic}"
        if cfg.T_BC is not None:
            calib.T_BC = np.asarray(cfg.T_BC, dtype=np.float64).reshape(4, 4)
        return calib.validate(self.calibration_source)

    def _check_first_images(self) -> None:
        """DataError naming the topic when the first image's size or encoding does not fit."""
        calib = self.raw_calibration
        for role in ("left", "right", "depth"):
            if role not in self.roles:
                continue
            cam = calib.right if role == "right" and calib.right is not None else calib
            try:
                img = self._read_role(role, int(self._frame_ordinals[role][0]))
            except FrameReadError as exc:
                raise DataError(f"{self.root}: {exc}") from exc
            h, w = img.shape[:2]
            if (w, h) != (cam.width, cam.height):
                raise DataError(f"{self.root}: images of topic {self.roles[role]} are {w}x{h} but the calibration "
                                f"({self.calibration_source}) is for {cam.width}x{cam.height}")

    # ------------------------------------------------------------ frames
    def _read_role(self, role: str, ordinal: int) -> np.ndarray:
        index = self._indices_by_role[role]
        with self._lock:
            with self._guard("cannot read a message", index.topic, FrameReadError):
                cursor = self._cursors.get(role)
                if cursor is None or cursor.reader is not self._open_reader():
                    cursor = self._cursors[role] = _Cursor(self._open_reader(), index)
                raw = cursor.read(ordinal)
                msg = self._deserialize(raw, index.msgtype)
        img = image_from_message(msg, index.msgtype, index.topic, depth=role == "depth")
        stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        if stamp != int(index.stamps_ns[ordinal]):
            raise FrameReadError(f"{index.topic}: message {ordinal} has stamp {stamp}, indexed {index.stamps_ns[ordinal]}")
        return img

    def _read_sized(self, role: str, raw_index: int) -> np.ndarray:
        """The role's image of a raw frame; FrameSizeError naming the topic when its size is not the calibration's."""
        ordinal = int(self._frame_ordinals[role][raw_index])
        img = self._read_role(role, ordinal)
        cam = self.raw_calibration.right if role == "right" and self.raw_calibration.right is not None else self.raw_calibration
        h, w = img.shape[:2]
        if (w, h) != (cam.width, cam.height):
            raise FrameSizeError(f"{self.roles[role]}: message {ordinal} is {w}x{h}, expected {cam.width}x{cam.height} "
                                 f"(the calibration's size, {self.calibration_source})")
        return img

    def _read_raw(self, raw_index: int) -> RawFrame:
        image = self._read_sized("left", raw_index)
        right = depth = None
        if "right" in self.roles and self.config.load_right:
            right = self._read_sized("right", raw_index)
            if right.ndim == 3:
                import cv2  # deferred: OpenCV

                right = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)
        if "depth" in self.roles and self.config.load_depth:
            depth = self._read_sized("depth", raw_index)
        return RawFrame(image, None, right, depth)

    # ------------------------------------------------------------ info
    def topic_table(self) -> list[dict]:
        """Image, depth, IMU and CameraInfo topics with message counts and rates (Hz): from the header
        stamps of the topics in use, from the log times of the others (read once for this)."""
        used = {topic: role for role, topic in self.roles.items()}
        out = []
        for topic, msgtype in sorted(self.topic_types.items()):
            if msgtype not in (IMAGE, COMPRESSED, IMU, CAMERA_INFO):
                continue
            kind = ("imu" if msgtype == IMU else "camera_info" if msgtype == CAMERA_INFO
                    else "depth" if topic in self.depth_topics else "image")
            count = self.topic_counts[topic]
            index = self._indices_by_role.get(used.get(topic, ""))
            if index is not None and index.stamps_ns.size > 1:
                rate = (index.stamps_ns.size - 1) / ((index.stamps_ns[-1] - index.stamps_ns[0]) / 1e9)
            elif used.get(topic) == "imu" and self.imu is not None and len(self.imu) > 1:
                rate = (len(self.imu) - 1) / float(self.imu.timestamps[-1] - self.imu.timestamps[0])
            else:
                rate = self._log_rate(topic)
            out.append({"topic": topic, "type": msgtype, "kind": kind, "role": used.get(topic),
                        "messages": count, "rate_hz": round(float(rate), 3)})
        return out

    def _log_rate(self, topic: str) -> float:
        """Messages per second of a topic not indexed at open, from its log times (reads the topic once)."""
        with self._lock, self._guard("cannot read the messages", topic):
            reader = self._open_reader()
            conns = [c for c in reader.connections if c.topic == topic]
            times = [log_ns for _, log_ns, _ in reader.messages(connections=conns)]
        span = (max(times) - min(times)) / 1e9 if len(times) > 1 else 0.0
        return (len(times) - 1) / span if span > 0 else 0.0

    def summary(self) -> dict:
        out = super().summary()
        out["topics"] = self.topic_table()
        out["ros_version"] = 2 if self._ros2 else 1
        return out


def _check_increasing(root: Path, topic: str, stamps_ns: np.ndarray) -> None:
    if stamps_ns.size > 1:
        bad = np.flatnonzero(np.diff(stamps_ns) <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise DataError(f"{root}: topic {topic}: header stamp of message {i} ({stamps_ns[i]} ns) is not after the "
                            f"previous one ({stamps_ns[i - 1]} ns); stamps must be strictly increasing")
