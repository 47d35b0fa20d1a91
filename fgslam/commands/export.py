"""``fgslam export RUN_DIR --colmap DIR | --ply FILE | --bag OUT``: the map of a finished run as a COLMAP
model (``DIR/sparse/0`` + ``DIR/images``) or a PLY point cloud (see :mod:`fgslam.export.run_export`), or
its trajectory as a ROS bag (:mod:`fgslam.export.bag`)."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

from ..core.config import check_ranges
from ..export.bag import BagExportConfig, export_bag
from ..export.ply import PlyExportConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", metavar="RUN_DIR", help="output folder of `fgslam run` (holds map.npz)")
    target = parser.add_mutually_exclusive_group(required=True)
    target.add_argument("--colmap", metavar="DIR", help="write a COLMAP model into DIR (sparse/0 and images/)")
    target.add_argument("--ply", metavar="FILE", help="write the map's points as a PLY file")
    target.add_argument("--bag", metavar="OUT", help="write the trajectory as a ROS bag: nav_msgs/Path, PoseStamped, "
                        "tf (ROS 1 when OUT ends in .bag, else a ROS 2 bag folder; needs fgslam[bag])")
    parser.add_argument("--bag-storage", choices=("sqlite3", "mcap"), default="sqlite3", help="ROS 2 bag storage")
    parser.add_argument("--all-frames", action="store_true", help="COLMAP: every posed frame as an image, not only keyframes")
    parser.add_argument("--colmap-format", choices=("bin", "txt"), default="bin", help="COLMAP: binary (default) or text files")
    parser.add_argument("--no-images", action="store_true", help="COLMAP: the model only (do not read the dataset again)")
    parser.add_argument("--max-point-range", type=float, default=None, metavar="FACTOR",
                        help="PLY: leave out points farther from every keyframe than FACTOR x the map's median such "
                             f"distance (far points; default {PlyExportConfig().max_point_range_factor:g}; 0: keep every "
                             "point; PlyExportConfig.max_point_range_factor)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output: a PLY file, a ROS bag, a "
                        "previous COLMAP export (a folder holding sparse/) or an empty folder; never another folder")
    parser.add_argument("--json", action="store_true", help="print what was written as one JSON object")


def ply_config(args: argparse.Namespace) -> PlyExportConfig:
    """The PLY export's settings: the defaults, ``--max-point-range`` (checked against its range)."""
    config = PlyExportConfig()
    if args.max_point_range is not None:
        config = replace(config, max_point_range_factor=args.max_point_range)
        check_ranges(config, source="--max-point-range")
    return config


def run(args: argparse.Namespace) -> int:
    if args.bag:
        result = export_bag(args.run_dir, args.bag, overwrite=args.overwrite,
                            config=BagExportConfig(storage=args.bag_storage))
        print(json.dumps(result) if args.json else
              f"wrote {result['poses']} poses to {result['bag']} (ROS {result['ros_version']}: {', '.join(result['topics'])})")
        return 0
    from ..export.run_export import export_colmap, export_ply, open_run_folder  # deferred: torch (fgslam --help stays fast)

    run_folder = open_run_folder(args.run_dir)
    if args.ply:
        result = export_ply(run_folder, args.ply, overwrite=args.overwrite, config=ply_config(args))
        text = (f"wrote {result['points']} points to {result['ply']}"
                + (f" ({result['points_left_out']} far or non-finite points left out)" if result["points_left_out"] else ""))
    else:
        result = export_colmap(run_folder, args.colmap, all_frames=args.all_frames, fmt=args.colmap_format,
                               images=not args.no_images, overwrite=args.overwrite)
        text = (f"wrote COLMAP model {result['model']} ({result['format']}): {result['images']} images, "
                f"{result['points']} points, {result['observations']} observations (median reprojection error "
                f"{result['median_reprojection_px']:.2f} px; {result['dropped_observations']} observations and "
                f"{result['dropped_points']} points left out)"
                + (f"; {result['images_written']} images in {args.colmap}/images" if "images_written" in result else ""))
    print(json.dumps(result) if args.json else text)
    return 0
