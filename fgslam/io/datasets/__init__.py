"""Dataset loaders: one lazy ``Dataset`` interface over TUM RGB-D, EuRoC, KITTI, TartanAir,
7-Scenes, image folders, videos and ROS 1 / ROS 2 bags.  ``open_dataset`` picks the loader from the folder layout.

Detection order (``fmt="auto"``): ``camera:SPEC`` -> ``camera`` (a live OpenCV capture); a ``.bag`` file or a folder with ``metadata.yaml`` -> ``rosbag``
(ROS 1 / ROS 2);
a file with a video extension -> ``video``; ``dso/camchain.yaml`` with ``mav0/cam0`` -> ``tumvi``; ``mav0/cam0`` or
``cam0/data.csv`` -> ``euroc``; ``image_0/`` + ``calib.txt`` -> ``kitti``; ``image_left/`` ->
``tartanair``; ``rgb.txt`` -> ``tum``; ``seq-NN/frame-*.color.*`` (or such frames directly) ->
``7scenes``; a folder with images -> ``folder``. A folder that matches none of them but holds ``*.db3`` /
``*.mcap`` files (a ROS 2 bag without its ``metadata.yaml``), or such a file given alone: DataError naming it.
"""

from __future__ import annotations

from pathlib import Path

from ...core.errors import DataError
from .capture import PREFIX as CAPTURE_PREFIX
from .capture import CaptureDataset, is_capture
from .common import Dataset, DatasetConfig
from .euroc import EurocDataset, mav0_dir
from .folder import VIDEO_EXTENSIONS, FolderDataset, VideoDataset
from .kitti import KittiDataset, list_images
from .rosbag import RosbagDataset, check_ros2_bag_parts, is_bag
from .sevenscenes import SevenScenesDataset, is_sequence_dir
from .tartanair import TartanAirDataset
from .tum import TumDataset
from .tumvi import TumviDataset, tumvi_root

LOADERS: dict[str, type[Dataset]] = {
    "tum": TumDataset,
    "euroc": EurocDataset,
    "tumvi": TumviDataset,
    "kitti": KittiDataset,
    "tartanair": TartanAirDataset,
    "7scenes": SevenScenesDataset,
    "folder": FolderDataset,
    "video": VideoDataset,
    "rosbag": RosbagDataset,
    "camera": CaptureDataset,
}
FORMATS = tuple(LOADERS)
#: the loaders that read ``dataset.calibration_file``; the others take the calibration of their own files
CALIBRATION_FILE_FORMATS = ("tum", "folder", "video", "rosbag", "camera")


def detect_format(path: str | Path) -> str:
    """Loader name for the layout at ``path``; DataError when nothing matches."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if is_bag(path):
        return "rosbag"
    if path.is_file():
        if path.suffix.lower() in VIDEO_EXTENSIONS:
            return "video"
        check_ros2_bag_parts(path)  # a ROS 2 bag's storage file given instead of its folder is named as such
        raise DataError(f"{path}: a file that is neither a video ({', '.join(VIDEO_EXTENSIONS)}) nor a ROS 1 .bag; "
                        "give a dataset folder")
    if tumvi_root(path) is not None:
        return "tumvi"
    if mav0_dir(path) is not None:
        return "euroc"
    if (path / "image_0").is_dir() and (path / "calib.txt").is_file():
        return "kitti"
    if (path / "image_left").is_dir():
        return "tartanair"
    if (path / "rgb.txt").is_file():
        return "tum"
    if is_sequence_dir(path) or any(is_sequence_dir(p) for p in path.glob("seq-*")):
        return "7scenes"
    if list_images(path):
        return "folder"
    # last: a stray *.db3 / *.mcap beside another layout's files never hides that layout
    check_ros2_bag_parts(path)  # a ROS 2 bag without its metadata.yaml is named as such
    raise DataError(
        f"{path}: unknown dataset layout (looked for metadata.yaml (ROS 2 bag), "
        "dso/camchain.yaml + mav0/cam0 (TUM-VI), mav0/cam0 (EuRoC), image_0 + calib.txt (KITTI), "
        "image_left (TartanAir), rgb.txt (TUM), seq-NN/frame-*.color.* (7-Scenes), image files (folder))"
    )


def open_dataset(path: str | Path, fmt: str = "auto", config: DatasetConfig | None = None) -> Dataset:
    """Open the sequence at ``path`` with the loader ``fmt`` (``auto``: detected from the layout; a path
    ``camera:SPEC`` is a live capture, :mod:`fgslam.io.datasets.capture`)."""
    if is_capture(path) and fmt in ("auto", "camera"):
        return CaptureDataset(str(path), config if config is not None else DatasetConfig())
    if fmt == "camera":
        raise DataError(f"{path}: the camera format takes {CAPTURE_PREFIX}SPEC (a device number, a stream URL or a file)")
    path = Path(path)
    if fmt == "auto":
        fmt = detect_format(path)
    elif fmt not in LOADERS:
        raise DataError(f"{path}: unknown dataset format {fmt!r} (expected auto or one of {', '.join(FORMATS)})")
    elif not path.exists():
        raise DataError(f"{path}: no such file or folder")
    config = config if config is not None else DatasetConfig()
    if config.calibration_file and fmt not in CALIBRATION_FILE_FORMATS:
        raise DataError(f"{path}: dataset.calibration_file is read by the {', '.join(CALIBRATION_FILE_FORMATS)} "
                        f"loaders; the {fmt} loader takes the calibration of its own files (leave the key out)")
    config.warn_unused_bag_keys(fmt)
    return LOADERS[fmt](path, config)


__all__ = ["CALIBRATION_FILE_FORMATS", "Dataset", "DatasetConfig", "FORMATS", "LOADERS", "detect_format", "is_capture", "open_dataset"] + [
    cls.__name__ for cls in LOADERS.values()
]
