"""``fgslam eval GT EST``: compare an estimated trajectory with ground truth (ATE, RPE, KITTI errors).

Association: pose k with pose k when either file is KITTI without a times file (same length
required), otherwise nearest timestamps (``--max-diff``, ``--offset``). KITTI t_rel / r_rel are
reported when the ground truth is in KITTI format (or with ``--kitti-metrics``). The estimate must
have one pose per timestamp (a repeated one is an error naming its line); the ground truth may
repeat a rounded stamp. ``--plot`` creates the plot's own folder, nothing above it (checked before
the evaluation); the results are printed even when writing the plot fails.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

from ..core.config import load_config
from ..core.errors import DataError
from ..eval.trajectory import EvalConfig, evaluate
from ..io import plot  # called through the module: a test replaces plot.plot_trajectories
from ..io.trajectory import read_trajectory
from . import add_config_arguments


_FORMATS = ("tum", "kitti", "euroc")
_ALIGN = ("se3", "sim3", "none", "first-pose")
_PLANES = ("xz", "xy", "yz")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("gt", help="ground-truth trajectory file")
    parser.add_argument("est", help="estimated trajectory file")
    parser.add_argument("--format", required=True, choices=_FORMATS, help="format of GT (and of EST by default)")
    parser.add_argument("--est-format", choices=_FORMATS, help="format of EST when it differs from --format")
    parser.add_argument("--gt-times", help="KITTI times file of GT (one timestamp per line)")
    parser.add_argument("--est-times", help="KITTI times file of EST")
    parser.add_argument("--align", choices=_ALIGN, help="alignment of EST to GT (default: se3)")
    parser.add_argument("--association", choices=("timestamp", "index"), help="override the automatic choice")
    parser.add_argument("--max-diff", type=float, help="largest timestamp difference of a match, s")
    parser.add_argument("--offset", type=float, help="time offset added to EST timestamps, s")
    parser.add_argument("--delta-frames", type=int, help="frame step of the per-frame RPE")
    parser.add_argument("--delta-m", type=float, help="distance (m) of the per-distance RPE")
    parser.add_argument("--kitti-metrics", action="store_true", help="report KITTI t_rel/r_rel for non-KITTI GT")
    add_config_arguments(parser, "EvalConfig", "fgslam/configs/eval.yaml")
    parser.add_argument("--plot", metavar="PNG", help="write a top-view plot of GT and the aligned EST")
    parser.add_argument("--plane", choices=_PLANES, help="plot plane (default: xz for KITTI, else xy)")


def run(args: argparse.Namespace) -> int:
    gt_format = args.format
    est_format = args.est_format or args.format
    config = load_config(EvalConfig, args.config, args.overrides)
    flags = {
        "align": args.align,
        "max_time_diff": args.max_diff,
        "time_offset": args.offset,
        "rpe_delta_frames": args.delta_frames,
        "rpe_delta_meters": args.delta_m,
    }
    config = dataclasses.replace(config, **{k: v for k, v in flags.items() if v is not None})
    index_based = (gt_format == "kitti" and args.gt_times is None) or (est_format == "kitti" and args.est_times is None)
    association = args.association or ("index" if index_based else "timestamp")
    kitti_metrics = config.kitti_metrics or args.kitti_metrics or gt_format == "kitti"
    config = dataclasses.replace(config, association=association, kitti_metrics=kitti_metrics)

    if args.plot:
        plot.check_plot_path(args.plot)
    gt = read_trajectory(args.gt, gt_format, args.gt_times)
    est = read_trajectory(args.est, est_format, args.est_times, unique_timestamps=True)
    result = evaluate(gt, est, config)

    plot_error = None
    if args.plot:
        plane = args.plane or ("xz" if gt_format == "kitti" else "xy")
        title = f"ATE {result.ate.rmse:.3f} m ({config.align}, {result.n_matched} poses)"
        try:
            plot.plot_trajectories(args.plot, gt, result.aligned_est, title=title, plane=plane,
                                   errors={"estimate": plot.pose_errors(result.matched_gt, result.aligned_est)})
        except DataError as exc:  # the results are still printed, then the error
            plot_error = exc

    if args.json:
        out = {
            "gt": str(args.gt),
            "est": str(args.est),
            "gt_format": gt_format,
            "est_format": est_format,
            "config": dataclasses.asdict(config),
            **result.to_dict(),
            "plot": args.plot if plot_error is None else None,
        }
        print(json.dumps(out))
    else:
        print(_format_text(result, args, plot_error is None))
    if plot_error is not None:
        raise plot_error
    return 0


def _stats_line(label: str, stats) -> str:
    return (
        f"{label:<22} rmse {stats.rmse:.4f}  mean {stats.mean:.4f}  median {stats.median:.4f}  "
        f"std {stats.std:.4f}  min {stats.min:.4f}  max {stats.max:.4f}  (n={stats.n})"
    )


def _format_text(result, args: argparse.Namespace, plot_written: bool) -> str:
    lines = [
        f"ground truth: {args.gt} ({result.n_gt} poses; path length over the {result.n_matched} matched poses "
        f"{result.gt_path_length_m:.2f} m)",
        f"estimate:     {args.est} ({result.n_est} poses), matched {result.n_matched}",
        f"alignment:    {result.align}, scale {result.alignment.s:.4f}",
        _stats_line("ATE trans [m]", result.ate),
    ]
    for rpe in (result.rpe_frames, result.rpe_meters):
        if rpe is None:
            continue
        delta = f"{rpe.delta:g} {rpe.unit}"
        lines.append(_stats_line(f"RPE {delta} trans [m]", rpe.trans))
        lines.append(_stats_line(f"RPE {delta} rot [deg]", rpe.rot_deg))
    if result.kitti is not None:
        k = result.kitti
        lines.append(
            f"KITTI t_rel {k.t_rel_percent:.4f} %  r_rel {k.r_rel_deg_per_100m:.4f} deg/100m  ({k.n_segments} segments)"
        )
    if args.plot and plot_written:
        lines.append(f"plot:         {args.plot}")
    return "\n".join(lines)
