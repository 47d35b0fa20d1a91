"""Per-stage profile of one ``fgslam run`` (any family: patch, dense, pointmap); JSON to stdout.

Runs what ``fgslam run CONFIG --data PATH`` runs, in this process, under :mod:`cProfile` with a CPU
timer (``time.process_time``: user + system CPU of the process; ``--timer wall`` for wall time), and
attributes every function's own time to one stage:

- ``flow_or_matching``: the measurement sources (dense flow, the patch family's patch selection
  and Lucas-Kanade tracking, the pointmap family's matching, the learned networks);
- ``linearisation``: the blocks' and problems' ``linearize`` (residuals and Jacobians);
- ``elimination``: the Schur complements (``fgslam.factors.schur``) and GTSAM's elimination of the
  reduced systems (``GaussianFactorGraph.optimize`` / ``eliminate*``);
- ``solve``: the rest of the Levenberg-Marquardt loops (trial steps and their costs, back-substitution,
  damping, the backend's and the patch window's set-up of a solve);
- ``bookkeeping``: everything else of the frontends, services and system per frame;
- ``io``: reading the dataset; ``outputs``: evaluation and writing the outputs after the loop;
- ``other``: what no stage function called (the tool itself, imports).

A function that no stage rule names inherits the stage of its callers, split in proportion to the
time each caller spent in it (gprof's assumption: every call of a function costs the same), so the
stages add up to the profiled total. ``python_overhead`` cuts across the stages: the time spent in
Python frames themselves (not in C / C++ kernels: numpy, torch, OpenCV, GTSAM), per stage and in all.

The run's own stage timers (``summary.json`` ``stage_s``, wall time measured by the frontend) are
reported beside the profile, as are the unprofiled-comparable totals (``cpu_s``, ``wall_s`` of the
run loop under the profiler: the profiler adds its own overhead to Python-heavy code, so compare
stages of one tool, not with ``fgslam run``'s figures).

Usage:
  OMP_NUM_THREADS=1 .venv/bin/python tools/profile_family.py dense_7scenes_rgbd \
      --data ../shared/data/7scenes_redkitchen_0-599 --end 200 [-o key=value ...] [--top 20]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import resource
import sys
import tempfile
import time
from pathlib import Path

STAGES = ("flow_or_matching", "linearisation", "elimination", "solve", "bookkeeping", "io", "outputs", "other")

# (stage, path fragment of the function's file or "" for any, function names or None for every function
# of that file); the first rule that matches names the stage. Builtins (C functions) have file "~".
_RULES: tuple[tuple[str, str, frozenset | None], ...] = (
    ("flow_or_matching", "fgslam/frontends/flow.py", frozenset({"revise", "_revise_edge", "add_frame"})),
    ("flow_or_matching", "fgslam/frontends/dense/source.py", frozenset({"revise", "add_frame"})),
    ("flow_or_matching", "fgslam/frontends/patch/lk.py", None),
    ("flow_or_matching", "fgslam/frontends/patch/measurement.py", None),
    ("flow_or_matching", "fgslam/frontends/patch/source.py", None),
    ("flow_or_matching", "fgslam/frontends/pointmap/matching.py", None),
    ("flow_or_matching", "fgslam/frontends/pointmap/source.py", None),
    ("flow_or_matching", "fgslam/frontends/pointmap/descriptors.py", None),
    ("flow_or_matching", "fgslam/frontends/patch/patches.py", frozenset({"select_patches"})),
    ("flow_or_matching", "fgslam/nets/", None),
    ("elimination", "fgslam/factors/schur.py", frozenset({"schur_reduce", "eliminate_structure"})),
    ("linearisation", "fgslam/", frozenset({"linearize", "linearized"})),
    ("solve", "fgslam/backend/solver.py", None),
    ("solve", "fgslam/backend/", frozenset({"optimize_window", "optimize_pose", "optimize_global", "trial",
                                              "accept", "cost"})),
    ("solve", "fgslam/factors/", frozenset({"back_substitute", "refine_structure"})),
    ("solve", "fgslam/frontends/patch/window.py", frozenset({"optimize"})),
    ("io", "fgslam/io/", None),
    ("outputs", "fgslam/run/runner.py", frozenset({"_write_outputs"})),
    ("outputs", "fgslam/run/results.py", frozenset({"outputs_text"})),
    ("outputs", "fgslam/eval/trajectory.py", None),
    ("outputs", "fgslam/export/", None),
    ("bookkeeping", "fgslam/run/runner.py", frozenset({"_loop"})),
    ("bookkeeping", "fgslam/run/system.py", None),
)
# GTSAM's elimination of a linear system (C++ builtins)
_ELIMINATION_BUILTINS = ("optimize", "eliminate")


def stage_of(filename: str, funcname: str) -> str | None:
    """The stage a function is named in (None: it inherits its callers')."""
    path = filename.replace(os.sep, "/")
    if filename == "~":
        if "gtsam" in funcname and ("GaussianFactorGraph" in funcname or "GaussianBayes" in funcname) \
                and any(word in funcname for word in _ELIMINATION_BUILTINS):
            return "elimination"
        return None
    for stage, fragment, names in _RULES:
        if fragment in path and (names is None or funcname in names):
            return stage
    return None


def attribute(stats: pstats.Stats) -> dict[str, dict[str, float]]:
    """Own time of every profiled function split over the stages: ``{stage: {"total": s, "python": s}}``."""
    raw = stats.stats  # (file, line, name) -> (cc, nc, tt, ct, callers {caller: (cc, nc, tt, ct)})
    memo: dict = {}
    visiting: set = set()

    def dist(key) -> dict[str, float]:
        if key in memo:
            return memo[key]
        label = stage_of(key[0], key[2])
        if label is not None:
            memo[key] = {label: 1.0}
            return memo[key]
        if key in visiting:  # recursion: the cycle's share stays with its entry
            return {}
        visiting.add(key)
        callers = raw[key][4]
        weights = {c: float(v[3]) for c, v in callers.items() if c in raw}
        total = sum(weights.values())
        if total <= 0:
            weights = {c: float(v[1]) for c, v in callers.items() if c in raw}
            total = sum(weights.values())
        out: dict[str, float] = {}
        for caller, w in weights.items():
            for stage, share in dist(caller).items():
                out[stage] = out.get(stage, 0.0) + share * w / total
        visiting.discard(key)
        norm = sum(out.values())
        out = {s: v / norm for s, v in out.items()} if norm > 0 else {"other": 1.0}
        memo[key] = out
        return out

    result = {s: {"total": 0.0, "python": 0.0} for s in STAGES}
    for key, (_, _, tt, _, _) in raw.items():
        python = key[0] != "~"
        for stage, share in dist(key).items():
            result[stage]["total"] += tt * share
            if python:
                result[stage]["python"] += tt * share
    return result


def top_functions(stats: pstats.Stats, n: int) -> list[dict]:
    """The ``n`` functions of largest own time, with their stage."""
    rows = sorted(stats.stats.items(), key=lambda kv: -kv[1][2])[:n]
    return [{"function": f"{Path(k[0]).name}:{k[1]}({k[2]})" if k[0] != "~" else k[2], "own_s": round(v[2], 4),
             "cumulative_s": round(v[3], 4), "calls": v[1]} for k, v in rows]


def profile_run(config_name: str, data: str, overrides: list[str], end: int | None = None, timer: str = "cpu",
                out_dir: str | None = None, top: int = 15, pstats_path: str | None = None) -> dict:
    """Profile one run (module docstring); the JSON-ready result."""
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam

    overrides = list(overrides)
    if end is not None:
        overrides.append(f"dataset.end={int(end)}")
    overrides.append("output.plot=false")
    config = load_slam_config(config_name, overrides)
    dataset = open_slam_dataset(data, config)
    clock = time.process_time if timer == "cpu" else time.perf_counter
    profiler = cProfile.Profile(clock)
    with tempfile.TemporaryDirectory(prefix="fgslam_profile_") as tmp:
        out = Path(out_dir) if out_dir else Path(tmp) / "run"
        load_before = os.getloadavg()
        cpu0 = resource.getrusage(resource.RUSAGE_SELF)
        profiler.enable()
        try:
            summary = run_slam(dataset, config, out, progress=False, overwrite=True)
        finally:
            profiler.disable()
        cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    stats = pstats.Stats(profiler)
    if pstats_path:
        stats.dump_stats(pstats_path)
    stages = attribute(stats)
    s = summary.to_dict()
    n = max(int(s["frames_processed"]), 1)
    profiled = sum(v["total"] for v in stages.values())
    ev = s.get("evaluation") or {}
    ms = lambda v: round(1000.0 * v / n, 3)  # noqa: E731 - per-frame milliseconds
    return {
        "config": config_name, "data": str(data), "overrides": overrides, "family": s["frontend"],
        "sensor": s["sensor"], "frames": s["frames_processed"], "keyframes": s["keyframes"],
        "timer": timer,
        "profiled_s": round(profiled, 4),
        "process_cpu_s": round((cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime), 4),
        "run": {"cpu_s": s["cpu_s"], "wall_s": s["wall_s"], "fps": s["fps"], "max_frame_s": s.get("max_frame_s"),
                "ate_m": (ev.get("ate") or {}).get("rmse"), "align": ev.get("align")},
        "stage_ms_per_frame": {k: ms(v["total"]) for k, v in stages.items()},
        "stage_python_ms_per_frame": {k: ms(v["python"]) for k, v in stages.items()},
        "python_overhead_ms_per_frame": ms(sum(v["python"] for v in stages.values())),
        "total_ms_per_frame": ms(profiled),
        "run_stage_wall_ms_per_frame": {k: round(v, 3) for k, v in (s.get("stage_ms_per_frame") or {}).items()},
        "top_functions": top_functions(stats, top),
        "load_average_before": [round(v, 2) for v in load_before],
        "load_average_after": [round(v, 2) for v in os.getloadavg()],
    }


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("config", help="preset name or SlamConfig YAML (as fgslam run)")
    p.add_argument("--data", required=True, help="dataset folder")
    p.add_argument("-o", "--override", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--end", type=int, default=None, help="process frames up to this index (dataset.end)")
    p.add_argument("--timer", choices=("cpu", "wall"), default="cpu", help="profiler clock (default: process CPU)")
    p.add_argument("--out", default=None, help="keep the run's outputs here (default: a temporary folder)")
    p.add_argument("--top", type=int, default=15, help="functions of largest own time listed")
    p.add_argument("--pstats", default=None, metavar="FILE", help="also write the raw profile (pstats format) here")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    result = profile_run(args.config, args.data, args.overrides, args.end, args.timer, args.out, args.top, args.pstats)
    json.dump(result, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
