"""Save a map from Python, read it back, and localise frames in it.

    python examples/read_map.py PATH/TO/SEQUENCE --preset handheld_rgbd --end 100 --map kitchen.map

Builds a map from the first frames of the sequence (unless ``--map`` already exists: a map saved by
``fgslam run ... --save-map`` or by this script), prints its keyframes, then localises every
``--every``-th frame of the sequence in it: a pose in the map's frame, or "not localised".
"""

from __future__ import annotations

import argparse
from pathlib import Path

import fgslam


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="sequence folder or video")
    parser.add_argument("--preset", default="handheld_rgbd", help="preset name")
    parser.add_argument("--end", type=int, default=None, help="frames used to build the map")
    parser.add_argument("--map", default="fgslam.map", help="the stored map (built when missing)")
    parser.add_argument("--every", type=int, default=5, help="localise every N-th frame")
    args = parser.parse_args()

    overrides = {} if args.end is None else {"dataset.end": args.end}
    if not Path(args.map).exists():
        dataset = fgslam.open_dataset(args.data, args.preset, overrides=overrides)
        with fgslam.Slam.from_preset(args.preset, dataset.camera, overrides=overrides) as slam:
            for frame in dataset:
                slam.track(frame.image, frame.timestamp, depth=frame.depth, right=frame.image_right)
        slam.finish()
        slam.save_map(args.map)
        print(f"saved {args.map}")

    localizer = fgslam.Slam.localize_in(args.map)
    keyframes = localizer.keyframes()
    print(f"{args.map}: {len(keyframes)} keyframes, {localizer.width}x{localizer.height} images")
    for kf_id, t, T_WC in list(zip(keyframes.ids, keyframes.t, keyframes.T_WC))[:5]:
        print(f"  keyframe {kf_id:4d}  t={t:8.3f} s  position {' '.join(f'{v:+.3f}' for v in T_WC[:3, 3])}")

    dataset = fgslam.open_dataset(args.data, args.preset, overrides={**overrides, "dataset.stride": args.every})
    found = 0
    for frame in dataset:
        result = localizer.track(frame.image, frame.timestamp)
        found += result.T_WC is not None
    print(f"localised {found} of {len(dataset)} frames")


if __name__ == "__main__":
    main()
