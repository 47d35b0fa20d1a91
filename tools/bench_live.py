"""Live replay: a recorded clip fed to ``fgslam run --live`` at its own rate (``--speed`` times it), beside
the offline run of the same preset on the same frames; prints one JSON object.

For each speed: the latency of the results (a frame's arrival to its pose: median, 99th percentile,
largest, milliseconds), the frames dropped because the system was behind, the frames processed, the CPU
seconds, and the accuracy: ATE against the ground truth (the sensor's alignment), beside the offline
run's, and the ATE of the live trajectory against the offline one (how far dropping frames moved it).

Each run is its own process (``fgslam run``); the machine may be shared: the load average is recorded.

Usage:
  .venv/bin/python tools/bench_live.py [--data ../shared/data/7scenes_redkitchen_0-599] [--preset handheld_rgbd]
      [--end 600] [--speed 1 --speed 2] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Optional

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "7scenes_redkitchen_0-599"


def run(preset: str, data: Path, out: Path, end: Optional[int], live_speed: Optional[float]) -> dict:
    """One ``fgslam run`` in its own process; its summary.json (with the exit code)."""
    cmd = [sys.executable, "-m", "fgslam", "run", preset, "--data", str(data), "--out", str(out), "--overwrite",
           "--no-progress", "--json"]
    if end is not None:
        cmd += ["-o", f"dataset.end={end}"]
    if live_speed is not None:
        cmd += ["--live", "--live-speed", str(live_speed)]
    summary_path = out / "summary.json"
    summary_path.unlink(missing_ok=True)  # a run that fails before writing one must not report a previous one
    load = os.getloadavg()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    if not summary_path.is_file():
        return {"exit_code": proc.returncode, "error": proc.stderr.strip().splitlines()[-1:] or None}
    s = json.loads(summary_path.read_text())
    ev = s.get("evaluation") or {}
    return {"exit_code": proc.returncode, "frames_processed": s["frames_processed"],
            "frames_with_pose": s["frames_with_pose"], "cpu_s": round(s["cpu_s"], 2), "wall_s": round(s["wall_s"], 2),
            "ate_rmse_m": (ev.get("ate") or {}).get("rmse"), "live": s.get("live"),
            "load_before": [round(v, 2) for v in load], "load_after": [round(v, 2) for v in os.getloadavg()]}


def ate_between(reference: Path, estimate: Path, align: str) -> Optional[float]:
    """ATE RMSE of ``estimate`` against ``reference`` (TUM files), ``align`` (sim3 / se3); None if either is missing."""
    from fgslam.eval.trajectory import EvalConfig, evaluate
    from fgslam.io.trajectory import read_trajectory

    if not (reference.is_file() and estimate.is_file()):
        return None
    result = evaluate(read_trajectory(reference, "tum"), read_trajectory(estimate, "tum"), EvalConfig(align=align))
    return float(result.ate.rmse)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the clip (any layout fgslam run reads)")
    parser.add_argument("--preset", default="handheld_rgbd")
    parser.add_argument("--end", type=int, default=None, help="frames of the clip (default: all)")
    parser.add_argument("--speed", type=float, action="append", default=None,
                        help="replay speed, times the clip's rate (repeatable; default 1)")
    parser.add_argument("--out", type=Path, default=None, help="keep the runs' outputs here (default: a temporary folder)")
    args = parser.parse_args()
    from fgslam.run.config import load_slam_config

    align = load_slam_config(args.preset).alignment()
    speeds = args.speed or [1.0]
    with tempfile.TemporaryDirectory(prefix="fgslam_bench_live_") as tmp:
        root = args.out or Path(tmp)
        offline_dir = root / "offline"
        report = {"preset": args.preset, "data": str(args.data), "end": args.end, "cpus": os.cpu_count(),
                  "offline": run(args.preset, args.data, offline_dir, args.end, None), "live": {}}
        for speed in speeds:
            live_dir = root / f"live_x{speed:g}"
            entry = run(args.preset, args.data, live_dir, args.end, speed)
            entry["ate_vs_offline_m"] = ate_between(offline_dir / "trajectory_tum.txt", live_dir / "trajectory_tum.txt",
                                                    align)
            report["live"][f"x{speed:g}"] = entry
    print(json.dumps(report, indent=2))
    failed = [r for r in [report["offline"], *report["live"].values()] if r["exit_code"] != 0]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
