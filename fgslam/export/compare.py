"""The pieces of ``fgslam compare-colmap`` that read and write data: its settings, the frames
written for COLMAP, and the point-cloud distances (the comparison that runs both is
:func:`fgslam.commands.compare_colmap.compare_colmap`).

Both run monocular on the same undistorted frames with the same pinhole calibration (COLMAP's kept
fixed): fgslam through :func:`fgslam.run.runner.run_slam`, COLMAP through
:func:`fgslam.export.colmap.run_colmap_sfm` (SIFT on the CPU, sequential matching, incremental
mapping) on the frames written as PNG files (writing them is timed for neither).

Reported: wall and CPU time of each and their ratio, frames each registered, the ATE of each
against the ground truth (Sim(3) alignment: monocular scale), fgslam's ATE over only the frames
COLMAP registered, and the point clouds' accuracy and completion against each other (MASt3R-SLAM
table 3: accuracy = mean distance from each point of a cloud to the nearest point of the
reference, completion = mean distance from each reference point to the nearest point of the
cloud; here fgslam's cloud against COLMAP's, in the ground truth's metres after each run's own
trajectory alignment, or in COLMAP's frame after aligning fgslam's trajectory to COLMAP's when the
sequence has no ground truth).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.config import MAX_COUNT, MAX_SCALAR, ranged
from ..core.errors import DataError
from ..core.mapdata import points_near_cameras
from .colmap import ColmapSfmConfig

COMPARE_JSON = "compare.json"
COMPARE_PNG = "compare.png"
IMAGE_NAME = "{index:06d}.png"  # frame images written for COLMAP (dataset index)


@dataclass
class CompareConfig:
    """``fgslam compare-colmap`` settings (the fgslam run's own config is its preset)."""

    colmap: ColmapSfmConfig = field(default_factory=ColmapSfmConfig)
    max_cloud_points: int = ranged(200000, ge=100, le=MAX_COUNT)  # clouds are subsampled (evenly) to this many points for the distances
    max_point_range_factor: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # cloud metrics leave out points farther from every camera of their run than this x the cloud's median such distance


PRESET_BY_FORMAT = {"kitti": "patch_kitti_mono", "7scenes": "patch_7scenes_mono", "euroc": "patch_euroc_mono"}
DEFAULT_PRESET = "patch_mono"


SYNTH_MARKER = "synth_config.yaml"  # written by `fgslam synth` beside the EuRoC layout


def preset_for(fmt: str, root: str | Path | None = None) -> str:
    """The monocular preset for a dataset format (KITTI, 7-Scenes, EuRoC; else ``patch_mono``);
    ``fgslam synth`` renders (EuRoC layout with ``synth_config.yaml``) get ``patch_mono``."""
    if root is not None and (Path(root) / SYNTH_MARKER).is_file():
        return DEFAULT_PRESET
    return PRESET_BY_FORMAT.get(fmt, DEFAULT_PRESET)


def cloud_distances(cloud: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """Accuracy (cloud -> reference) and completion (reference -> cloud): mean and median nearest
    neighbour distances."""
    from scipy.spatial import cKDTree  # deferred: scipy

    if cloud.shape[0] == 0 or reference.shape[0] == 0:
        return {"accuracy_mean": float("nan"), "accuracy_median": float("nan"),
                "completion_mean": float("nan"), "completion_median": float("nan")}
    acc = cKDTree(reference).query(cloud)[0]
    comp = cKDTree(cloud).query(reference)[0]
    return {"accuracy_mean": float(acc.mean()), "accuracy_median": float(np.median(acc)),
            "completion_mean": float(comp.mean()), "completion_median": float(np.median(comp)),
            "chamfer_mean": float(0.5 * (acc.mean() + comp.mean()))}


def _subsample(X: np.ndarray, n: int) -> np.ndarray:
    X = X[np.all(np.isfinite(X), axis=1)]
    if X.shape[0] <= n:
        return X
    return X[np.linspace(0, X.shape[0] - 1, n).astype(np.int64)]


def compare_clouds(fg_cloud: np.ndarray, cm_cloud: np.ndarray, fg_centres: np.ndarray, cm_centres: np.ndarray,
                   config: "CompareConfig", frame: str) -> dict[str, Any]:
    """Accuracy and completion of fgslam's cloud against COLMAP's, both in one frame, each cloud
    without its points farther from every camera of its own run than ``max_point_range_factor``
    times the median such distance of the cloud (far points: near-zero inverse depths, sky),
    counted in the report (:func:`fgslam.core.mapdata.points_near_cameras`, also the PLY export's rule)."""
    kept, limits = {}, {}
    for name, cloud, centres in (("fgslam", fg_cloud, fg_centres), ("colmap", cm_cloud, cm_centres)):
        cloud = cloud[np.all(np.isfinite(cloud), axis=1)]
        near, limit = points_near_cameras(cloud, centres, config.max_point_range_factor)
        if limit is not None:
            limits[name] = limit
        kept[name] = (cloud[near], int((~near).sum()))
    d = cloud_distances(_subsample(kept["fgslam"][0], config.max_cloud_points),
                        _subsample(kept["colmap"][0], config.max_cloud_points))
    return {"frame": frame, "fgslam_against_colmap": d, "range_limits": limits,
            "far_points_left_out": {"fgslam": kept["fgslam"][1], "colmap": kept["colmap"][1]},
            "note": "accuracy: fgslam points to the nearest COLMAP point; completion: COLMAP points to the nearest "
                    "fgslam point (COLMAP against fgslam swaps the two)"}


def write_frames(dataset, image_dir: Path) -> dict[str, float]:
    """Write the dataset's (undistorted) grey frames as PNG files; returns name -> timestamp."""
    import cv2  # deferred: cv2

    image_dir.mkdir(parents=True, exist_ok=True)
    names: dict[str, float] = {}
    for frame in dataset:
        name = IMAGE_NAME.format(index=frame.index)
        if not cv2.imwrite(str(image_dir / name), frame.image):
            raise DataError(f"{image_dir / name}: cannot write the frame image")
        names[name] = float(frame.timestamp)
    return names
