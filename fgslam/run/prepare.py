"""The checks of a run before any work, each run once: the config, the rerun target, the output folder
(created, writable, not the dataset folder nor inside it, no previous run's outputs unless
``overwrite``), the dataset against the config (the images the sensor needs, the image size, the
estimated peak memory: :mod:`fgslam.run.memory`), the stored map's camera (``--map``) and the IMU
stream (units, axes, clock).

Two ways in, both ending in a :class:`PreparedRun` that the runner (:func:`fgslam.run.runner.run_prepared`)
trusts:

- :func:`prepare_run`, the command line's order (``fgslam run``, ``fgslam batch``, the demo): from
  the dataset's path, the output folder is checked before the dataset is opened, so that a run that
  cannot write its outputs costs no loading;
- :func:`prepare_opened`, for a dataset the caller has opened (:func:`fgslam.run.runner.run_slam`):
  it is checked against the config given here (the caller may have opened it for another).

A refused run leaves no output folder behind: the output folder, when its checks created it
(:attr:`PreparedRun.created`), is removed again when a later check refuses the run, if it is still
empty (``os.rmdir``: a folder that existed before, or holds anything, is never removed). Its parents
stay, also those created with it: runs in parallel (a batch's cells of one config) share them, and
one refused run removing a parent would pull it from under a run creating its own folder there.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from ..core.config import check_ranges
from ..core.errors import ConfigError, DataError
from ..export.mapfile import check_map_camera, check_map_file, load_stored_map
from ..export.rerun import check_rerun_target
from ..io.calibration import Calibration
from ..io.datasets import CaptureDataset, Dataset, DatasetConfig, is_capture, open_dataset
from ..io.live import LiveConfig
from ..services.imu_checks import check_imu_stream
from .config import SlamConfig, dataset_config_for
from .files import DEPTH_DIR, RUN_OUTPUT_FILES
from .memory import check_run_memory

logger = logging.getLogger(__name__)



@dataclass(frozen=True)
class PreparedRun:
    """A run whose inputs are checked (module docstring): the opened dataset, the config, the output
    folder (created and writable; ``overwrite``: a previous run's outputs there are removed when the
    run starts), the rerun target (None: none) and the IMU input checks' warnings."""

    dataset: Dataset
    config: SlamConfig
    out: Path
    overwrite: bool = False
    rerun: Optional[str] = None
    imu_warnings: list[str] = field(default_factory=list)
    live: Optional[LiveConfig] = None  # live mode: frames at their own pace, the oldest dropped when behind
    created: Optional[Path] = None  # the output folder, when the checks created it: removed again (if empty)
    # when the run is refused before it writes anything (remove_created_folder)


def prepare_run(data: str | Path, config: SlamConfig, out_dir: str | Path, *, fmt: str = "auto",
                overwrite: bool = False, rerun: Optional[str] = None, live: Optional[LiveConfig] = None) -> PreparedRun:
    """Check a run from its dataset's path, in the command line's order: the config, the rerun target,
    the output folder (:func:`prepare_output`), the stored map's file (``output.extend_map``), then the
    dataset opened and checked (:func:`open_slam_dataset`), the stored map's camera and the IMU stream.

    Raises:
        ConfigError: a check failed (naming the key, the folder or the file).
        DataError: the output folder cannot be created or written, or the data cannot be read.
    """
    check_config(config)
    if live is not None:
        check_ranges(live, "live.", "the live options (--live-speed, --live-queue)")
    check_capture_map(data, is_capture(data), config)
    if rerun:
        check_rerun_target(rerun)
    created = new_folder(out_dir)
    try:
        out = prepare_output(out_dir, data, overwrite)
        if config.output.extend_map:  # a missing or foreign map: refused before the dataset is opened
            check_map_file(config.output.extend_map)
        dataset = open_slam_dataset(data, config, fmt)
        check_extended_map(dataset, config, data)
        if isinstance(dataset, CaptureDataset):  # a capture is live: a device at its own pace, a file at its rate
            live = live if live is not None else LiveConfig()
            if not dataset.is_file:
                live = LiveConfig(queue=live.queue, paced=False)
        return PreparedRun(dataset, config, out, overwrite, rerun, check_imu_input(dataset, config), live, created)
    except BaseException:  # refused: no output folder left behind (only an empty one created here)
        remove_created_folder(created)
        raise


def prepare_opened(dataset: Dataset, config: SlamConfig, out_dir: str | Path, *, overwrite: bool = False,
                   rerun: Optional[str] = None) -> PreparedRun:
    """Check a run on a dataset the caller opened: the config, the dataset against it
    (:func:`check_dataset`), the output folder (:func:`prepare_output`), the rerun target, the stored
    map's camera (``output.extend_map``) and the IMU stream. Raises as :func:`prepare_run`."""
    check_config(config)
    check_capture_map(dataset.root, isinstance(dataset, CaptureDataset), config)
    check_dataset(dataset, config)
    created = new_folder(out_dir)
    try:
        out = prepare_output(out_dir, dataset.root, overwrite)
        if rerun:
            check_rerun_target(rerun)
        check_extended_map(dataset, config, dataset.root)
        return PreparedRun(dataset, config, out, overwrite, rerun, check_imu_input(dataset, config),
                           created=created)
    except BaseException:  # refused: no output folder left behind (only an empty one created here)
        remove_created_folder(created)
        raise


def check_extended_map(dataset: Dataset, config: SlamConfig, data: str | Path) -> None:
    """A stored map the run continues (``output.extend_map``) must have been made with this camera:
    refused before any work (:func:`fgslam.export.mapfile.check_map_camera` names what differs)."""
    if config.output.extend_map:
        c = dataset.calibration
        check_map_camera(load_stored_map(config.output.extend_map), c.K, c.width, c.height,
                         config.output.extend_map, data)


def check_config(config: SlamConfig) -> None:
    """The config's own checks and every field's range (a config built in code is checked too)."""
    config.validate()
    check_ranges(config)


# ----------------------------------------------------------------------------------------- dataset side


def open_slam_dataset(path: str | Path, config: SlamConfig, fmt: str = "auto") -> Dataset:
    """Open the dataset at ``path`` with the streams ``config`` needs (:func:`fgslam.run.config.dataset_config_for`)
    and check it against ``config`` (:func:`check_dataset`)."""
    dataset = open_dataset(path, fmt, dataset_config_for(config))
    check_dataset(dataset, config)
    return dataset


def check_dataset(dataset: Dataset, config: SlamConfig) -> None:
    """Raise ConfigError unless ``dataset`` has what ``config.sensor`` needs, images of at least
    ``dataset.min_image_side`` pixels, and an estimated peak memory within ``max_memory_gib``
    (:mod:`fgslam.run.memory`)."""
    check_sensor(dataset, config.sensor)
    check_image_size(dataset)
    check_run_memory(config, dataset)


def check_capture_map(data: str | Path, capture: bool, config: SlamConfig) -> None:
    """Raise ConfigError when a live capture (``capture``) would save or extend a stored map: both need the
    run's frames again at the end, which a capture cannot give."""
    if capture and (config.output.save_map or config.output.extend_map):
        raise ConfigError(f"{data}: --save-map and --map need the run's frames again at the end, which a live "
                          "capture cannot give: record it to a video file and run on that")


def check_image_size(dataset: Dataset) -> None:
    """Raise ConfigError when the dataset's output images (after resizing and cropping) are smaller
    than ``dataset.min_image_side`` on a side, naming the resize keys and both sizes."""
    check_output_size(dataset.config, dataset.calibration, dataset.raw_calibration)


def check_output_size(cfg: DatasetConfig, calibration: Calibration, raw: Optional[Calibration]) -> None:
    """:func:`check_image_size` of the output camera ``calibration`` made from ``raw`` with ``cfg`` (a
    loader's, or ``fgslam.Slam``'s for a script's images)."""
    width, height = int(calibration.width), int(calibration.height)
    if min(width, height) >= cfg.min_image_side:
        return
    source = f" from {raw.width}x{raw.height}" if raw is not None else ""
    raise ConfigError(
        f"{cfg.resize_text()} gives {width}x{height} images{source}"
        f"{f' (after cropping to a multiple of {cfg.crop_multiple})' if cfg.crop_multiple > 1 else ''}; "
        f"both sides must be at least dataset.min_image_side={cfg.min_image_side} pixels"
    )


def check_sensor(dataset: Dataset, sensor: str) -> None:
    """Raise ConfigError when ``dataset`` lacks the images ``sensor`` needs (stereo: right images,
    rgbd: depth maps)."""
    where = f"{dataset.root} ({dataset.format})"
    if sensor == "stereo" and not dataset.has_stereo:
        why = "dataset.load_right is false" if not dataset.config.load_right else "it has no right camera images"
        raise ConfigError(
            f"sensor 'stereo' needs right camera images but {where}: {why}; use sensor=mono or a stereo dataset"
        )
    if sensor == "rgbd" and not dataset.has_depth:
        why = "dataset.load_depth is false" if not dataset.config.load_depth else "it has no depth maps"
        raise ConfigError(f"sensor 'rgbd' needs depth maps but {where}: {why}; use sensor=mono or an RGB-D dataset")
    if sensor not in ("mono", "stereo", "rgbd"):
        raise ConfigError(f"unknown sensor {sensor!r} (expected mono, stereo or rgbd)")


def check_imu_input(dataset: Dataset, config: SlamConfig) -> list[str]:
    """With ``imu.enabled`` and an IMU stream: its units, axes and clock checked against the frames
    (:func:`fgslam.services.imu_checks.check_imu_stream`: a recognised mistake is a DataError naming
    it); the warnings found (none otherwise)."""
    if not (config.imu.enabled and dataset.imu is not None):
        return []
    return check_imu_stream(dataset.imu, dataset.timestamps, config.imu.checks, config.imu.gravity,
                            where=str(dataset.root), T_BC=dataset.calibration.T_BC)


# ----------------------------------------------------------------------------------------- output side


def prepare_output(out_dir: str | Path, data: str | Path | None, overwrite: bool) -> Path:
    """The output folder checked before any work: created and writable, not the dataset folder ``data``
    nor inside it (:func:`prepare_output_dir`), and holding no previous run's outputs unless
    ``overwrite`` (:func:`check_previous_outputs`; they are removed when the run starts,
    :func:`remove_previous_outputs`)."""
    out = prepare_output_dir(out_dir, data)
    check_previous_outputs(out, overwrite)
    return out


def prepare_output_dir(out_dir: str | Path, data: str | Path | None = None) -> Path:
    """Create the output folder and check that it is writable, before any work.

    Raises ConfigError when it is the dataset folder ``data`` or inside it (outputs would mix with
    the input data), DataError when it cannot be created or written (a file in the way, no
    permission, a read-only or full file system)."""
    out = Path(out_dir)
    if data is not None:
        out_abs, data_abs = out.resolve(), Path(data).resolve()
        if out_abs == data_abs or data_abs in out_abs.parents:
            where = "is the dataset folder" if out_abs == data_abs else f"is inside the dataset folder {data}"
            raise ConfigError(f"output folder {out} {where}: outputs would mix with the input data; "
                              "choose a folder outside it")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"{out}: cannot create the output folder: {exc.strerror or exc}") from exc
    try:
        fd, probe = tempfile.mkstemp(prefix=".fgslam-write-test-", dir=out)
        try:
            os.write(fd, b"fgslam")
            os.fsync(fd)
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        raise DataError(f"{out}: the output folder is not writable: {exc.strerror or exc}") from exc
    return out


def new_folder(path: str | Path) -> Optional[Path]:
    """``path`` (absolute) when it does not exist yet, the folder that the output checks then create;
    None for one that exists (or a link, even a broken one: never the run's to remove)."""
    folder = Path(path).absolute()
    return None if folder.exists() or folder.is_symlink() else folder


def remove_created_folder(folder: Optional[Path]) -> None:
    """Remove ``folder``, the output folder a refused run created (:func:`new_folder`; None: none), if
    it is still empty; ``os.rmdir`` never removes a folder holding anything, which then stays. Its
    parents stay (module docstring)."""
    if folder is None:
        return
    try:
        folder.rmdir()
    except OSError:  # not empty, or already gone: left as it is
        return
    logger.debug("removed the output folder %s created by the refused run", folder)


def check_save_map_path(save_map: str | Path, out_dir: str | Path, extend_map: str | Path | None,
                        overwrite: bool) -> None:
    """``--save-map``: ConfigError when its folder does not exist, when the path is one of the run's
    own output files in ``out_dir`` (:data:`~fgslam.run.files.RUN_OUTPUT_FILES`, ``depth/``), or an
    existing file that is not the ``--map`` being extended and ``overwrite`` is not given (a map is
    never replaced silently)."""
    path = Path(save_map).resolve()
    if not path.parent.is_dir():
        raise ConfigError(f"--save-map {save_map}: its folder does not exist")
    out = Path(out_dir).resolve()
    if path.parent == out and path.name in RUN_OUTPUT_FILES or out / DEPTH_DIR in (path, *path.parents):
        raise ConfigError(f"--save-map {save_map}: that is one of the run's own output files in {out_dir}; "
                          "choose another name")
    if path.is_dir():
        raise ConfigError(f"--save-map {save_map}: is a folder")
    if path.exists() and not overwrite and (extend_map is None or Path(extend_map).resolve() != path):
        raise ConfigError(f"--save-map {save_map}: the file exists; use --overwrite to replace it "
                          "(or save the extended map over its --map)")


def previous_run_outputs(out_dir: str | Path) -> list[Path]:
    """The outputs of a previous run in ``out_dir`` (:data:`~fgslam.run.files.RUN_OUTPUT_FILES` and ``depth/``)."""
    out = Path(out_dir)
    found = [out / name for name in RUN_OUTPUT_FILES if (out / name).is_file()]
    return found + ([out / DEPTH_DIR] if (out / DEPTH_DIR).is_dir() else [])


def check_previous_outputs(out_dir: str | Path, overwrite: bool) -> None:
    """Refuse an output folder that holds a previous run's outputs (:func:`previous_run_outputs`)
    unless ``overwrite``, so that no output of the previous run is ever taken for one of the new
    run's: ConfigError naming the folder and ``--overwrite``."""
    out = Path(out_dir)
    previous = previous_run_outputs(out)
    if previous and not overwrite:
        names = ", ".join(p.name for p in previous)
        raise ConfigError(f"output folder {out} holds the outputs of a previous run ({names}); "
                          "use --overwrite to replace them, or another --out")


def remove_previous_outputs(out_dir: str | Path) -> None:
    """Remove a previous run's outputs in ``out_dir`` (:func:`previous_run_outputs`; other files are
    left alone), when the run starts. DataError when one cannot be removed."""
    out = Path(out_dir)
    previous = previous_run_outputs(out)
    for path in previous:
        try:
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        except OSError as exc:
            raise DataError(f"{path}: cannot remove the previous run's output: {exc.strerror or exc}") from exc
    if previous:
        logger.info("removed the previous run's outputs in %s: %s", out, ", ".join(p.name for p in previous))
