"""Where tracking stalls: one ``fgslam run`` of a preset with every frame's step timed (wall and CPU
seconds of the tracking thread, safe point included), JSON to stdout.

Reports ATE, ``max_frame_s`` (wall, as ``summary.json``), the largest per-frame CPU time of the
tracking thread (comparable across machine loads, unlike wall time on a shared machine), frames/s,
stage seconds, the loop summary, the load average, and the slowest frames (wall s, CPU s, index,
keyframe, events). Used for issue 24's "global optimisation never stalls tracking" figures.

Usage:
  .venv/bin/python tools/bench_frame_stalls.py dense_7scenes_rgbd --data ../shared/data/7scenes_redkitchen_0-599 \
      --out /tmp/stalls [-o dense.global_ba.every=10 -o loop_closure.mode=proximity]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("preset")
    parser.add_argument("--data", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("-o", dest="overrides", action="append", default=[], help="config override key=value")
    parser.add_argument("--slowest", type=int, default=8, help="slowest frames reported")
    args = parser.parse_args(argv)

    from fgslam.io.run_files import SUMMARY_FILE
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam
    from fgslam.run.system import SlamSystem

    cfg = load_slam_config(args.preset, ["output.plot=false", *args.overrides])
    frames = []
    step = SlamSystem.step

    def timed(self, frame):
        t, c = time.perf_counter(), time.thread_time()
        status = step(self, frame)
        frames.append((time.perf_counter() - t, time.thread_time() - c, int(frame.index), bool(status.is_keyframe),
                       list(status.events)))
        return status

    SlamSystem.step = timed
    load_before = os.getloadavg()
    try:
        run_slam(open_slam_dataset(args.data, cfg), cfg, Path(args.out), progress=False, overwrite=True)
    finally:
        SlamSystem.step = step
    s = json.loads((Path(args.out) / SUMMARY_FILE).read_text())
    slowest = sorted(frames, key=lambda r: -r[0])[: args.slowest]
    report = {
        "preset": args.preset, "overrides": args.overrides, "ate_rmse_m": s["evaluation"]["ate"]["rmse"],
        "max_frame_s": s["max_frame_s"], "max_frame_cpu_s": max(r[1] for r in frames),
        "frame_cpu_s_p99": float(sorted(r[1] for r in frames)[int(0.99 * (len(frames) - 1))]),
        "fps": s["fps"], "keyframes": s["keyframes"], "stage_s": s["stage_s"], "loop": s.get("loop"),
        "cpu_s_process": resource.getrusage(resource.RUSAGE_SELF).ru_utime + resource.getrusage(resource.RUSAGE_SELF).ru_stime,
        "load_average": [list(load_before), list(os.getloadavg())],
        "slowest": [[round(w, 3), round(c, 3), i, k, e] for w, c, i, k, e in slowest],
    }
    print(json.dumps(report))
    return report


if __name__ == "__main__":
    main()
