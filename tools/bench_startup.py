"""What a user pays before any frame: a refused command's answer time, and the compilation of the
compiled kernels (fgslam/core/jit.py) on the first run after an install against the runs after it;
prints one JSON object.

- ``refusals``: wall seconds (best and worst of ``--repeat``) and exit codes of ``fgslam run`` commands
  that stop at a check (a missing data folder, an unknown key, an out-of-range value, an unknown
  preset), beside ``fgslam --help`` (the interpreter and the command line alone).
- ``compilation``: per family, a short run (``--frames``) on a shared clip with an empty kernel cache
  (``NUMBA_CACHE_DIR`` set to a new folder: what the first run after an install does) and then twice
  with that cache filled; the run's CPU seconds (``summary.json`` ``cpu_s``) and the process's wall
  seconds. The first run's extra CPU is the compilation; the later runs only load the kernels.

Each command runs in its own process. The machine may be shared: the load average is recorded.

Usage:
  .venv/bin/python tools/bench_startup.py [--data ../shared/data] [--frames 60] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"
SEVEN_SCENES = "7scenes_redkitchen_0-599"
KITTI = "kitti00_0-199"
# family -> (preset, clip): the recommended patch presets and the other two families' RGB-D presets
RUNS = {"patch_rgbd": ("handheld_rgbd", SEVEN_SCENES), "patch_mono": ("driving_mono", KITTI),
        "pointmap_rgbd": ("pointmap_7scenes_rgbd", SEVEN_SCENES), "dense_rgbd": ("dense_7scenes_rgbd", SEVEN_SCENES)}


def timed(cmd: list[str], env: dict | None = None) -> tuple[float, int]:
    """Wall seconds and exit code of the child."""
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
    return time.perf_counter() - t0, proc.returncode


def refusals(data: Path, repeat: int) -> dict:
    fgslam = [sys.executable, "-m", "fgslam"]
    out_dir = str(Path(tempfile.gettempdir()) / "fgslam_bench_startup_refused")
    cases = {
        "help": fgslam + ["--help"],
        "missing_data": fgslam + ["run", "handheld_rgbd", "--data", "/nonexistent", "--out", out_dir],
        "unknown_key": fgslam + ["run", "handheld_rgbd", "--data", str(data / SEVEN_SCENES), "--out", out_dir,
                                 "-o", "patch.no_such_key=1"],
        "out_of_range": fgslam + ["run", "handheld_rgbd", "--data", str(data / SEVEN_SCENES), "--out", out_dir,
                                  "-o", "patch.graph.optimization_window=-3"],
        "unknown_preset": fgslam + ["run", "no_such_preset", "--data", str(data / SEVEN_SCENES), "--out", out_dir],
    }
    result = {}
    for name, cmd in cases.items():
        walls, codes = [], set()
        for _ in range(repeat):
            wall, rc = timed(cmd)
            walls.append(wall)
            codes.add(rc)
        result[name] = {"wall_s_min": round(min(walls), 3), "wall_s_max": round(max(walls), 3),
                        "exit_codes": sorted(codes)}
    return result


def run_once(preset: str, clip: Path, frames: int, cache: Path, out: Path) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    cmd = [sys.executable, "-m", "fgslam", "-q", "run", preset, "--data", str(clip), "--out", str(out), "--overwrite",
           "--no-progress", "-o", f"dataset.end={frames}", "-o", "output.plot=false"]
    wall, rc = timed(cmd, env)
    summary = out / "summary.json"
    if rc != 0 or not summary.is_file():
        return {"error": f"exit {rc}"}
    s = json.loads(summary.read_text())
    return {"process_wall_s": round(wall, 2), "run_cpu_s": round(s["cpu_s"], 2), "max_frame_s": round(s["max_frame_s"], 3)}


def compilation(data: Path, frames: int) -> dict:
    result = {}
    with tempfile.TemporaryDirectory(prefix="fgslam_bench_startup_") as tmp:
        for name, (preset, clip) in RUNS.items():
            if not (data / clip).is_dir():
                result[name] = {"skipped": f"{data / clip}: not found"}
                continue
            cache = Path(tmp) / f"cache_{name}"
            runs = [run_once(preset, data / clip, frames, cache, Path(tmp) / f"out_{name}") for _ in range(3)]
            entry = {"preset": preset, "clip": clip, "frames": frames, "first_run": runs[0], "later_runs": runs[1:]}
            if all("run_cpu_s" in r for r in runs):
                later = min(r["run_cpu_s"] for r in runs[1:])
                entry["compile_cpu_s"] = round(runs[0]["run_cpu_s"] - later, 2)
            result[name] = entry
    return result


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    p.add_argument("--frames", type=int, default=60, help="frames of each compilation run")
    p.add_argument("--repeat", type=int, default=3, help="runs of each refused command")
    p.add_argument("--skip-compilation", action="store_true", help="only the refused commands")
    args = p.parse_args(argv)
    if args.frames < 2 or args.repeat < 1:
        p.error("--frames must be >= 2 and --repeat >= 1")
    load = [round(v, 2) for v in os.getloadavg()]
    report = {"benchmark": "start-up: refused commands and kernel compilation", "cpus": os.cpu_count(),
              "load_average_start": load, "refusals": refusals(args.data, args.repeat)}
    if not args.skip_compilation:
        report["compilation"] = compilation(args.data, args.frames)
    report["load_average_end"] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
