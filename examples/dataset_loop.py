"""Run fgslam from Python over a recorded sequence, one frame at a time.

    python examples/dataset_loop.py PATH/TO/SEQUENCE --preset handheld_rgbd --end 100

The frames come from ``fgslam.open_dataset`` (any layout ``fgslam run --data`` reads), already
undistorted and resized for the preset; your own processing can go between reading and tracking.
Writes the final trajectory (TUM format: ``t tx ty tz qx qy qz qw``, camera-to-world) to ``--out``.
"""

from __future__ import annotations

import argparse

import numpy as np

import fgslam


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="sequence folder (TUM, EuRoC, KITTI, 7-Scenes, ...) or video")
    parser.add_argument("--preset", default="handheld_rgbd", help="preset name (fgslam run --help lists them)")
    parser.add_argument("--end", type=int, default=None, help="stop after this raw frame index")
    parser.add_argument("--out", default="trajectory_tum.txt", help="where to write the trajectory")
    args = parser.parse_args()

    overrides = {} if args.end is None else {"dataset.end": args.end}
    dataset = fgslam.open_dataset(args.data, args.preset, overrides=overrides)
    with fgslam.Slam.from_preset(args.preset, dataset.camera, overrides=overrides) as slam:
        for frame in dataset:
            result = slam.track(frame.image, frame.timestamp, depth=frame.depth, right=frame.image_right)
            if result.index % 20 == 0:
                where = "no pose yet" if result.T_WC is None else np.array2string(result.T_WC[:3, 3], precision=3)
                print(f"frame {result.index:4d}  t={result.t:8.3f} s  {result.status:<12} {where}")
    trajectory = slam.finish()  # the final trajectory, after the last optimisation
    keyframes = slam.keyframes()
    print(f"{len(trajectory)} poses, {len(keyframes)} keyframes, path {trajectory.path_length():.2f} (map units)")
    trajectory.write(args.out, "tum")  # t tx ty tz qx qy qz qw, camera-to-world
    print(f"trajectory: {args.out}")


if __name__ == "__main__":
    main()
