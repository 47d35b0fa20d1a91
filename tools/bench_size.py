"""Per-stage size by measurement: one preset over a grid of config values (for example the input width
and the keyframe flow threshold) on synthetic renders of a chosen size; JSON to stdout.

Each grid point runs ``fgslam run PRESET`` in a child process on every sequence and reports frames/s,
frames per CPU second, keyframes, tracking failures, the longest frame and ATE; the load average before
and after is recorded. Sequences are ``synth:PRESET:FRAMES[:WxH[:SEED]]`` renders (made once into
``--synth-dir`` and reused) or dataset folders. Used for ``dense_kitti_stereo`` (issue 39: the dense
family at KITTI-size stereo).

Usage:
  .venv/bin/python tools/bench_size.py dense_stereo \\
      --data synth:kitti00-drive:101:1241x376 --data synth:kitti00-drive:161:1241x376:7 \\
      --grid dataset.max_width=640,480,320 --grid dense.graph.motion_filter_flow=12,16,20
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_stability import synth_sequence


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("preset")
    p.add_argument("--data", action="append", required=True, help="a dataset folder or synth:PRESET:FRAMES[:WxH[:SEED]] (repeatable)")
    p.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2,...", help="a config key and its values (repeatable)")
    p.add_argument("-o", "--override", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--synth-dir", type=Path, default=Path(tempfile.gettempdir()) / "fgslam_bench_synth")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds per run")
    args = p.parse_args(argv)
    keys, values = [], []
    for g in args.grid:
        key, _, vals = g.partition("=")
        keys.append(key)
        values.append(vals.split(","))
    sequences = [synth_sequence(d, args.synth_dir, "size") if d.startswith("synth:") else Path(d) for d in args.data]
    rows = []
    for point in itertools.product(*values) if keys else [()]:
        overrides = [f"{k}={v}" for k, v in zip(keys, point)]
        for spec, root in zip(args.data, sequences):
            with tempfile.TemporaryDirectory() as out:
                load = os.getloadavg()
                cmd = [sys.executable, "-m", "fgslam", "-q", "run", args.preset, "--data", str(root), "--out", out,
                       "--no-progress", "-o", "output.plot=false"]
                for o in [*args.overrides, *overrides]:
                    cmd += ["-o", o]
                try:
                    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
                    returncode, stderr = proc.returncode, proc.stderr
                except subprocess.TimeoutExpired:
                    returncode, stderr = None, f"stopped after {args.timeout:.0f} s"
                row = {"data": spec, "overrides": overrides, "returncode": returncode,
                       "load_average": [list(load), list(os.getloadavg())]}
                summary_path = Path(out) / "summary.json"
                if summary_path.exists():
                    s = json.loads(summary_path.read_text())
                    ev = s.get("evaluation") or {}
                    row.update(fps=s["fps"], frames_per_cpu_s=s["frames_processed"] / s["cpu_s"] if s["cpu_s"] > 0 else None,
                               keyframes=s["keyframes"], tracking_failures=s["failures"]["tracking"],
                               max_frame_s=s["max_frame_s"], ate_rmse_m=ev.get("ate_rmse_m"))
                else:
                    row["error"] = stderr.strip().splitlines()[-1:] or ["no summary"]
                rows.append(row)
                print(json.dumps(row), file=sys.stderr)
    report = {"preset": args.preset, "data": args.data, "grid": args.grid, "overrides": args.overrides, "runs": rows}
    print(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
