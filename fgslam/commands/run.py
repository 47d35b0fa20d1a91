"""``fgslam run CONFIG --data PATH --out DIR``: run SLAM on a dataset and write trajectories,
``summary.json`` and ``trajectory.png`` (see :mod:`fgslam.run.runner`).

CONFIG is a YAML file or the name of a preset shipped in the package's ``fgslam/configs/`` folder
(``patch_kitti_mono``, ``patch_7scenes_rgbd``, ``patch_euroc_stereo``, ...). ``-o key=value``
overrides any SlamConfig field, e.g. ``-o sensor=stereo -o dataset.end=200 -o patch.ba.iterations=3``.
"""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING

from ..run.presets import run_presets
from . import FORMAT_CHOICES, add_selection_arguments, selection_overrides

if TYPE_CHECKING:  # the run's results pull torch: imported in run() only (fgslam --help stays fast)
    from ..io.live import LiveConfig
    from ..run.results import RunSummary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    presets = run_presets()  # each preset's own "# description:" line
    width = max(map(len, presets), default=0)
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = "presets (CONFIG), and the data each is for:\n" + "\n".join(
        f"  {name:<{width}}  {text}" for name, text in presets.items())
    parser.add_argument("config", metavar="CONFIG", help="SlamConfig YAML file or preset name (listed below)")
    parser.add_argument("--data", required=True, metavar="PATH",
                        help="dataset folder, video file, or camera:SPEC (a live OpenCV capture: camera:0, an RTSP/HTTP "
                             "URL; with -o dataset.calibration_file=PATH)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the outputs of a previous run in --out (without it such a folder is an error) "
                             "and an existing --save-map file")
    parser.add_argument("--format", default="auto", choices=FORMAT_CHOICES, help="dataset loader (default: detect)")
    add_selection_arguments(parser)  # dataset.start/end/stride, as fgslam localize's
    parser.add_argument("-o", "--override", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a SlamConfig field, e.g. -o sensor=rgbd -o dataset.end=100 (repeatable)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar or lines on stderr")
    parser.add_argument("--rerun", metavar="OUT.rrd", default=None,
                        help="log frames, poses, keyframe points and loop edges to a rerun file (or 'live': a running "
                             "viewer); needs the optional extra fgslam[rerun]")
    parser.add_argument("--live", action="store_true",
                        help="live mode: frames come at their own pace (a recording replays at its timestamps), the "
                             "oldest waiting frame is dropped when the system is behind; the console shows latency "
                             "and drops, summary.json 'live' has them (--data camera:SPEC is always live)")
    parser.add_argument("--live-speed", type=float, default=None, metavar="X",
                        help="live: replay a recording at X times its rate (default 1)")
    parser.add_argument("--live-queue", type=int, default=None, metavar="N",
                        help="live: frames waiting at most before the oldest is dropped (default 1)")
    parser.add_argument("--json", action="store_true", help="print the run summary as one JSON object")
    parser.add_argument("--map", metavar="MAP", default=None,
                        help="continue this stored map: the recording is merged into it once its keyframes localise "
                             "in it (merge.json, merged_trajectory_tum.txt; --save-map saves the merged map)")
    parser.add_argument("--save-map", metavar="MAP", default=None,
                        help="also save the map (keyframes, structure, features, retrieval database, calibration, "
                             "config) to this file, for `fgslam localize` (fgslam/export/mapfile.py); an existing file only "
                             "with --overwrite or when it is the --map being extended")


def run(args: argparse.Namespace) -> int:
    # the config and the checks import neither torch nor OpenCV nor gtsam (tests/test_startup.py): a refused run
    # answers at once; the runner, which pulls them, is imported once every check has passed
    from ..run.config import load_slam_config  # deferred: fgslam --help stays fast
    from ..run.prepare import check_save_map_path, prepare_run  # deferred: as above

    overrides = list(args.overrides) + selection_overrides(args)  # --start/--end/--stride over -o dataset.*
    if args.save_map:
        check_save_map_path(args.save_map, args.out, args.map, args.overwrite)
        overrides.append(f"output.save_map={args.save_map}")
    if args.map:
        overrides.append(f"output.extend_map={args.map}")
    config = load_slam_config(args.config, overrides)
    # every check before any work, once: rerun target, output folder, dataset, the --map's camera
    prepared = prepare_run(args.data, config, args.out, fmt=args.format, overwrite=args.overwrite, rerun=args.rerun,
                           live=live_config(args))
    from ..run.runner import run_prepared  # deferred: torch, OpenCV, gtsam (after the checks, above)

    def report(summary: RunSummary) -> None:  # also when the run then fails or is interrupted (the error line follows)
        print(json.dumps(summary.to_dict(), default=str) if args.json else format_report(summary.to_dict()), flush=True)

    run_prepared(prepared, progress=not args.no_progress, on_summary=report)
    return 0


def live_config(args: argparse.Namespace) -> "LiveConfig | None":
    """The live options of ``--live``, ``--live-speed`` and ``--live-queue`` (None: not live; the speed
    or queue size alone turn live mode on)."""
    from ..io.live import LiveConfig  # deferred: light, but only live runs need it

    if not (args.live or args.live_speed is not None or args.live_queue is not None):
        return None
    default = LiveConfig()
    return LiveConfig(speed=default.speed if args.live_speed is None else args.live_speed,
                      queue=default.queue if args.live_queue is None else args.live_queue)


def inertial_text(i: dict) -> str:
    """One line of the IMU state of ``summary.json`` ``inertial``."""
    if not i["initialized"]:
        text = "not initialised"
    else:
        after = "" if i.get("init_after_s") is None else f" {i['init_after_s']:.2f} s after the first frame"
        text = f"initialised{after}"
        if i.get("scale") is not None:
            text += f", scale {i['scale']:.4f}"
            if i.get("scale_sigma") is not None:
                text += f" +- {i['scale_sigma']:.4f} ({i.get('inertial_only_runs', 0)} inertial-only optimisations)"
        if i.get("gravity_norm") is not None:
            text += f", |g| {i['gravity_norm']:.3f} m/s^2"
        if i.get("bias_gyro_norm") is not None:
            text += f", bias |gyro| {i['bias_gyro_norm']:.4f} rad/s, |accel| {i['bias_accel_norm']:.4f} m/s^2"
    for warning in i.get("input_warnings") or []:
        text += f"; input: {warning}"
    return text


def format_report(s: dict) -> str:
    """A short human-readable report of a run summary (``summary.json`` contents)."""
    lines = [
        f"{s['frontend']} {s['sensor']} on {s['dataset']['name']} ({s['dataset']['format']}, "
        f"{s['dataset']['resolution'][0]}x{s['dataset']['resolution'][1]})",
        f"  frames:     {s['frames_processed']} processed of {s['frames_total']}, {s['frames_with_pose']} with a pose, "
        f"{s['keyframes']} keyframes",
        f"  speed:      {s['fps']:.1f} frames/s overall ({s['wall_s']:.1f} s wall, {s['cpu_s']:.1f} s CPU), "
        f"{s['fps_frontend']:.1f} frames/s frontend",
    ]
    if s["stage_ms_per_frame"]:
        stages = ", ".join(f"{k} {v:.1f}" for k, v in s["stage_ms_per_frame"].items())
        lines.append(f"  stages:     {stages} ms/frame")
    f = s["failures"]
    lines.append(f"  failures:   {f['tracking']} tracking (motion-model poses), {f['no_pose']} without pose, "
                 f"{f['skipped_corrupt']} frames skipped (unreadable or of the wrong size)")
    loop = s.get("loop")
    if loop:
        parts = []
        if "accepted_loops" in loop:
            parts.append(f"classical {loop['accepted_loops']} accepted of {loop['verified_loops']} verified, "
                         f"{loop['corrections_applied']} corrections, {loop['relocalized']} relocalisations")
        if "proximity" in loop:
            p = loop["proximity"]
            parts.append(f"proximity {p['accepted']} accepted of {p['candidates']} candidates, "
                         f"{p['global_ba_runs']} global BAs ({p['global_ba_s']:.1f} s)")
        if "relocalized_in_loaded_map" in loop:
            parts.append(f"relocalised in the loaded map {loop['relocalized_in_loaded_map']} times in "
                         f"{loop['relocalization_attempts']} relocalisation attempts")
        lines.append(f"  loops:      {'; '.join(parts)} (mode {loop['mode']})")
    inertial = s.get("inertial")
    if inertial:
        lines.append(f"  inertial:   {inertial_text(inertial)}")
    ev = s["evaluation"]
    if ev is not None:
        pct = ev["ate_percent_of_path"]
        pct_txt = (f" = {pct:.2f}% of the {ev['gt_path_length_m']:.2f} m ground-truth path over the matched poses"
                   if pct is not None else "")
        lines.append(f"  ATE:        {ev['ate_rmse_m']:.4f} m RMSE ({ev['align']} alignment, scale {ev['scale']:.4f}, "
                     f"{ev['n_matched']} poses){pct_txt}")
    else:
        m = s["motion"]
        lines.append(f"  motion:     path {m['path_length']:.3f}, largest distance from start "
                     f"{m['max_distance_from_start']:.3f} (estimate units; no ground truth evaluated)")
    live = s.get("live")
    if live:
        p50, p99 = live["latency_ms_p50"], live["latency_ms_p99"]
        latency = "no frame" if p50 is None else f"latency {p50:.0f} ms median, {p99:.0f} ms p99"
        lines.append(f"  live:       {latency}; {live['dropped']} frames dropped (behind), {live['delivered']} processed")
    for note in s["notes"]:
        lines.append(f"  note:       {note}")
    if s.get("error"):
        lines.append(f"  stopped:    {s['error']}")
    for kind, why in (s.get("output_errors") or {}).items():
        lines.append(f"  not written: {kind} ({why})")
    lines.append(f"  outputs:    {s['out_dir']} ({', '.join(sorted(s['outputs']))})")
    return "\n".join(lines)
