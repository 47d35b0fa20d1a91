"""Benchmark ``fgslam pgo`` against gtsam's own reader + LM on the same g2o files; prints JSON.

For each file:
* fgslam: ``fgslam.run.pgo.run_pgo`` end to end (our parser, graph build, chordal init, LM).
* gtsam: ``gtsam.readG2o`` + the same gauge prior + the same initialisation (InitializePose3 in 3-D;
  LAGO in 2-D, on the marginal-variance copy LAGO requires) + ``LevenbergMarquardtOptimizer`` with the
  same parameters.
Runs alternate between the two; times are the best of ``--repeat`` runs (wall and process CPU time,
the machine is shared); ratios are fgslam / gtsam.

Usage: OMP_NUM_THREADS=1 .venv/bin/python tools/bench_pgo.py [--data ../shared/data/g2o] [--repeat 3]
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform
import time
from pathlib import Path

import gtsam
import numpy as np

from fgslam.run.pgo import PGOConfig, diagonalised_pose2_graph, lm_params, run_pgo

FILES = ["sphere2500", "torus3D", "parking-garage", "kitti_00"]
DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "g2o"


def bench_fgslam(path: Path, config: PGOConfig) -> dict:
    c0, t0 = time.process_time(), time.perf_counter()
    result = run_pgo(path, config)
    total = time.perf_counter() - t0
    return {
        "time_s": total,
        "cpu_s": time.process_time() - c0,
        "lm_time_s": result.optimize_time_s,
        "iterations": result.iterations,
        "initial_cost": result.initial_cost,
        "final_cost": result.final_cost,
        "converged": result.converged,
    }


def is_3d(path: Path) -> bool:
    """Whether the first vertex/edge line of a g2o file is SE3 (gtsam.readG2o needs to be told)."""
    with path.open() as f:
        for line in f:
            if line.strip() and not line.startswith("#"):
                return "SE3" in line.split()[0]
    return False


def bench_gtsam(path: Path, config: PGOConfig, is3d: bool) -> dict:
    c0, t0 = time.process_time(), time.perf_counter()
    graph, initial = gtsam.readG2o(str(path), is3d)
    prior_noise = gtsam.noiseModel.Diagonal.Variances(np.full(6 if is3d else 3, config.prior_variance))
    if is3d:
        anchor = initial.atPose3(0) if initial.exists(0) else gtsam.Pose3()
        graph.add(gtsam.PriorFactorPose3(0, anchor, prior_noise))
        start = gtsam.InitializePose3.initialize(graph)
    else:
        anchor = initial.atPose2(0) if initial.exists(0) else gtsam.Pose2()
        graph.add(gtsam.PriorFactorPose2(0, anchor, prior_noise))
        start = gtsam.lago.initialize(diagonalised_pose2_graph(graph))
    initial_cost = graph.error(start)
    t1 = time.perf_counter()
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, start, lm_params(config))
    values = optimizer.optimize()
    t2 = time.perf_counter()
    return {
        "time_s": t2 - t0,
        "cpu_s": time.process_time() - c0,
        "lm_time_s": t2 - t1,
        "iterations": optimizer.iterations(),
        "initial_cost": initial_cost,
        "final_cost": graph.error(values),
    }


def best(runs: list[dict]) -> dict:
    """The fastest run, with the smallest LM and CPU times over all runs (the machine is shared)."""
    fastest = dict(min(runs, key=lambda r: r["time_s"]))
    for key in ("lm_time_s", "cpu_s"):
        fastest[key] = min(r[key] for r in runs)
    return fastest


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder with the g2o files")
    parser.add_argument("--repeat", type=int, default=3, help="runs per file and method (best time kept)")
    parser.add_argument("--files", nargs="*", default=FILES, help="file stems to run")
    args = parser.parse_args()
    config = PGOConfig()
    rows = []
    for name in args.files:
        path = args.data / f"{name}.g2o"
        three_d = is_3d(path)
        ours_runs, theirs_runs = [], []
        for _ in range(args.repeat):  # interleaved, so that load from other processes hits both alike
            ours_runs.append(bench_fgslam(path, config))
            theirs_runs.append(bench_gtsam(path, config, three_d))
        ours, theirs = best(ours_runs), best(theirs_runs)
        rows.append(
            {
                "file": name,
                "fgslam": ours,
                "gtsam": theirs,
                "time_ratio": ours["time_s"] / theirs["time_s"],
                "cpu_ratio": ours["cpu_s"] / theirs["cpu_s"],
                "lm_time_ratio": ours["lm_time_s"] / theirs["lm_time_s"],
                "final_cost_rel_diff": abs(ours["final_cost"] - theirs["final_cost"]) / abs(theirs["final_cost"]),
            }
        )
    report = {
        "benchmark": "pgo",
        "gtsam_version": importlib.metadata.version("gtsam"),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "machine": platform.machine(),
        "repeat": args.repeat,
        "config": "PGOConfig defaults (chordal init, gtsam LM defaults)",
        "results": rows,
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
