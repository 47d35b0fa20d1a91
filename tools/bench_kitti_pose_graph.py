"""The full KITTI 00 Sim(3) pose graph through fgslam's one LM loop against GTSAM's own LM; prints JSON.

Graph (:func:`build_kitti_pose_graph`, also used by tests/test_solver_pose_graph.py on a prefix):
keyframe ``k`` = ground-truth pose ``k`` of ``kitti_gt/00.txt`` (4,541 poses); the simulated
monocular drift of tools/bench_pose_graph.py (scale drift, heading bias, per-step noise; no false
loops) gives the initial estimate ``T_WC_odom``; the terms are a gauge prior on keyframe 0, one
``BetweenFactorSimilarity3`` per consecutive pair with the odometry's relative pose (sigmas
``PoseGraphConfig.smooth_sigmas``, scaled per distance as in the pose-graph correction) and one per
ground-truth revisit (positions within ``loop_radius_m``, ``min_loop_gap_s`` apart; the noisy
Sim(3) measurement of the simulation, sigmas ``PoseGraphConfig.loop_sigmas``). Plain Gaussian
noise, no robust kernel: the least-squares pose-graph correction.

Solvers, from the same initial values with the same stopping rules (``--max-iterations``,
``--relative-tolerance``, ``--absolute-tolerance``; GTSAM's defaults otherwise: lambda 1e-5,
factor 10, upper bound 1e5, identity damping, multifrontal Cholesky, COLAMD):

- ``gtsam``: ``gtsam.LevenbergMarquardtOptimizer``;
- ``fgslam``: ``fgslam.backend.solver.levenberg_marquardt`` on a ``NonlinearProblem`` (the loop the
  backend's pose-graph correction, ``fgslam.loop.pose_graph`` and ``fgslam pgo`` run).

Through the backend (``backend`` in the JSON): the same drifted keyframes and loop factors in a
:class:`fgslam.backend.Backend` (loops added with ``add_factor``), timed through its pose-graph
correction ``Backend.correct_pose_graph()`` (graph building included: consecutive odometry from the
current estimate with ``map.pose_graph`` sigmas, the loop factors, the anchor prior) against GTSAM's
LM on the graph ``Backend.pose_graph_problem()`` builds (building excluded), with the backend's
stopping rule (relative decrease ``--relative-tolerance``) given to both.

Times are the best of ``--repeats`` alternating runs (wall and process CPU: the machine is shared;
the load average is recorded); ``ratio`` = fgslam / gtsam; the final costs must agree to 1e-6
relative (``cost_relative_difference``).

    OMP_NUM_THREADS=1 .venv/bin/python tools/bench_kitti_pose_graph.py [--data ../shared/data] [--poses N]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

TOOLS_DIR = Path(__file__).resolve().parent
KITTI_FRAME_RATE_HZ = 10.0


def _bench_pose_graph():
    """tools/bench_pose_graph.py (the drift simulation; tools/ is not a package)."""
    name = "bench_pose_graph"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, TOOLS_DIR / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def build_kitti_pose_graph(gt_T_WC: np.ndarray, seed: int = 0, frame_dt_s: float = 1.0 / KITTI_FRAME_RATE_HZ):
    """``(graph, initial, info)``: the Sim(3) pose graph of the module docstring on ground truth
    ``gt_T_WC`` (N, 4, 4) (every pose a keyframe, ``frame_dt_s`` apart), as a
    ``gtsam.NonlinearFactorGraph`` and the drifted ``gtsam.Values``."""
    import gtsam

    from fgslam.factors.sim3 import SIM3_DOF, make_between_factors
    from fgslam.loop.pose_graph import PoseGraphConfig, smooth_sigmas

    bench = _bench_pose_graph()
    sim = bench.DriftSimConfig(stride=1, false_loop_fraction=0.0, seed=seed)
    scn = bench.simulate_kitti_drift(gt_T_WC, sim, frame_dt_s)
    pg = PoseGraphConfig()
    T = scn.T_WC_odom
    K = T.shape[0]
    graph = gtsam.NonlinearFactorGraph()
    prior_model = gtsam.noiseModel.Isotropic.Sigma(SIM3_DOF, pg.prior_sigma)
    graph.add(gtsam.PriorFactorSimilarity3(0, T[0].to_gtsam(), prior_model))
    keys = np.arange(K)
    for f in make_between_factors(keys[:-1], keys[1:], T[:-1].inverse() @ T[1:], sigmas=smooth_sigmas(T, pg)):
        graph.add(f)
    for f in make_between_factors(scn.loop_i, scn.loop_j, scn.T_CiCj, sigmas=np.asarray(pg.loop_sigmas)):
        graph.add(f)
    initial = gtsam.Values()
    for k, pose in enumerate(T.to_gtsam()):
        initial.insert(k, pose)
    info = {"poses": K, "loops": int(scn.loop_i.size), "factors": int(graph.size()), "drift_sim_config": asdict(sim)}
    return graph, initial, info


def solve_gtsam(graph, initial, max_iterations: int, relative_tolerance: float, absolute_tolerance: float):
    """GTSAM's LevenbergMarquardtOptimizer; returns (values, iterations)."""
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_tolerance)
    params.setAbsoluteErrorTol(absolute_tolerance)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    values = optimizer.optimize()
    return values, optimizer.iterations()


def solve_fgslam(graph, initial, max_iterations: int, relative_tolerance: float, absolute_tolerance: float):
    """fgslam's LM loop with GTSAM's LM defaults; returns (values, LMReport)."""
    from fgslam.backend.solver import LMSettings, NonlinearProblem, levenberg_marquardt

    settings = LMSettings(max_iterations=max_iterations, lambda_initial=1e-5, lambda_factor=10.0, lambda_max=1e5,
                          relative_tolerance=relative_tolerance, absolute_decrease_tolerance=absolute_tolerance)
    problem = NonlinearProblem(graph, initial)
    report = levenberg_marquardt(problem, settings)
    return problem.values, report


def _timed(fn, *args):
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0, time.process_time() - c0


def run(gt_T_WC: np.ndarray, repeats: int, max_iterations: int, relative_tolerance: float,
        absolute_tolerance: float, seed: int = 0, frame_dt_s: float = 1.0 / KITTI_FRAME_RATE_HZ) -> dict:
    """Both solvers on the graph of ``gt_T_WC``; the JSON-ready comparison."""
    graph, initial, info = build_kitti_pose_graph(gt_T_WC, seed, frame_dt_s)
    args = (graph, initial, max_iterations, relative_tolerance, absolute_tolerance)
    best = {"gtsam": None, "fgslam": None}
    for _ in range(repeats):
        for name, fn in (("gtsam", solve_gtsam), ("fgslam", solve_fgslam)):
            (values, extra), wall, cpu = _timed(fn, *args)
            entry = {"time_s": wall, "cpu_s": cpu, "final_cost": float(graph.error(values))}
            if name == "gtsam":
                entry["iterations"] = int(extra)
            else:
                entry.update(iterations=extra.iterations, solves=extra.solves, timings=extra.timings)
            if best[name] is None or wall < best[name]["time_s"]:
                best[name] = entry
    g, f = best["gtsam"], best["fgslam"]
    return {
        **info,
        "initial_cost": float(graph.error(initial)),
        "gtsam": g,
        "fgslam": f,
        "ratio_time": f["time_s"] / g["time_s"],
        "ratio_cpu": f["cpu_s"] / g["cpu_s"],
        "cost_relative_difference": abs(f["final_cost"] - g["final_cost"]) / max(abs(g["final_cost"]), 1e-300),
    }


def run_backend(gt_T_WC: np.ndarray, repeats: int, max_iterations: int, relative_tolerance: float, seed: int = 0,
                frame_dt_s: float = 1.0 / KITTI_FRAME_RATE_HZ) -> dict:
    """The pose-graph correction of a Backend holding the drifted keyframes and the loops, against
    GTSAM's LM on the same graph (module docstring)."""
    import gtsam

    from fgslam.backend import keys as backend_keys
    from fgslam.backend.config import BackendConfig
    from fgslam.backend.graph import Backend, as_similarity3
    from fgslam.factors.sim3 import make_between_factors
    from fgslam.loop.pose_graph import PoseGraphConfig

    bench = _bench_pose_graph()
    scn = bench.simulate_kitti_drift(gt_T_WC, bench.DriftSimConfig(stride=1, false_loop_fraction=0.0, seed=seed),
                                     frame_dt_s)
    config = BackendConfig(max_iterations=max_iterations, relative_tolerance=relative_tolerance, absolute_tolerance=0.0,
                           step_tolerance=0.0, lambda_initial=1e-5, lambda_factor=10.0, lambda_max=1e5)
    backend = Backend(config)
    for k, pose in enumerate(scn.T_WC_odom.to_gtsam()):
        backend.add_keyframe(k, pose, timestamp=k * frame_dt_s)
    keys_i = [backend_keys.pose_key(int(i)) for i in scn.loop_i]
    keys_j = [backend_keys.pose_key(int(j)) for j in scn.loop_j]
    for f in make_between_factors(np.array(keys_i, dtype=np.int64), np.array(keys_j, dtype=np.int64), scn.T_CiCj,
                                  sigmas=np.asarray(PoseGraphConfig().loop_sigmas)):
        backend.add_factor(f, owner="loop")
    graph, initial, ids = backend.pose_graph_problem()
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_tolerance)
    params.setAbsoluteErrorTol(0.0)
    best = {"gtsam": None, "backend": None}
    for _ in range(repeats):
        (values, iterations), wall, cpu = _timed(lambda: (lambda o: (o.optimize(), o.iterations()))(
            gtsam.LevenbergMarquardtOptimizer(graph, initial, params)))
        entry = {"time_s": wall, "cpu_s": cpu, "final_cost": float(graph.error(values)), "iterations": int(iterations)}
        if best["gtsam"] is None or wall < best["gtsam"]["time_s"]:
            best["gtsam"] = entry
        new, wall, cpu = _timed(backend.correct_pose_graph)
        result = gtsam.Values()
        for kf, T in new.items():
            result.insert(backend_keys.pose_key(kf), as_similarity3(T))
        entry = {"time_s": wall, "cpu_s": cpu, "final_cost": float(graph.error(result))}
        if best["backend"] is None or wall < best["backend"]["time_s"]:
            best["backend"] = entry
    g, b = best["gtsam"], best["backend"]
    return {"keyframes": len(ids), "loops": len(keys_i), "initial_cost": float(graph.error(initial)), "gtsam": g,
            "backend": b, "ratio_time": b["time_s"] / g["time_s"], "ratio_cpu": b["cpu_s"] / g["cpu_s"],
            "cost_relative_difference": abs(b["final_cost"] - g["final_cost"]) / max(abs(g["final_cost"]), 1e-300)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=TOOLS_DIR.parent.parent / "shared" / "data")
    ap.add_argument("--poses", type=int, default=0, help="first N poses of 00 (0: all 4,541)")
    ap.add_argument("--stride", type=int, default=1,
                    help="every stride-th pose a keyframe (a smaller graph with the same loops)")
    ap.add_argument("--repeats", type=int, default=3, help="alternating runs per solver; the fastest is reported")
    ap.add_argument("--max-iterations", type=int, default=100)
    ap.add_argument("--relative-tolerance", type=float, default=1e-5, help="GTSAM's default")
    ap.add_argument("--absolute-tolerance", type=float, default=1e-5, help="GTSAM's default")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    from fgslam.io.trajectory import read_trajectory

    gt = read_trajectory(args.data / "kitti_gt" / "00.txt", "kitti").T_WC
    if args.poses > 0:
        gt = gt[: args.poses]
    gt = gt[:: args.stride]
    load_start = os.getloadavg()[0]
    out = run(gt, args.repeats, args.max_iterations, args.relative_tolerance, args.absolute_tolerance, args.seed,
              args.stride / KITTI_FRAME_RATE_HZ)
    out["backend"] = run_backend(gt, args.repeats, args.max_iterations, args.relative_tolerance, args.seed,
                                 args.stride / KITTI_FRAME_RATE_HZ)
    out.update(load_average_1min_start=load_start, load_average_1min_end=os.getloadavg()[0], cpu_count=os.cpu_count())
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
