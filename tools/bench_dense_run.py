"""Dense (DROID-SLAM family) and patch frontends side by side in one benchmark run; JSON to stdout.

Every case runs ``fgslam run`` twice in child processes (dense preset, then the patch preset of the
same class of data), alternating, and reports per frontend: ATE (m and % of the ground-truth path,
with the alignment used), frames/s (wall and per CPU second), CPU seconds, ms per frame of every
frontend stage, keyframes, tracking failures, the estimate's motion extent (EuRoC static clip), and
the dense/patch ratios (ATE, CPU seconds). The load average before and after each run is recorded
(the machine is shared: CPU seconds are the comparable speed figure).

Cases: synthetic ``room-loop`` (mono, stereo, RGB-D) and ``low-texture`` (mono, RGB-D) rendered at
``--synth-size`` (320x240 by default, the issue's speed target size) and ``--synth-rate``; KITTI 00
frames 0-199 mono, 7-Scenes kitchen 0-599 mono and RGB-D (dense presets at half resolution), EuRoC
V1_01 micro clip stereo (static camera).

Usage:
  OMP_NUM_THREADS=1 .venv/bin/python tools/bench_dense_run.py [--cases room_mono,kitti00_mono] \
      [--synth-size 320x240] [--synth-frames 401] [--frontends dense,patch] [-o key=value ...]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import NamedTuple

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"


class Case(NamedTuple):
    dense: str  # dense preset
    patch: str  # patch preset
    data: str  # folder under --data, or "synth:<preset>"
    target: str  # the issue-12 target (text)


CASES: dict[str, Case] = {
    "room_mono": Case("dense_mono", "patch_mono", "synth:room-loop", "Sim(3) ATE <= 0.5 % of path; >= 10 frames/s at 320x240"),
    "room_stereo": Case("dense_stereo", "patch_stereo", "synth:room-loop", "SE(3) ATE <= 0.3 % of path"),
    "room_rgbd": Case("dense_rgbd", "patch_rgbd", "synth:room-loop", "SE(3) ATE <= 0.3 % of path"),
    "lowtex_mono": Case("dense_mono", "patch_mono", "synth:low-texture", "no failure, Sim(3) ATE <= 1 % of path"),
    "lowtex_rgbd": Case("dense_rgbd", "patch_rgbd", "synth:low-texture", "no failure, SE(3) ATE <= 0.5 % of path"),
    "kitti00_mono": Case("dense_kitti_mono", "patch_kitti_mono", "kitti00_0-199", "Sim(3) ATE <= 1 % of path; >= 5 frames/s"),
    "7scenes_mono": Case("dense_7scenes_mono", "patch_7scenes_mono", "7scenes_redkitchen_0-599", "Sim(3) ATE <= 0.04 m; >= 15 frames/s"),
    "7scenes_rgbd": Case("dense_7scenes_rgbd", "patch_7scenes_rgbd", "7scenes_redkitchen_0-599", "SE(3) ATE <= 0.04 m; >= 15 frames/s"),
    "euroc_stereo": Case("dense_euroc_stereo", "patch_euroc_stereo", "euroc_v101_micro", "static: <= 0.01 m of estimated motion"),
}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", default=",".join(CASES), help="comma-separated subset of: " + ", ".join(CASES))
    p.add_argument("--frontends", default="dense,patch", help="dense, patch or both (dense,patch)")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    p.add_argument("--synth-size", default="320x240", help="WxH of the synthetic renders")
    p.add_argument("--synth-frames", type=int, default=401, help="frames of the synthetic sequences (401: one loop at 20 Hz)")
    p.add_argument("--synth-rate", type=float, default=20.0, help="frame rate (Hz) of the synthetic sequences")
    p.add_argument("--synth-dir", type=Path, default=Path(tempfile.gettempdir()) / "fgslam_bench_synth")
    p.add_argument("--out", type=Path, default=None, help="keep each run's outputs in DIR/<case>_<frontend>")
    p.add_argument("-o", "--override", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override for the dense runs (repeatable)")
    return p.parse_args(argv)


def synth_root(preset: str, args: argparse.Namespace) -> Path:
    from fgslam.run.demo import DemoSceneConfig, render_scene

    w, h = (int(v) for v in args.synth_size.lower().split("x"))
    scene = DemoSceneConfig(preset=preset, frames=args.synth_frames, rate_hz=args.synth_rate, width=w, height=h)
    root = args.synth_dir / f"{preset}_{w}x{h}_{args.synth_frames}_{args.synth_rate:g}hz"
    render_scene(scene, root)
    return root


def load() -> float:
    return os.getloadavg()[0]


def run_one(preset: str, root: Path, out: Path, overrides: list[str]) -> dict:
    cmd = [sys.executable, "-m", "fgslam", "-q", "run", preset, "--data", str(root), "--out", str(out),
           "-o", "output.plot=false"]
    for o in overrides:
        cmd += ["-o", o]
    before = load()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO,
                          env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")})
    after = load()
    summary_path = out / "summary.json"
    if not summary_path.is_file():
        return {"preset": preset, "error": proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]}
    s = json.loads(summary_path.read_text())
    ev = s.get("evaluation") or {}
    ate = (ev.get("ate") or {}).get("rmse")
    path = ev.get("gt_path_length_m") or ev.get("path_length_m")
    n = max(int(s["frames_processed"]), 1)
    return {
        "preset": preset, "frames": s["frames_processed"], "frames_with_pose": s["frames_with_pose"],
        "keyframes": s["keyframes"], "failures": s["failures"]["tracking"],
        "ate_m": ate, "align": ev.get("align"), "path_m": path,
        "ate_percent_of_path": None if ate is None or not path else 100.0 * ate / path,
        "fps": s["fps"], "cpu_s": s["cpu_s"], "frames_per_cpu_s": n / s["cpu_s"] if s["cpu_s"] else None,
        "stage_ms_per_frame": {k: 1000.0 * v / n for k, v in (s.get("stage_s") or {}).items()},
        "max_frame_s": s.get("max_frame_s"),
        "max_distance_from_start": (s.get("motion") or {}).get("max_distance_from_start"),
        "load_before": before, "load_after": after, "error": s.get("error"),
    }


def main(argv=None) -> int:
    args = parse_args(argv)
    names = [c for c in args.cases.split(",") if c]
    unknown = [c for c in names if c not in CASES]
    if unknown:
        print(f"unknown cases: {unknown}; known: {list(CASES)}", file=sys.stderr)
        return 2
    frontends = [f for f in args.frontends.split(",") if f]
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        base = args.out or Path(tmp)
        for name in names:
            case = CASES[name]
            root = synth_root(case.data[6:], args) if case.data.startswith("synth:") else args.data / case.data
            res: dict = {"target": case.target, "data": str(root)}
            for fe in frontends:
                preset = case.dense if fe == "dense" else case.patch
                res[fe] = run_one(preset, root, base / f"{name}_{fe}", args.overrides if fe == "dense" else [])
            d, p = res.get("dense", {}), res.get("patch", {})
            if d.get("ate_m") and p.get("ate_m"):
                res["ratio_dense_over_patch"] = {"ate": d["ate_m"] / p["ate_m"], "cpu_s": d["cpu_s"] / p["cpu_s"]}
            results[name] = res
            print(json.dumps({name: res}), file=sys.stderr, flush=True)  # progress
    print(json.dumps({"benchmark": "dense vs patch (fgslam run)", "synth_size": args.synth_size,
                      "synth_frames": args.synth_frames, "synth_rate_hz": args.synth_rate,
                      "dense_overrides": args.overrides, "cases": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
