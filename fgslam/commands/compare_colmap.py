"""``fgslam compare-colmap --data PATH``: fgslam against pycolmap's structure from motion on the same
frames (see :mod:`fgslam.export.compare`): time of each and the ratio, registered frames, ATE of
each against the ground truth (Sim(3)), point-cloud accuracy and completion against each other;
``compare.json`` and ``compare.png`` in ``--out``.
"""

from __future__ import annotations

import argparse
import json

HELP = "run pycolmap's SfM and fgslam (monocular) on the same frames and compare time, ATE and point clouds"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, metavar="PATH", help="dataset folder")
    parser.add_argument("--frames", type=int, default=None, metavar="N", help="the first N frames (default: all)")
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="output folder (default: compare-colmap-<sequence name>); refused when it exists "
                             "and is not empty, unless --overwrite")
    parser.add_argument("--overwrite", action="store_true", help="write into an existing output folder")
    parser.add_argument("--format", default="auto", help="dataset loader (default: detect)")
    parser.add_argument("--preset", default=None, metavar="CONFIG",
                        help="fgslam config or preset (default: the format's monocular preset, e.g. patch_kitti_mono)")
    parser.add_argument("-o", "--override", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a field of the fgslam run config (repeatable)")
    parser.add_argument("--features", type=int, default=None, metavar="N", help="COLMAP SIFT features per image (default 8192)")
    parser.add_argument("--no-progress", action="store_true", help="no progress lines")
    parser.add_argument("--json", action="store_true", help="print the report as one JSON object")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace
    from pathlib import Path

    from ..errors import ConfigError, DataError
    from ..export.compare import CompareConfig, compare_colmap, preset_for
    from ..io.datasets import DatasetConfig, open_dataset
    from ..slam import load_slam_config, open_slam_dataset, prepare_output_dir

    if args.frames is not None and args.frames < 3:
        raise ConfigError(f"--frames must be at least 3 (got {args.frames})")
    probe = open_dataset(args.data, args.format, DatasetConfig(load_right=False, load_depth=False, load_imu=False))
    preset = args.preset or preset_for(probe.format, probe.root)
    overrides = ["sensor=mono", *args.overrides]
    if args.frames is not None:
        overrides.append(f"dataset.end={probe.config.start + args.frames * probe.config.stride}")
    config = load_slam_config(preset, overrides)
    out = Path(args.out or f"compare-colmap-{probe.name}")
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise ConfigError(f"{out}: output folder exists and is not empty (use --overwrite or another --out)")
    prepare_output_dir(out, args.data)
    dataset = open_slam_dataset(args.data, config, args.format)
    cfg = CompareConfig()
    if args.features is not None:
        if args.features < 16:
            raise ConfigError(f"--features must be at least 16 (got {args.features})")
        cfg = replace(cfg, colmap=replace(cfg.colmap, max_num_features=args.features))
    report = compare_colmap(dataset, config, out, cfg, progress=not args.no_progress, preset=preset)
    if args.json:
        print(json.dumps(report, default=float))
    else:
        print(format_report(report))
    if report["colmap"].get("error"):  # no comparison: the report says so, and the command fails
        raise DataError(f"{report['colmap']['error']} ({report['colmap']['models']} models; see {out / 'colmap'}): "
                        f"no comparison, report in {report['outputs']['json']}")
    return 0


def format_report(r: dict) -> str:
    fg, cm = r["fgslam"], r["colmap"]
    fmt = lambda v: "-" if v is None else f"{v:.4f} m"  # noqa: E731
    lines = [
        f"{r['dataset']['path']} ({r['dataset']['format']}, {r['dataset']['frames']} frames, load {r['load_average_start']})",
        f"  fgslam ({fg['preset']}): {fg['wall_s']:.1f} s wall ({fg['cpu_s']:.1f} s CPU), {fg['registered_frames']} frames posed, "
        f"{fg['points']} points, ATE {fmt(fg.get('ate_m'))} (on COLMAP's frames {fmt(fg.get('ate_on_colmap_frames_m'))})",
        f"  COLMAP: {cm['wall_s']:.1f} s wall ({cm['cpu_s']:.1f} s CPU), {cm['registered_frames']} frames registered "
        f"({cm['models']} models), {cm['points']} points, ATE {fmt(cm.get('ate_m'))}",
    ]
    if cm.get("error"):
        lines.append(f"  ratio:  none ({cm['error']})")
    else:
        lines.append(f"  ratio:  COLMAP / fgslam time {r['speed_ratio_wall']:.1f}x wall, {r['speed_ratio_cpu']:.1f}x CPU"
                     + (f"; ATE fgslam / COLMAP {r['ate_ratio']:.2f}" if r.get("ate_ratio") is not None else ""))
    if r.get("clouds"):
        d = r["clouds"]["fgslam_against_colmap"]
        lines.append(f"  clouds: fgslam against COLMAP: accuracy {d['accuracy_mean']:.4f} (median {d['accuracy_median']:.4f}), "
                     f"completion {d['completion_mean']:.4f} (median {d['completion_median']:.4f}) in the {r['clouds']['frame']} frame")
    lines.append(f"  outputs: {', '.join(r['outputs'].values())}")
    return "\n".join(lines)
