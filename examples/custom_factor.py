"""Add your own factor to fgslam's graph: a plugin class named in the config's ``factors`` list.

    python examples/custom_factor.py PATH/TO/SEQUENCE --preset handheld_rgbd --end 100

The plugin below adds a weak "no sudden jump" factor between consecutive keyframes: a GTSAM
``BetweenFactorSimilarity3`` towards the identity with a large sigma. Any GTSAM factor on the
keyframe pose keys (``Similarity3``: camera-to-world, metres) can be added the same way.
"""

from __future__ import annotations

import argparse

import gtsam

import fgslam

SIGMA = 10.0  # weak: a hint, not a constraint (rotation in rad, translation in metres, log-scale)


class WeakSmoothness:
    """A factor plugin: built as ``WeakSmoothness(options, key)``, then ``attach(backend)`` once."""

    added = 0  # factors added by the run's plugins (a class count: the config check builds one too)

    def __init__(self, options: dict, key: str) -> None:
        self.key = key  # the config key ("factors[0]"): the owner of this plugin's factors
        self.sigma = float(options.get("sigma", SIGMA))
        self.previous: int | None = None  # the pose key of the previous keyframe

    def attach(self, backend) -> None:
        self.backend = backend
        backend.on_keyframe(self.on_keyframe)  # called after each new keyframe

    def on_keyframe(self, kf_id: int, timestamp: float, pose_key: int) -> None:
        if self.previous is not None:
            noise = gtsam.noiseModel.Isotropic.Sigma(7, self.sigma)
            factor = gtsam.BetweenFactorSimilarity3(self.previous, pose_key, gtsam.Similarity3(), noise)
            self.backend.add_factor(factor, owner=self.key)
            WeakSmoothness.added += 1
        self.previous = pose_key


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="sequence folder or video")
    parser.add_argument("--preset", default="handheld_rgbd", help="preset name")
    parser.add_argument("--end", type=int, default=None, help="stop after this raw frame index")
    args = parser.parse_args()

    overrides = {"factors": [{"class": f"{__name__}:WeakSmoothness", "options": {"sigma": SIGMA}}]}
    if args.end is not None:
        overrides["dataset.end"] = args.end
    dataset = fgslam.open_dataset(args.data, args.preset, overrides=overrides)
    with fgslam.Slam.from_preset(args.preset, dataset.camera, overrides=overrides) as slam:
        for frame in dataset:
            slam.track(frame.image, frame.timestamp, depth=frame.depth, right=frame.image_right)
    trajectory = slam.finish()
    print(f"{len(trajectory)} poses; the plugin added {WeakSmoothness.added} factors between keyframes")


if __name__ == "__main__":
    main()
