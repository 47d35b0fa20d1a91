"""``fgslam localize MAP --data SEQ --out DIR``: track a new sequence against a stored map (``fgslam
run ... --save-map MAP``) without growing it (:mod:`fgslam.localize.sequence`)."""

from __future__ import annotations

import argparse
import json
import signal
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

from ..core.config import load_config
from . import FORMAT_CHOICES, add_config_arguments, add_selection_arguments

if TYPE_CHECKING:
    import numpy as np

    from ..run.config import SlamConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("map", metavar="MAP", help="stored map (fgslam run ... --save-map MAP)")
    parser.add_argument("--data", required=True, metavar="PATH", help="dataset folder (or video file)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the outputs of a previous run in --out (without it such a folder is an error)")
    parser.add_argument("--format", default="auto", choices=FORMAT_CHOICES, help="dataset loader (default: detect)")
    add_selection_arguments(parser)
    add_config_arguments(parser, "LocalizeConfig", "fgslam/configs/localize.yaml")


def run(args: argparse.Namespace) -> int:
    from ..localize.localizer import LocalizeConfig  # deferred: localisation pulls torch (fgslam --help stays fast)
    from ..localize.sequence import run_localization  # deferred: as above
    from ..run.prepare import prepare_output, remove_previous_outputs  # deferred: as above
    from ..run.signals import StopOnSignal  # deferred: as above

    config = load_config(LocalizeConfig, args.config, args.overrides)

    def prepare_out(out: Path) -> None:  # fgslam run's rule for --out, once the map and the sequence are checked:
        prepare_output(out, args.data, args.overwrite)  # writable, not the dataset folder nor inside it, no previous outputs
        if args.overwrite:  # unless --overwrite: then removed
            remove_previous_outputs(out)

    with StopOnSignal((signal.SIGINT, signal.SIGTERM)):  # a stop writes the frames so far (then exit 130 / 143)
        s = run_localization(args.map, args.data, args.out, config, fmt=args.format, start=args.start, end=args.end,
                             stride=args.stride, prepare_out=prepare_out, odometry=MapRunOdometry)
    if args.json:
        print(json.dumps(s))
        return 0
    odo = s["odometry_run"]
    by_odometry = f", {s['odometry']} by the anchored odometry" if odo["ran"] else ""
    print(f"localised {s['localised']} of {s['frames']} frames ({100 * s['localised_fraction']:.1f} %: "
          f"{s['tracked']} tracked, {s['relocalised']} relocalised{by_odometry}) in "
          f"{s['map']} ({s['map_keyframes']} keyframes); {s['cpu_ms_per_frame']:.1f} ms CPU per frame")
    if odo["note"]:
        print(f"odometry: {odo['note']}")
    ev = s["evaluation"]
    if ev is not None:
        print(f"ATE of the localised poses: {ev['ate_rmse_m']:.4f} m ({ev['align']}; holding the first pose: "
              f"{ev['stationary_ate_rmse_m']:.4f} m)")
    print(f"outputs: {args.out} ({', '.join(s['outputs'])})")
    return 0


class MapRunOdometry:
    """The sequence's odometry for :func:`fgslam.localize.sequence.run_localization`
    (:class:`fgslam.localize.anchor.OdometryFactory`): the map run's own SLAM config as visual odometry
    (:meth:`odometry_config`) on the sequence's frames; a frame's pose only where it was tracked (a motion
    model's prediction is no pose)."""

    @staticmethod
    def odometry_config(map_config: dict) -> "SlamConfig":
        """The map run's config without what does not belong to an odometry of another sequence: its
        outputs (defaults: this run writes nothing), loop closure (a correction would move the odometry's
        frame under the anchor's fit), factor plugins (their files are the map run's) and the IMU."""
        from ..core.config import from_dict
        from ..run.config import SlamConfig

        settings = {key: value for key, value in map_config.items() if key not in ("output", "factors")}
        config = from_dict(SlamConfig, settings, "the map run's config (stored in the map)")
        config.loop_closure.mode = "off"
        config.imu.enabled = False
        return config

    @classmethod
    def dataset_streams(cls, map_config: dict) -> dict[str, bool]:
        """The streams the odometry reads (``fgslam run``'s rule, :func:`fgslam.run.config.dataset_config_for`)."""
        from ..run.config import dataset_config_for

        ds = dataset_config_for(cls.odometry_config(map_config))
        return {"load_rgb": ds.load_rgb, "load_depth": ds.load_depth, "load_right": ds.load_right, "load_imu": False}

    def __init__(self, map_config: dict, calibration: Any) -> None:
        from ..run.session import Slam  # deferred: torch, gtsam

        self.slam = Slam(self.odometry_config(map_config), calibration, keep_frames=False,
                         where="fgslam localize (odometry)")

    def track(self, frame: Any) -> Optional[np.ndarray]:
        result = self.slam.track_frame(frame)
        return result.T_WC if result.tracked else None

    def close(self) -> None:
        self.slam.abort()
