"""Export of a finished run folder (``fgslam export RUN_DIR --colmap DIR | --ply FILE``).

A run folder holds ``summary.json`` and, since maps are exported, ``map.npz``
(:mod:`fgslam.export.map`). A COLMAP export lays out ``DIR/sparse/0/`` (the model) and
``DIR/images/`` (the frames as the frontend saw them: undistorted, resized; read again from the
dataset recorded in ``summary.json``, unless ``images=False``), the layout COLMAP's MVS and
Gaussian-splatting trainers expect. A PLY export leaves out the map's far points (near-zero inverse
depths: :class:`~fgslam.export.ply.PlyExportConfig`). Either is written into a temporary sibling and
moved into place once complete (:mod:`fgslam.export.inplace`): a failed or interrupted export leaves
nothing behind and keeps a previous output. ``--overwrite`` replaces a PLY file, or a folder that is a
previous COLMAP export (holds ``sparse/``) or empty: never another folder.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config import from_dict
from ..core.errors import ConfigError, DataError
from ..io.datasets import CALIBRATION_FILE_FORMATS, DatasetConfig, open_dataset
from ..io.datasets.common import SAME_FRAME_DT
from ..io.run_files import SUMMARY_FILE, TUM_FILE
from ..io.trajectory import read_trajectory
from .colmap import IMAGES_SUBDIR, SPARSE_SUBDIR, ColmapExportConfig, build_reconstruction, write_model
from .inplace import check_target, refuse_existing, written_in_place
from .map import MAP_FILE, RunMap, load_run_map
from .ply import PlyExportConfig, kept_points, write_ply

logger = logging.getLogger(__name__)

IMAGE_NAME = "{index:06d}.png"
#: the folder of a COLMAP export's models (``sparse/0``...): what marks a folder as one (``--overwrite``)
COLMAP_MODELS_SUBDIR = SPARSE_SUBDIR.parent


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
        raise DataError(f"{run}: " + missing_map_reason(summary))
    return RunFolder(run, summary, load_run_map(run / MAP_FILE))


def missing_map_reason(summary: dict[str, Any]) -> str:
    """Why a run folder has no map, from its ``summary.json``: the run's own reason when it gave no
    frame a pose (it never initialised, it failed: then it writes no map), the map's write error or
    note, and only for a run with poses that wrote no map at all the advice to rerun with
    ``output.write_map=true``."""
    if summary.get("frames_with_pose") == 0:
        why = summary.get("error")
        return f"the run produced no pose, so it has no map ({MAP_FILE})" + (f": {why}" if why else "")
    why = (summary.get("output_errors") or {}).get("map")
    note = next((n for n in summary.get("notes", []) if MAP_FILE in n), None)
    if why or note:
        return f"the run folder has no map ({MAP_FILE}): {why or note}"
    if ((summary.get("config") or {}).get("output") or {}).get("write_map") is False:
        return f"the run folder has no map ({MAP_FILE}): the run had output.write_map=false; rerun the sequence with true"
    return (f"the run folder has no map ({MAP_FILE}) (written by runs with output.write_map=true since fgslam "
            "exports maps; rerun the sequence)")


def check_ply_output(path: Path, overwrite: bool) -> None:
    """A PLY target: a file name; an existing file is refused unless ``overwrite`` (then replaced once the
    new one is written, :func:`~fgslam.export.inplace.written_in_place`), a folder always."""
    if path.is_dir():
        raise ConfigError(f"{path}: is a folder (--ply takes a file name, e.g. {path / 'map.ply'})")
    refuse_existing(path, overwrite)


def check_colmap_output(path: Path, overwrite: bool) -> None:
    """A COLMAP target: an existing one that is not a previous COLMAP export (a folder holding ``sparse/``)
    or an empty folder is refused, --overwrite never deletes another folder; one that is, unless
    ``overwrite``."""
    if not (path.exists() or path.is_symlink()):
        return
    if not path.is_dir():
        raise ConfigError(f"{path}: exists and is not a folder; --overwrite replaces only a previous COLMAP export")
    try:
        replaceable = (path / COLMAP_MODELS_SUBDIR).is_dir() or not any(path.iterdir())
    except OSError as exc:
        raise DataError(f"{path}: cannot read the folder: {exc.strerror or exc}") from exc
    if not replaceable:
        raise ConfigError(f"{path}: not a previous COLMAP export (no {COLMAP_MODELS_SUBDIR}/ in it, not empty); "
                          "--overwrite replaces only those: choose another folder")
    refuse_existing(path, overwrite)


def export_ply(run: RunFolder, path: str | Path, overwrite: bool = False,
               config: PlyExportConfig | None = None) -> dict[str, Any]:
    """Write the map's finite points (without the far ones, ``config.max_point_range_factor``) as a PLY
    file; returns what was written."""
    path = Path(path)
    config = config or PlyExportConfig()
    m = run.run_map.map
    keep, limit = kept_points(m.X_W, m.T_WC[:, :3, 3], config)
    with written_in_place(path, overwrite=overwrite, check=check_ply_output) as tmp:
        write_ply(tmp, m.X_W[keep], m.colour[keep])
    left_out = m.num_points - int(keep.sum())
    if left_out:
        logger.info("PLY: %d of %d points left out (non-finite%s)", left_out, m.num_points,
                    "" if limit is None else f", or farther than {limit:.4g} from every keyframe")
    return {"ply": str(path), "points": int(keep.sum()), "points_left_out": left_out, "range_limit": limit}


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
        if j < 0 or abs(t[j] - stamp) > SAME_FRAME_DT:  # the same frame's time, not a relative tolerance (epoch times)
            continue
        index = int(idx[j])
        if index not in keyframe_indices:
            out[index] = (IMAGE_NAME.format(index=index), T)
    return out


def export_colmap(run: RunFolder, out_dir: str | Path, all_frames: bool = False, fmt: str = "bin",
                  images: bool = True, overwrite: bool = False, config: ColmapExportConfig | None = None) -> dict[str, Any]:
    """Write the run's COLMAP model (and frame images) into ``out_dir``; returns what was written."""
    out = Path(out_dir)
    check_target(out, overwrite, check_colmap_output)  # a missing parent folder is refused, as for --ply
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
    result: dict[str, Any] = {"colmap": str(out), "model": str(out / SPARSE_SUBDIR), "format": fmt, **stats.to_dict()}
    # a failure (the dataset's images not there) leaves nothing behind, and a previous export as it was
    with written_in_place(out, overwrite=overwrite, folder=True, check=check_colmap_output) as tmp:
        write_model(rec, tmp / SPARSE_SUBDIR, fmt)
        if images:
            wanted = {int(i) for i in run_map.keyframe_frame_indices()} | {int(Path(n).stem) for n, _ in extra.values()}
            result["images_written"] = write_frame_images(run, tmp / IMAGES_SUBDIR, sorted(wanted))
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
    if ds_info.get("format", "auto") not in (*CALIBRATION_FILE_FORMATS, "auto"):  # an older run's key, never read
        ds_cfg.calibration_file = None
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
