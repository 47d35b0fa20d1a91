"""``fgslam demo``: the command line of :mod:`fgslam.run.demo` (render ``room-loop``, run patch SLAM, report)."""

from __future__ import annotations

import argparse
import json


DEFAULT_OUT = "fgslam_demo"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default=DEFAULT_OUT, metavar="DIR", help=f"output folder (default: ./{DEFAULT_OUT})")
    parser.add_argument("--frames", type=int, default=None, metavar="N",
                        help="frames to render and run (default: the config's, one loop)")
    parser.add_argument("--config", default=None, metavar="YAML", help="demo config (default: the preset fgslam/configs/demo.yaml)")
    parser.add_argument("-o", "--override", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override, e.g. -o scene.width=640 -o slam.sensor=stereo (repeatable)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the report")


def run(args: argparse.Namespace) -> int:
    from ..run.demo import format_demo_report, load_demo_config, run_demo  # deferred: the demo runs SLAM (torch; fgslam --help stays fast)

    overrides = list(args.overrides)
    if args.frames is not None:
        overrides.append(f"scene.frames={args.frames}")
    config = load_demo_config(args.config, overrides)
    result = run_demo(config, args.out, progress=not args.json)
    if args.json:
        print(json.dumps(result, default=str))
    else:
        print(format_demo_report(config.scene, result["sequence"], result["summary"], result["total_s"]))
    return 0
