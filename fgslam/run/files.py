"""The files a run writes into its output folder (stable names: tools and tests read them) and the
set of them that marks a previous run's outputs. ``summary.json``, ``trajectory_tum.txt`` and
``localization.csv`` are named in :mod:`fgslam.io.run_files` (several layers use them)."""

from __future__ import annotations

from ..io.run_files import LOCALIZATION_FILE, SUMMARY_FILE, TUM_FILE

KITTI_FILE = "trajectory_kitti.txt"  # 3x4 rows per pose
KITTI_TIMES_FILE = "trajectory_kitti_times.txt"  # the KITTI rows' timestamps (seconds)
PLOT_FILE = "trajectory.png"
PLY_FILE = "points.ply"
MAP_FILE = "map.npz"  # fgslam.export.map.MAP_FILE
MERGED_TUM_FILE = "merged_trajectory_tum.txt"  # fgslam run --map: frames from the merge on, in the stored map's frame
JOINT_TUM_FILE = "joint_trajectory_tum.txt"  # fgslam run --map: every session's frames after the joint optimisation, by time
MERGE_FILE = "merge.json"  # fgslam run --map: the merge (transform, keyframes) or why none
DEPTH_DIR = "depth"  # depth/<kf:06d>.png per keyframe (output.write_depth)

#: What a run writes into its output folder (a previous run's outputs: refused, or removed with overwrite).
RUN_OUTPUT_FILES = (TUM_FILE, KITTI_FILE, KITTI_TIMES_FILE, SUMMARY_FILE, SUMMARY_FILE + ".tmp", PLOT_FILE, PLY_FILE,
                    MAP_FILE, MERGED_TUM_FILE, JOINT_TUM_FILE, MERGE_FILE, LOCALIZATION_FILE)
