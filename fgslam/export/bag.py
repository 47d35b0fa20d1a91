"""A run's trajectory as a ROS bag (``fgslam export RUN_DIR --bag OUT``), to play beside the recording.

``OUT`` ending in ``.bag``: a ROS 1 bag; else a ROS 2 bag folder (``storage``: sqlite3 or mcap).
Topics (``BagExportConfig``): ``pose_topic`` (``geometry_msgs/PoseStamped``, one per posed frame),
``tf_topic`` (``tf2_msgs/TFMessage``, ``frame_id -> child_frame_id`` per posed frame) and
``path_topic`` (``nav_msgs/Path``, the whole trajectory once, stamped with its last frame). Poses are
the run's ``trajectory_tum.txt`` (camera-to-world ``T_WC`` of the left camera, stamps of the frames
in the dataset's time base: a bag's header stamps for a bag input). Written with ``rosbags``
(optional extra ``fgslam[bag]``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from ..core.errors import DataError
from .inplace import refuse_existing, written_in_place
from ..io.datasets.rosbag import ROS1_SUFFIX, import_rosbags, is_bag
from ..io.run_files import TUM_FILE
from ..io.trajectory import Trajectory, read_trajectory, rotation_to_quaternion_xyzw

if TYPE_CHECKING:
    from rosbags.interfaces import Connection

logger = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000
TRAJECTORY_FILE = TUM_FILE
PATH_TYPE = "nav_msgs/msg/Path"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
TF_TYPE = "tf2_msgs/msg/TFMessage"
TF_MESSAGE_DEF = "geometry_msgs/TransformStamped[] transforms\n"  # tf2_msgs/TFMessage (not in rosbags' ROS 1 store)
ROS2_BAG_VERSION = 8  # rosbag2 format version written (readable by ROS 2 Humble and later)


@dataclass
class BagExportConfig:
    """Topics and frames of an exported trajectory bag."""

    frame_id: str = "map"  # world frame of the poses
    child_frame_id: str = "fgslam_camera"  # the camera frame (tf child)
    path_topic: str = "/fgslam/path"
    pose_topic: str = "/fgslam/pose"
    tf_topic: str = "/tf"
    storage: Literal["sqlite3", "mcap"] = "sqlite3"  # ROS 2 storage plugin


class BagWriter:
    """ROS 1 (``.bag``) or ROS 2 (folder) bag writer over ``rosbags`` with typed messages (instances of
    the typestore's message classes, built at run time: ``object`` here)."""

    def __init__(self, path: str | Path, storage: str = "sqlite3") -> None:
        import_rosbags()
        from rosbags.typesys import Stores, get_typestore  # deferred: rosbags (optional extra)

        self.path = Path(path)
        self.ros1 = self.path.suffix == ROS1_SUFFIX
        self.typestore = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if TF_TYPE not in self.typestore.types:
            from rosbags.typesys import get_types_from_msg  # deferred: rosbags

            self.typestore.register(get_types_from_msg(TF_MESSAGE_DEF, TF_TYPE))
        self.types = self.typestore.types
        if self.ros1:
            from rosbags.rosbag1 import Writer  # deferred: rosbags

            self._writer = Writer(self.path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer  # deferred: rosbags

            plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}[storage]
            self._writer = Writer(self.path, version=ROS2_BAG_VERSION, storage_plugin=plugin)
        self._connections: dict[str, Connection] = {}
        self._seq = 0

    def __enter__(self) -> "BagWriter":
        self._writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self._writer.close()

    def header(self, stamp_ns: int, frame_id: str) -> object:
        stamp = self.types["builtin_interfaces/msg/Time"](sec=int(stamp_ns // NS_PER_S), nanosec=int(stamp_ns % NS_PER_S))
        if self.ros1:
            self._seq += 1
            return self.types["std_msgs/msg/Header"](seq=self._seq, stamp=stamp, frame_id=frame_id)
        return self.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def write(self, topic: str, msgtype: str, log_ns: int, msg: object) -> None:
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._connections[topic] = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
        data = (self.typestore.serialize_ros1(msg, msgtype) if self.ros1
                else self.typestore.serialize_cdr(msg, msgtype))
        self._writer.write(conn, int(log_ns), data)


def stamp_ns(t: float) -> int:
    """Seconds -> integer nanoseconds (rounded)."""
    return int(round(float(t) * NS_PER_S))


def _pose(types: dict, T: np.ndarray) -> object:
    qx, qy, qz, qw = rotation_to_quaternion_xyzw(T[:3, :3])
    x, y, z = (float(v) for v in T[:3, 3])
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=types["geometry_msgs/msg/Quaternion"](x=float(qx), y=float(qy), z=float(qz), w=float(qw)))


def write_trajectory_bag(traj: Trajectory, out: str | Path, config: BagExportConfig | None = None) -> dict:
    """Write ``traj`` (``T_WC`` per stamp) to the bag ``out``; returns what was written."""
    cfg = config or BagExportConfig()
    out = Path(out)
    with BagWriter(out, cfg.storage) as bag:
        T = bag.types
        poses = []
        for t, T_WC in zip(traj.timestamps, traj.T_WC):
            ns = stamp_ns(t)
            pose = T["geometry_msgs/msg/PoseStamped"](header=bag.header(ns, cfg.frame_id), pose=_pose(T, T_WC))
            poses.append(pose)
            bag.write(cfg.pose_topic, POSE_TYPE, ns, pose)
            p, q = pose.pose.position, pose.pose.orientation
            tf = T["geometry_msgs/msg/TransformStamped"](
                header=bag.header(ns, cfg.frame_id), child_frame_id=cfg.child_frame_id,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=p.x, y=p.y, z=p.z), rotation=q))
            bag.write(cfg.tf_topic, TF_TYPE, ns, T["tf2_msgs/msg/TFMessage"](transforms=[tf]))
        last = stamp_ns(traj.timestamps[-1])
        bag.write(cfg.path_topic, PATH_TYPE, last,
                  T["nav_msgs/msg/Path"](header=bag.header(last, cfg.frame_id), poses=poses))
    return {"bag": str(out), "ros_version": 1 if out.suffix == ROS1_SUFFIX else 2, "poses": len(traj),
            "topics": [cfg.pose_topic, cfg.tf_topic, cfg.path_topic]}


def _check_bag_target(out: Path, overwrite: bool) -> None:
    """An existing ``out`` is replaced only with ``overwrite``, and only when it is a ROS bag."""
    refuse_existing(out, overwrite)
    if out.exists() or out.is_symlink():
        if out.is_symlink() or not is_bag(out):
            raise DataError(f"{out} exists and is not a ROS bag (a .bag file or a folder with metadata.yaml): "
                            "not replaced, even with --overwrite; choose another path")


def export_bag(run_dir: str | Path, out: str | Path, overwrite: bool = False,
               config: BagExportConfig | None = None) -> dict:
    """``fgslam export RUN_DIR --bag OUT``: the run's ``trajectory_tum.txt`` as a ROS bag."""
    run, out = Path(run_dir), Path(out)
    src = run / TRAJECTORY_FILE
    if not src.is_file():
        raise DataError(f"{run}: no {TRAJECTORY_FILE} (give the --out folder of a `fgslam run` that posed frames)")
    traj = read_trajectory(src, "tum")
    if len(traj) == 0:
        raise DataError(f"{src}: empty trajectory")
    # written beside OUT under its own name (the writer reads ROS 1 or 2 from it) and moved into place: a
    # failure leaves OUT as it was (fgslam.export.inplace, as every export)
    with written_in_place(out, overwrite=overwrite, same_name=True, check=_check_bag_target) as tmp:
        result = write_trajectory_bag(traj, tmp, config)
    result["bag"] = str(out)
    logger.info("wrote %d poses to %s", len(traj), out)
    return result
