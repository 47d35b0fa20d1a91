"""Benchmark full SLAM runs (``fgslam run``) on the shared real sequences and the synthetic room loop;
prints one JSON object.

Cases (``--list``): KITTI 00 frames 0-199 monocular; 7-Scenes kitchen 0-599 monocular and RGB-D,
each also with loop closure ``both``; EuRoC V1_01 micro clip (static camera) monocular and stereo,
where the estimated motion extent is the figure of merit; synthetic ``room-loop`` monocular, stereo
and RGB-D; the synthetic ``street-loop`` drive (1,100 frames) with loop closure (``street_loop``,
not in the default set: it renders and runs for several minutes); the pointmap family's cases
(``pm_*``, issue 13 targets; not in the default set: ``--cases pm_7scenes_rgbd,...``). Each case reports ATE
(m and % of the ground-truth path, with the alignment used), frames/s overall and of the frontend,
ms per frame of every frontend stage, the longest frame (``max_frame_s``), keyframes, failures, the estimate's motion extent, peak RSS,
and whether the issue-4 target is met. Every case runs in its own process (peak RSS per case).

The machine may be shared: the load average before and after each case is recorded.

Side by side (``--baseline DIR``): every case also runs on the fgslam source tree in DIR (for example
``git worktree add /tmp/base main``), alternating new and baseline run by run, and the report gives
both results and their ratios (ATE, frames/s, CPU seconds): before and after in one run, under the
same load.

Usage:
  OMP_NUM_THREADS=1 .venv/bin/python tools/bench_run.py [--cases kitti00_mono,room_mono] \
      [--synth-size 640x480] [--synth-frames 401] [--keep-outputs DIR] [--baseline DIR] [-o key=value ...]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"
SYNTH = "synthetic room-loop"

STREET = "synthetic street-loop"
STREET_FRAMES = 1100  # one loop (1,001 frames, 606 m) and the return past the start


class Case(NamedTuple):
    """A benchmark case: preset, data folder under --data (or SYNTH / STREET), the issue target as
    (metric, bound, text), and config overrides of the case (before the command line's)."""

    preset: str
    data: str
    target: tuple[str, float, str]
    overrides: tuple[str, ...] = ()


LOOP_BOTH = ("loop_closure.mode=both",)
CASES: dict[str, Case] = {
    "kitti00_mono": Case("patch_kitti_mono", "kitti00_0-199",
                         ("ate_percent_of_path", 1.0, "Sim(3) ATE <= 1% of the 145 m path (aim 0.5%), >= 10 frames/s")),
    "7scenes_mono": Case("patch_7scenes_mono", "7scenes_redkitchen_0-599",
                         ("ate_rmse_m", 0.05, "monocular Sim(3) ATE <= 0.05 m")),
    "7scenes_rgbd": Case("patch_7scenes_rgbd", "7scenes_redkitchen_0-599",
                         ("ate_rmse_m", 0.03, "RGB-D SE(3) ATE <= 0.03 m")),
    "7scenes_mono_lc": Case("patch_7scenes_mono", "7scenes_redkitchen_0-599",
                            ("ate_rmse_m", 0.05, "monocular Sim(3) ATE <= 0.05 m, loop closure both"), LOOP_BOTH),
    "7scenes_rgbd_lc": Case("patch_7scenes_rgbd", "7scenes_redkitchen_0-599",
                            ("ate_rmse_m", 0.03, "RGB-D SE(3) ATE <= 0.03 m, loop closure both"), LOOP_BOTH),
    "euroc_mono": Case("patch_euroc_mono", "euroc_v101_micro",
                       ("frames_with_pose", 0.0, "static camera: waits for parallax, never initialises a spurious scale")),
    "euroc_stereo": Case("patch_euroc_stereo", "euroc_v101_micro",
                         ("max_distance_from_start", 0.01, "static camera: <= 0.01 m of estimated motion; >= 20 frames/s")),
    "room_mono": Case("patch_mono", SYNTH, ("ate_percent_of_path", 1.0, "Sim(3) ATE <= 1% of path")),
    "room_stereo": Case("patch_stereo", SYNTH, ("ate_percent_of_path", 0.5, "SE(3) ATE <= 0.5% of path")),
    "room_rgbd": Case("patch_rgbd", SYNTH, ("ate_percent_of_path", 0.5, "SE(3) ATE <= 0.5% of path")),
    "street_loop": Case("patch_street_loop", STREET,
                        ("ate_rmse_m", 0.95, "loop closure both: <= 30% of the 3.18 m ATE without loop closure")),
    # dense family (issue 12)
    "dense_7scenes_rgbd": Case("dense_7scenes_rgbd", "7scenes_redkitchen_0-599",
                               ("ate_rmse_m", 0.04, "dense RGB-D SE(3) ATE <= 0.04 m")),
    # pointmap family (issue 13): frames matched at 320x240 (the presets' image_width)
    "pm_7scenes_rgbd": Case("pointmap_7scenes_rgbd", "7scenes_redkitchen_0-599",
                            ("ate_rmse_m", 0.04, "pointmap RGB-D SE(3) ATE <= 0.04 m, >= 5 frames/s")),
    "pm_7scenes_mono": Case("pointmap_7scenes_mono", "7scenes_redkitchen_0-599",
                            ("ate_rmse_m", 0.06, "pointmap monocular two-view Sim(3) ATE <= 0.06 m")),
    "pm_euroc_stereo": Case("pointmap_euroc_stereo", "euroc_v101_micro",
                            ("max_distance_from_start", 0.01, "pointmap stereo, static camera: <= 0.01 m of motion")),
    "pm_room_rgbd": Case("pointmap_rgbd", SYNTH, ("ate_percent_of_path", 0.5, "pointmap RGB-D SE(3) ATE <= 0.5% of path")),
    "pm_room_mono": Case("pointmap_mono", SYNTH, ("ate_percent_of_path", 1.5, "pointmap two-view Sim(3) ATE <= 1.5% of path")),
}
POINTMAP_CASES = [name for name in CASES if name.startswith("pm_")]
DEFAULT_CASES = [name for name in CASES if name not in ("street_loop", "dense_7scenes_rgbd") and name not in POINTMAP_CASES]
# Speed targets of issue 4 (frames/s on the 2-core reference machine), by case.
FPS_TARGETS = {"kitti00_mono": 10.0, "euroc_stereo": 20.0, "pm_7scenes_rgbd": 5.0}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", default=",".join(DEFAULT_CASES), help="comma-separated subset of: " + ", ".join(CASES))
    p.add_argument("--list", action="store_true", help="list the cases and exit")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    p.add_argument("--synth-size", default="640x480", help="WxH of the synthetic room-loop renders")
    p.add_argument("--synth-frames", type=int, default=401, help="frames of the synthetic sequence (401: one loop)")
    p.add_argument("--synth-rate", type=float, default=20.0, help="frame rate (Hz) of the synthetic sequence")
    p.add_argument("--synth-dir", type=Path, default=Path(tempfile.gettempdir()) / "fgslam_bench_synth",
                   help="cache folder of the synthetic renders (reused when the scene is the same)")
    p.add_argument("--keep-outputs", type=Path, default=None, help="write each run's outputs to DIR/<case>/new (and DIR/<case>/baseline)")
    p.add_argument("--baseline", type=Path, default=None,
                   help="fgslam source tree to run side by side (its fgslam/ package and presets), e.g. a git worktree of main")
    p.add_argument("-o", "--override", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="SlamConfig override applied to every case (repeatable)")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)  # internal: run one case in this process
    # internal: sequences the parent rendered (children, the baseline's included, reuse them as they are)
    p.add_argument("--rendered", action="append", default=[], help=argparse.SUPPRESS)
    return p.parse_args(argv)


def synth_root(args: argparse.Namespace) -> Path:
    """Render (or reuse) the synthetic room-loop sequence; returns its root."""
    from fgslam.run.demo import DemoSceneConfig, render_scene

    w, h = (int(v) for v in args.synth_size.lower().split("x"))
    scene = DemoSceneConfig(preset="room-loop", frames=args.synth_frames, rate_hz=args.synth_rate, width=w, height=h)
    root = args.synth_dir / f"room-loop_{w}x{h}_{args.synth_frames}_{args.synth_rate:g}hz"
    render_scene(scene, root)
    return root


def street_root(args: argparse.Namespace) -> Path:
    """Render (or reuse) the synthetic street-loop drive with the preset's own camera; returns its root."""
    from fgslam.run.demo import DemoSceneConfig, render_scene
    from fgslam.io.synth.scenarios import default_config

    camera = default_config("street-loop").camera
    scene = DemoSceneConfig(preset="street-loop", frames=STREET_FRAMES, rate_hz=camera.rate_hz,
                            width=camera.width, height=camera.height)
    root = args.synth_dir / f"street-loop_{camera.width}x{camera.height}_{STREET_FRAMES}"
    render_scene(scene, root)
    return root


def case_root(case: Case, args: argparse.Namespace) -> Path:
    rendered = dict(item.split("=", 1) for item in args.rendered)
    if case.data in rendered:
        return Path(rendered[case.data])
    if case.data == SYNTH:
        return synth_root(args)
    if case.data == STREET:
        return street_root(args)
    return args.data / case.data


def run_case(name: str, args: argparse.Namespace) -> dict:
    """Run one case in this process and return its result (JSON types)."""
    import fgslam

    # a --baseline tree that predates the run package (fgslam/run/) has its runner in fgslam.slam; decided by the
    # tree, not by trying the import: an editable install finds the new tree's fgslam.run from any tree
    if (Path(fgslam.__file__).parent / "run" / "runner.py").is_file():
        from fgslam.run.config import load_slam_config
        from fgslam.run.prepare import open_slam_dataset
        from fgslam.run.runner import run_slam
    else:  # only a baseline tree
        from fgslam.slam import load_slam_config, open_slam_dataset, run_slam

    preset, data, (metric, bound, text), case_overrides = CASES[name]
    config = load_slam_config(preset, list(case_overrides) + args.overrides)
    root = case_root(CASES[name], args)
    dataset = open_slam_dataset(root, config)
    code = Path(fgslam.__file__).resolve().parents[1]  # the source tree that runs (this one or --baseline's)
    side = "new" if code == REPO.resolve() else "baseline"
    out = args.keep_outputs / name / side if args.keep_outputs else Path(tempfile.mkdtemp(prefix=f"bench_{name}_"))
    if out.is_dir():  # --keep-outputs reruns replace (a baseline tree may predate run_slam's overwrite)
        shutil.rmtree(out)
    load_before = os.getloadavg()
    error = None
    started_ns = time.time_ns()
    try:
        s = run_slam(dataset, config, out, progress=False).to_dict()
    except Exception as exc:  # noqa: BLE001 - the benchmark reports failures instead of stopping
        error = f"{type(exc).__name__}: {exc}"
        summary_path = out / "summary.json"
        if not summary_path.is_file() or summary_path.stat().st_mtime_ns < started_ns:
            return {"case": name, "preset": preset, "data": str(root), "error": error}
        s = json.loads(summary_path.read_text())
    ev = s["evaluation"] or {}
    result = {
        "case": name,
        "code": str(code),  # the source tree that ran
        "preset": preset,
        "overrides": list(case_overrides) + args.overrides,
        "data": str(root),
        "resolution": s["dataset"]["resolution"],
        "frames": s["frames_processed"],
        "frames_with_pose": s["frames_with_pose"],
        "keyframes": s["keyframes"],
        "fps": s["fps"],
        "fps_frontend": s["fps_frontend"],
        "max_frame_s": s.get("max_frame_s"),  # longest frame of the tracking loop (None: a tree without it)
        "stage_ms_per_frame": s["stage_ms_per_frame"],
        "read_ms_per_frame": 1000.0 * s["read_s"] / max(s["frames_processed"], 1),
        "wall_s": s["wall_s"],
        "cpu_s": s["cpu_s"],  # user + system CPU of the run: less sensitive to a shared machine's load
        "frames_per_cpu_s": s["frames_processed"] / s["cpu_s"] if s["cpu_s"] > 0 else None,
        "failures": s["failures"],
        "align": ev.get("align"),
        "scale": ev.get("scale"),
        "ate_rmse_m": ev.get("ate_rmse_m"),
        "ate_percent_of_path": ev.get("ate_percent_of_path"),
        "gt_path_length_m": ev.get("gt_path_length_m"),
        "coverage": ev.get("coverage"),
        "motion": s["motion"],  # estimate units (metres for stereo/RGB-D)
        "max_distance_from_start": s["motion"]["max_distance_from_start"],
        "peak_rss_mb": s["peak_rss_mb"],
        "load_before": [round(v, 2) for v in load_before],
        "load_after": [round(v, 2) for v in os.getloadavg()],
        "error": error or s["error"],
        "outputs": str(out) if args.keep_outputs else None,
    }
    loop = s.get("loop")
    if loop:
        result["loop"] = loop
    value = result.get(metric)
    target = {"metric": metric, "bound": bound, "text": text, "value": value,
              "met": value is not None and value <= bound and result["error"] is None}
    if name in FPS_TARGETS:
        target["fps_bound"] = FPS_TARGETS[name]
        target["fps_met"] = result["fps"] >= FPS_TARGETS[name]
    result["target"] = target
    return result


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.list:
        for name, case in CASES.items():
            print(f"{name:16s} {case.preset:20s} {case.data:28s} {' '.join(case.overrides):24s} {case.target[2]}")
        return 0
    if args.child is not None:
        print(json.dumps(run_case(args.child, args)))
        return 0
    names = [n.strip() for n in args.cases.split(",") if n.strip()]
    unknown = [n for n in names if n not in CASES]
    if unknown:
        print(f"unknown case(s): {', '.join(unknown)} (known: {', '.join(CASES)})", file=sys.stderr)
        return 2
    base = [a for a in (argv if argv is not None else sys.argv[1:])]
    # render once, before any timing; children (the baseline's too) read these folders as they are
    if any(CASES[n].data == SYNTH for n in names):
        base += ["--rendered", f"{SYNTH}={synth_root(args)}"]
    if any(CASES[n].data == STREET for n in names):
        base += ["--rendered", f"{STREET}={street_root(args)}"]
    if args.baseline is not None and not (args.baseline / "fgslam" / "__init__.py").is_file():
        print(f"--baseline {args.baseline}: not an fgslam source tree (no fgslam/__init__.py)", file=sys.stderr)
        return 2
    results = {}
    t0 = time.perf_counter()
    for name in names:
        new = _child(name, base, None)
        if args.baseline is None:
            results[name] = new
            continue
        results[name] = {"new": new, "baseline": _child(name, base, args.baseline.resolve())}
        results[name]["ratio"] = _ratios(results[name]["new"], results[name]["baseline"])
    report = {
        "benchmark": "fgslam run (patch frontend)",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "omp_num_threads": os.environ.get("OMP_NUM_THREADS")},
        "overrides": args.overrides,
        "baseline": None if args.baseline is None else str(args.baseline.resolve()),
        "total_s": time.perf_counter() - t0,
        "cases": results,
    }
    print(json.dumps(report, indent=2))
    return 0


def _child(name: str, argv: list[str], code: Path | None) -> dict:
    """Run case ``name`` in a child process, on the fgslam source tree ``code`` (None: this one)."""
    cmd = [sys.executable, str(Path(__file__).resolve())] + argv + ["--child", name]
    env = dict(os.environ)
    if code is not None:  # the baseline's package and presets come first on the path
        env["PYTHONPATH"] = os.pathsep.join([str(code)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO if code is None else code, env=env)
    lines = proc.stdout.strip().splitlines()
    try:
        return json.loads(lines[-1])
    except (IndexError, json.JSONDecodeError):
        return {"case": name, "error": f"exit {proc.returncode}: {proc.stderr.strip()[-2000:]}"}


def _ratios(new: dict, baseline: dict) -> dict:
    """new / baseline of the figures that matter (None where either is missing or zero)."""
    out = {}
    for key in ("ate_rmse_m", "max_distance_from_start", "fps", "fps_frontend", "cpu_s", "max_frame_s"):
        a, b = new.get(key), baseline.get(key)
        out[key] = a / b if isinstance(a, (int, float)) and isinstance(b, (int, float)) and b else None
    return out


if __name__ == "__main__":
    sys.exit(main())
