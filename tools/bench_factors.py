"""Benchmark residual linearisation and one map LM iteration with Schur-compressed visual blocks; JSON to stdout.

Part 1, per factor type, for N = 10^3 .. ``--max`` measurements (best of ``--repeat``, ns per
measurement): inverse-depth reprojection (residual + Jacobians, one pose pair and per-row poses),
the Schur elimination of those rows, a whole ``InverseDepthBlock.linearize``, and the other
engineers' batched residuals when present (Sim(3) between, depth prior, MASt3R ray+distance and
calibrated pointmap residuals).

Part 2, one Levenberg-Marquardt iteration of ``fgslam.backend.Backend`` (solver lm, global) over a
20-keyframe window: ``dense`` (DROID: 80x60 inverse depths per keyframe, edges to the next
``--edges`` keyframes each way) and ``patch`` (DPV-SLAM: 96 patches of 3x3 pixels per keyframe,
edges to ``--patch-edges`` keyframes each way). Reports the time of block linearisation, of the
gtsam solve and of the whole iteration.

Usage: OMP_NUM_THREADS=1 .venv/bin/python tools/bench_factors.py [--max 1000000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import importlib
import json
import platform
import time

import torch

from fgslam.factors.reprojection import reproject_inv_depth
from fgslam.factors.schur import SlotGroups, schur_reduce
from fgslam.factors.visual_block import BlockConfig, InverseDepthBlock
from fgslam.core.lie import Sim3
from fgslam.backend import Backend, BackendConfig, GaugeConfig, pose_key

K = torch.tensor([320.0, 320.0, 320.0, 240.0], dtype=torch.float64)
IMAGE_SIZE = (640.0, 480.0)


def best_time(fn, repeat: int) -> float:
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def random_poses(n: int, gen: torch.Generator, spacing: float = 0.1) -> Sim3:
    xi = torch.zeros(n, 7, dtype=torch.float64)
    xi[:, 3] = spacing * torch.arange(n, dtype=torch.float64)
    xi[:, :3] = 0.02 * (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5)
    return Sim3.exp(xi)


def factor_kernels(n: int, repeat: int) -> dict:
    gen = torch.Generator().manual_seed(0)
    dt = torch.float64
    T = random_poses(2, gen)
    uv = torch.rand(n, 2, generator=gen, dtype=dt) * torch.tensor(IMAGE_SIZE, dtype=dt)
    d = 0.2 + 0.2 * torch.rand(n, generator=gen, dtype=dt)
    uv_t = uv + torch.randn(n, 2, generator=gen, dtype=dt)
    out = {}
    out["reprojection_pair_ns"] = best_time(lambda: reproject_inv_depth(uv, d, T[0], T[1], K, uv_t), repeat) / n * 1e9
    rows_i = tuple(x.expand(n, *x.shape[1:]) if x.ndim else x.expand(n) for x in (T.R[0:1], T.t[0:1], T.s[0:1]))
    rows_j = tuple(x.expand(n, *x.shape[1:]) if x.ndim else x.expand(n) for x in (T.R[1:2], T.t[1:2], T.s[1:2]))
    rows_i = tuple(x.contiguous() for x in rows_i)
    rows_j = tuple(x.contiguous() for x in rows_j)
    out["reprojection_per_row_poses_ns"] = best_time(
        lambda: reproject_inv_depth(uv, d, rows_i, rows_j, K, uv_t), repeat) / n * 1e9
    out["reprojection_pair_float32_ns"] = best_time(
        lambda: reproject_inv_depth(uv.float(), d.float(), T[0].to(torch.float32), T[1].to(torch.float32),
                                    K.float(), uv_t.float()), repeat) / n * 1e9

    # Schur elimination of the same rows: 4 edges from one source keyframe, n / 4 depths.
    res = reproject_inv_depth(uv, d, T[0], T[1], K, uv_t)
    J = torch.stack((res.J_Ti, res.J_Tj), dim=2)
    n_struct = max(n // 4, 1)
    idx = torch.arange(n) % n_struct
    slots = torch.stack((torch.zeros(n, dtype=torch.long), 1 + torch.arange(n) // n_struct % 4), dim=1)
    order, groups = SlotGroups.sort_rows(slots)
    args = (res.residual[order], J[order], slots[order], res.J_d[order], idx[order], torch.ones(n, 2, dtype=dt)[order])
    out["schur_reduce_ns"] = best_time(lambda: schur_reduce(*args, 5, n_struct, 0.0, groups), repeat) / n * 1e9

    keys = [pose_key(i) for i in range(5)]
    poses5 = random_poses(5, gen)
    block = InverseDepthBlock(keys, slots[:, 0], slots[:, 1], uv, uv_t, idx, torch.ones(n, 2, dtype=dt), K,
                              0.2 + 0.2 * torch.rand(n_struct, generator=gen, dtype=dt))
    import gtsam

    values = gtsam.Values()
    for key, pose in zip(keys, poses5.to_gtsam()):
        values.insert(key, pose)
    out["block_linearize_ns"] = best_time(lambda: block.linearize(values), repeat) / n * 1e9
    out["block_cost_ns"] = best_time(lambda: block.cost(values), repeat) / n * 1e9

    # Other engineers' residuals, when their modules exist.
    try:
        sim3 = importlib.import_module("fgslam.factors.sim3")
        m = min(n, 100_000)  # 7x7 Jacobians per measurement: keep memory bounded
        A = Sim3.exp(0.1 * torch.randn(m, 7, generator=gen, dtype=dt))
        B = Sim3.exp(0.1 * torch.randn(m, 7, generator=gen, dtype=dt))
        Z = Sim3.exp(0.1 * torch.randn(m, 7, generator=gen, dtype=dt))
        out["sim3_between_ns"] = best_time(lambda: sim3.sim3_between_residual(A, B, Z), repeat) / m * 1e9
    except (ImportError, AttributeError) as exc:
        out["sim3_between_ns"] = f"unavailable: {exc}"
    try:
        depth = importlib.import_module("fgslam.factors.depth")
        sensor = 1.01 * d  # sensor inverse depths 1 % off
        weight = torch.ones_like(d)
        out["depth_prior_ns"] = best_time(lambda: depth.depth_prior(d, sensor, weight), repeat) / n * 1e9
    except (ImportError, AttributeError) as exc:
        out["depth_prior_ns"] = f"unavailable: {exc}"
    try:
        pointmap = importlib.import_module("fgslam.factors.pointmap")
        X_f = torch.randn(n, 3, generator=gen, dtype=dt) + torch.tensor([0.0, 0.0, 4.0], dtype=dt)
        X_k = T[1].inverse().act(T[0].act(X_f))
        out["pointmap_ray_dist_ns"] = best_time(lambda: pointmap.ray_dist_residuals(T[1].inverse() @ T[0], X_f, X_k), repeat) / n * 1e9
        uv_k = X_k[:, :2] / X_k[:, 2:] * 320.0 + torch.tensor([320.0, 240.0], dtype=dt)
        out["pointmap_calibrated_ns"] = best_time(
            lambda: pointmap.calibrated_residuals(T[1].inverse() @ T[0], X_f, X_k, uv_k, K), repeat) / n * 1e9
    except (ImportError, AttributeError) as exc:
        out["pointmap_ns"] = f"unavailable: {exc}"
    return out


def window_problem(kind: str, num_kf: int, edges: int, gen: torch.Generator) -> Backend:
    """A 20-keyframe window with one InverseDepthBlock per source keyframe (noisy flow targets)."""
    dt = torch.float64
    poses = random_poses(num_kf, gen)
    smap = Backend(BackendConfig(solver="lm", max_iterations=1, refine_steps=0, gauge=GaugeConfig()))
    for kf in range(num_kf):
        smap.add_keyframe(kf, poses[kf], float(kf))
    blocks = []
    if kind == "dense":
        ys, xs = torch.meshgrid(torch.arange(60, dtype=dt), torch.arange(80, dtype=dt), indexing="ij")
        uv_struct = torch.stack((xs, ys), -1).reshape(-1, 2) * 8.0 + 4.0  # 1/8-resolution pixel centres
        pixels_per_struct = 1
    else:
        pixels_per_struct = 9
    for src in range(num_kf):
        targets = [j for j in range(src - edges, src + edges + 1) if j != src and 0 <= j < num_kf]
        if kind == "patch":
            centres = torch.rand(96, 2, generator=gen, dtype=dt) * (torch.tensor(IMAGE_SIZE, dtype=dt) - 8.0) + 4.0
            offs = torch.stack(torch.meshgrid(torch.arange(-1.0, 2.0, dtype=dt), torch.arange(-1.0, 2.0, dtype=dt),
                                              indexing="ij"), -1).reshape(9, 2)
            uv_struct = (centres[:, None, :] + offs[None]).reshape(-1, 2)
        n_struct = uv_struct.shape[0] // pixels_per_struct
        d_true = 0.2 + 0.2 * torch.rand(n_struct, generator=gen, dtype=dt)
        d_rows = d_true.repeat_interleave(pixels_per_struct)
        idx = torch.arange(n_struct).repeat_interleave(pixels_per_struct)
        keys = [pose_key(src)] + [pose_key(j) for j in targets]
        uvs, uvt, ids, tslot = [], [], [], []
        for slot, j in enumerate(targets, start=1):
            res = reproject_inv_depth(uv_struct, d_rows, poses[src], poses[j], K, torch.zeros_like(uv_struct))
            uvs.append(uv_struct)
            uvt.append(res.residual + 0.5 * torch.randn(uv_struct.shape, generator=gen, dtype=dt))
            ids.append(idx)
            tslot.append(torch.full((len(idx),), slot))
        n = sum(len(t) for t in tslot)
        block = InverseDepthBlock(keys, torch.zeros(n, dtype=torch.long), torch.cat(tslot), torch.cat(uvs),
                                  torch.cat(uvt), torch.cat(ids), torch.ones(n, 2, dtype=dt), K, d_true * 1.05,
                                  BlockConfig())
        blocks.append(block)
    smap.set_blocks("bench", blocks)
    return smap


def lm_iteration(kind: str, edges: int, repeat: int) -> dict:
    gen = torch.Generator().manual_seed(1)
    smap = window_problem(kind, 20, edges, gen)
    blocks = smap.blocks()
    measurements = sum(int(b.uv_source.shape[0]) for b in blocks)
    structures = sum(b.num_structs for b in blocks)
    values = smap.values
    t_lin = best_time(lambda: [b.linearize(values) for b in blocks], repeat)
    gfg = smap.linearize()
    t_solve = best_time(lambda: gfg.optimize(), repeat)
    t_cost = best_time(lambda: smap.cost(), repeat)
    initial = [b.structure.clone() for b in blocks]

    def one_iteration():
        for kf in smap.keyframe_ids:  # restart from the same state each repetition
            smap.set_pose(kf, values.atSimilarity3(pose_key(kf)))
        for b, d in zip(blocks, initial):
            b.set_structure(d)
        return smap.optimize_global()

    t_iter = best_time(one_iteration, repeat)
    return {
        "keyframes": 20,
        "blocks": len(blocks),
        "measurements": measurements,
        "structures": structures,
        "linearize_blocks_ms": 1e3 * t_lin,
        "linearize_ns_per_measurement": 1e9 * t_lin / measurements,
        "gtsam_solve_ms": 1e3 * t_solve,
        "true_cost_ms": 1e3 * t_cost,
        "lm_iteration_ms": 1e3 * t_iter,
        "lm_iteration_ns_per_measurement": 1e9 * t_iter / measurements,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max", type=int, default=1_000_000, help="largest number of measurements")
    parser.add_argument("--repeat", type=int, default=3, help="repetitions (best time is reported)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--edges", type=int, default=2, help="dense: edges to keyframes on each side")
    parser.add_argument("--patch-edges", type=int, default=4, help="patch: edges to keyframes on each side")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    sizes = [n for n in (10**3, 10**4, 10**5, 10**6) if n <= args.max]
    result = {
        "machine": platform.processor() or platform.machine(),
        "torch_threads": args.threads,
        "factors": {str(n): factor_kernels(n, args.repeat) for n in sizes},
        "lm_iteration": {
            "dense": lm_iteration("dense", args.edges, args.repeat),
            "patch": lm_iteration("patch", args.patch_edges, args.repeat),
        },
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
