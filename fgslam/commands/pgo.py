"""``fgslam pgo``: optimise a 2-D or 3-D g2o pose graph with gtsam's Levenberg-Marquardt."""

from __future__ import annotations

import argparse
import json

from ..core.config import load_config
from ..run.pgo import PGOConfig, run_pgo
from . import add_config_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.g2o", help="input pose graph (VERTEX/EDGE_SE2 or SE3:QUAT)")
    parser.add_argument("--out", metavar="OUT.g2o", default=None, help="write the optimised graph here")
    parser.add_argument(
        "--init", choices=("chordal", "as-is"), default=None, help="initialisation (default: the config's, chordal)"
    )
    add_config_arguments(parser, "PGOConfig", "fgslam/configs/pgo.yaml")


def run(args: argparse.Namespace) -> int:

    overrides = list(args.overrides or [])
    if args.init is not None:
        overrides.append(f"init={args.init}")
    config = load_config(PGOConfig, args.config, overrides)
    result = run_pgo(args.file, config, out=args.out)
    summary = result.summary()
    summary["init"] = config.init
    summary["out"] = args.out
    if args.json:
        print(json.dumps(summary))
        return 0
    dropped = summary["dropped_edges"]
    print(
        f"{summary['file']}: {summary['dim']}-D, {summary['vertices']} vertices, {summary['edges']} edges"
        + (f" ({dropped} dropped: non-positive-definite information)" if dropped else "")
    )
    print(f"  init           {config.init}")
    print(f"  initial cost   {summary['initial_cost']:.9g}")
    print(f"  final cost     {summary['final_cost']:.9g}")
    print(f"  iterations     {summary['iterations']} ({'converged' if summary['converged'] else 'NOT converged'})")
    print(
        f"  time           {summary['time_s']:.3f} s "
        f"(read {summary['read_time_s']:.3f} s, build + init {summary['init_time_s']:.3f} s, "
        f"LM {summary['optimize_time_s']:.3f} s)"
    )
    if args.out is not None:
        print(f"  wrote          {args.out}")
    return 0
