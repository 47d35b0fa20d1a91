"""fgslam against pycolmap's SfM (``fgslam compare-colmap``) on the issue-15 sequences; prints one
JSON object (a report per sequence, with the load average around each).

Sequences (``--list``): KITTI 00 frames 0-199 and 7-Scenes kitchen 0-599 from ``../shared/data``,
and the synthetic ``room-loop`` (401 frames 640x480, rendered once into ``--work``). ``--frames N``
takes the first N frames of each. Each comparison runs in its own process (``fgslam
compare-colmap --json``), as a user would; run it under ``nice`` on a shared machine and compare CPU
seconds (``speed_ratio_cpu``), which depend less on the load than wall times.

Usage:
  nice -n 10 .venv/bin/python tools/bench_colmap.py --work /tmp/bench_colmap [--sequences kitti00,room] \
      [--frames 150] [--features 8192]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
SEQUENCES = {
    "kitti00": SHARED / "kitti00_0-199",
    "kitchen": SHARED / "7scenes_redkitchen_0-599",
    "room": None,  # rendered into --work
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work", required=True, help="folder for the renders and the comparison outputs")
    parser.add_argument("--sequences", default=",".join(SEQUENCES), help="comma-separated names (see --list)")
    parser.add_argument("--frames", type=int, default=None, help="first N frames of each sequence")
    parser.add_argument("--features", type=int, default=None, help="COLMAP SIFT features per image (default 8192)")
    parser.add_argument("--list", action="store_true", help="list the sequences and exit")
    args = parser.parse_args()
    if args.list:
        print(json.dumps({k: str(v) if v else "synthetic room-loop (rendered)" for k, v in SEQUENCES.items()}))
        return 0
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    fgslam = [sys.executable, "-m", "fgslam"]
    results = {}
    for name in args.sequences.split(","):
        if name not in SEQUENCES:
            parser.error(f"unknown sequence {name!r} (known: {', '.join(SEQUENCES)})")
        data = SEQUENCES[name]
        if data is None:
            data = work / "room-loop"
            if not (data / "synth_config.yaml").is_file():
                subprocess.run([*fgslam, "-q", "synth", "--preset", "room-loop", "--out", str(data)], check=True)
        elif not data.is_dir():
            results[name] = {"skipped": f"{data} is absent"}
            continue
        cmd = [*fgslam, "-q", "compare-colmap", "--data", str(data), "--out", str(work / f"cmp_{name}"),
               "--overwrite", "--no-progress", "--json"]
        if args.frames:
            cmd += ["--frames", str(args.frames)]
        if args.features:
            cmd += ["--features", str(args.features)]
        load_before = os.getloadavg()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        load_after = os.getloadavg()
        if proc.returncode != 0:
            results[name] = {"error": proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]}
            continue
        report = json.loads(proc.stdout.strip().splitlines()[-1])
        report["load_average_before_after"] = [list(load_before), list(load_after)]
        results[name] = report
    print(json.dumps(results, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
