"""``fgslam info PATH``: describe a dataset (format, frames, resolution, rate, sensors, intrinsics)."""

from __future__ import annotations

import argparse
import json

from ..core.config import load_config
from ..io.datasets import DatasetConfig, open_dataset
from . import FORMAT_CHOICES, add_config_arguments

#: ``-o dataset.KEY=VALUE``, the spelling of ``fgslam run`` and ``localize`` (and of the loaders' messages), is
#: ``-o KEY=VALUE`` of this command's DatasetConfig too
DATASET_PREFIX = "dataset."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", help="dataset folder (or video file, ROS 1 .bag, ROS 2 bag folder)")
    parser.add_argument("--format", default="auto", choices=FORMAT_CHOICES, help="loader (default: detect from the layout)")
    add_config_arguments(parser, "DatasetConfig", "fgslam/configs/dataset.yaml")


def run(args: argparse.Namespace) -> int:

    overrides = [o[len(DATASET_PREFIX):] if o.startswith(DATASET_PREFIX) else o for o in args.overrides]
    config = load_config(DatasetConfig, args.config, overrides)
    ds = open_dataset(args.path, args.format, config)
    ds.check_readable()  # images that cannot be read are said so, not described from the calibration
    info = ds.summary()
    if args.json:
        print(json.dumps(info))
        return 0
    yes_no = {True: "yes", False: "no"}
    w, h = info["resolution"]
    rw, rh = info["raw_resolution"]
    lines = [
        f"path:         {info['path']}",
        f"format:       {info['format']}  ({info['name']})",
        f"frames:       {info['frames']}",
        f"resolution:   {w}x{h} (raw {rw}x{rh}, raw distortion {info['raw_distortion_model']})",
        f"rate:         {info['rate_hz']:.3f} Hz",
        f"stereo:       {yes_no[info['stereo']]}" + (f" (baseline {info['baseline_m']:.4f} m)" if "baseline_m" in info else ""),
        f"depth:        {yes_no[info['depth']]}",
        f"imu:          {yes_no[info['imu']]}" + (
            f" ({info['imu_samples']} samples, {info['imu_samples_in_span']} between the first and last frame)"
            if info["imu"] else ""),
        f"ground truth: {yes_no[info['groundtruth']]}" + (f" ({info['groundtruth_poses']} frames)" if info["groundtruth"] else ""),
        "intrinsics:   fx={:.3f} fy={:.3f} cx={:.3f} cy={:.3f}".format(*info["intrinsics"]),
    ]
    for row in info.get("topics", []):  # ROS bags
        lines.append(f"topic:        {row['topic']}  {row['kind']}, {row['messages']} messages, {row['rate_hz']:.3f} Hz"
                     + (f"  (used as {row['role']})" if row["role"] else ""))
    print("\n".join(lines))
    return 0
