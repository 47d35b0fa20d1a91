"""Export of a finished run folder (``fgslam export RUN_DIR --colmap DIR | --ply FILE``).

A run folder holds ``summary.json`` and, since maps are exported, ``map.npz``
(:mod:`fgslam.export.map`). A COLMAP export lays out ``DIR/sparse/0/`` (the model) and
``DIR/images/`` (the frames as the frontend saw them: undistorted, resized; read again from the
dataset recorded in ``summary.json``, unless ``images=False``), the layout COLMAP's MVS and
Gaussian-splatting trainers expect.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config import from_dict
from ..core.errors import ConfigError, DataError
from ..io.datasets import DatasetConfig, open_dataset
from ..io.run_files import SUMMARY_FILE, TUM_FILE
from ..io.trajectory import read_trajectory
from .colmap import IMAGES_SUBDIR, SPARSE_SUBDIR, ColmapExportConfig, build_reconstruction, write_model
from .map import MAP_FILE, RunMap, load_run_map
from .ply import write_ply

logger = logging.getLogger(__name__)

IMAGE_NAME = "{index:06d}.png"


@dataclass
class RunFolder:
    """A run folder's summary and map."""

    path: Path
    summary: dict[str, Any]
    run_map: RunMap


def open_run_folder(run_dir: str | Path) -> RunFolder:
    """Read ``summary.json`` and ``map.npz`` of a run folder (DataError naming what is missing)."""
    run = Path(run_dir)
    if not run.is_dir():
        raise DataError(f"{run}: no such run folder")
    if not (run / SUMMARY_FILE).is_file():
        raise DataError(f"{run}: not a run folder (no {SUMMARY_FILE}; give the --out folder of `fgslam run`)")
    try:
        summary = json.loads((run / SUMMARY_FILE).read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"{run / SUMMARY_FILE}: cannot read: {exc}") from exc
    if not (run / MAP_FILE).is_file():
        why = (summary.get("output_errors") or {}).get("map")
        note = next((n for n in summary.get("notes", []) if MAP_FILE in n), None)
        raise DataError(f"{run}: the run folder has no map ({MAP_FILE})"
                        + (f": {why}" if why else f": {note}" if note else
                           " (written by runs with output.write_map=true since fgslam exports maps; rerun the sequence)"))
    return RunFolder(run, summary, load_run_map(run / MAP_FILE))


def check_output(path: Path, overwrite: bool) -> None:
    """Refuse an existing output unless ``overwrite`` (then it is removed first)."""
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise ConfigError(f"{path}: exists (use --overwrite to replace it)")
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()


def export_ply(run: RunFolder, path: str | Path, overwrite: bool = False) -> dict[str, Any]:
    path = Path(path)
    check_output(path, overwrite)
    if not path.parent.is_dir():
        raise DataError(f"{path}: folder {path.parent} does not exist")
    m = run.run_map.map
    write_ply(path, m.X_W, m.colour)
    return {"ply": str(path), "points": m.num_points}


def _frame_names(run_map: RunMap) -> dict[int, str]:
    return {int(k): IMAGE_NAME.format(index=int(i)) for k, i in zip(run_map.map.kf_ids, run_map.keyframe_frame_indices())}


def _all_frame_poses(run: RunFolder, keyframe_indices: set[int]) -> dict[int, tuple[str, np.ndarray]]:
    """Frames that are not keyframes, with their poses from ``trajectory_tum.txt``: dataset index ->
    (image name, T_WC)."""
    path = run.path / TUM_FILE
    if not path.is_file():
        raise DataError(f"{run.path}: --all-frames needs {TUM_FILE} (the run wrote no trajectory)")
    traj = read_trajectory(path, "tum")
    t, idx = run.run_map.frame_timestamps, run.run_map.frame_indices
    out: dict[int, tuple[str, np.ndarray]] = {}
    for stamp, T in zip(traj.timestamps, traj.T_WC):
        j = int(np.argmin(np.abs(t - stamp))) if t.size else -1
        if j < 0 or abs(t[j] - stamp) > 1e-6 * max(1.0, abs(stamp)):
            continue
        index = int(idx[j])
        if index not in keyframe_indices:
            out[index] = (IMAGE_NAME.format(index=index), T)
    return out


def export_colmap(run: RunFolder, out_dir: str | Path, all_frames: bool = False, fmt: str = "bin",
                  images: bool = True, overwrite: bool = False, config: ColmapExportConfig | None = None) -> dict[str, Any]:
    """Write the run's COLMAP model (and frame images) into ``out_dir``; returns what was written."""
    out = Path(out_dir)
    check_output(out, overwrite)
    run_map = run.run_map
    if run_map.map.num_keyframes == 0:
        raise DataError(f"{run.path / MAP_FILE}: the map has no keyframes: nothing to export to COLMAP")
    names = _frame_names(run_map)
    extra: dict[int, tuple[str, np.ndarray]] = {}
    if all_frames:
        others = _all_frame_poses(run, {int(i) for i in run_map.keyframe_frame_indices()})
        first_id = run_map.map.num_keyframes + 1
        extra = {first_id + n: others[i] for n, i in enumerate(sorted(others))}
    rec, stats = build_reconstruction(run_map, names, config, extra)
    out.mkdir(parents=True)
    write_model(rec, out / SPARSE_SUBDIR, fmt)
    result: dict[str, Any] = {"colmap": str(out), "model": str(out / SPARSE_SUBDIR), "format": fmt, **stats.to_dict()}
    if images:
        wanted = {int(i) for i in run_map.keyframe_frame_indices()} | {int(Path(n).stem) for n, _ in extra.values()}
        result["images_written"] = write_frame_images(run, out / IMAGES_SUBDIR, sorted(wanted))
    return result


def write_frame_images(run: RunFolder, image_dir: Path, indices: list[int]) -> int:
    """Read frames ``indices`` again from the run's dataset (its path, format and dataset config
    from ``summary.json``) and write them as the frontend saw them (colour when the source has it)."""
    import cv2  # deferred: cv2

    ds_info, cfg = run.summary.get("dataset", {}), run.summary.get("config", {})
    path = ds_info.get("path")
    if not path or not Path(path).exists():
        raise DataError(f"{run.path}: the run's dataset {path!r} is not there any more; export with --no-images "
                        "(the model alone), or from the folder where the dataset is")
    ds_cfg = from_dict(DatasetConfig, cfg.get("dataset", {}), source=str(run.path / SUMMARY_FILE), prefix="dataset")
    ds_cfg.load_right, ds_cfg.load_depth, ds_cfg.load_imu, ds_cfg.load_rgb = False, False, False, True
    dataset = open_dataset(path, ds_info.get("format", "auto"), ds_cfg)
    c = dataset.calibration
    if (int(c.width), int(c.height)) != (run.run_map.width, run.run_map.height) or not np.allclose(c.K, run.run_map.intrinsics):
        raise DataError(f"{path}: the dataset's images ({c.width}x{c.height}, K {np.round(c.K, 3).tolist()}) are not "
                        f"the run's ({run.run_map.width}x{run.run_map.height}); export with --no-images")
    image_dir.mkdir(parents=True, exist_ok=True)
    for index in indices:
        frame = dataset[index]
        image = frame.image if frame.rgb is None else cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)
        target = image_dir / IMAGE_NAME.format(index=index)
        if not cv2.imwrite(str(target), image):
            raise DataError(f"{target}: cannot write the image")
    return len(indices)
