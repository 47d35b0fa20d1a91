"""Benchmark the dense (DROID-SLAM) pieces the dense frontend will call per frame; JSON to stdout.

Part 1, ``fgslam.factors.dense.DenseBlock`` over a window of ``--keyframes`` keyframes, each the source
of edges to its ``--edges`` nearest neighbours each way, with the grid of a W x H image (W/8 x H/8
inverse depths per keyframe): ms per ``linearize`` (all pieces), ``cost`` and ``refine_structure`` (one
step), and ns per measurement row of ``linearize``.

Part 2, ``fgslam.frontends.flow.DenseFlowSource.revise`` on rendered ``room-loop`` frames
(4 frames apart): ms per edge (forward and backward DIS, warps, confidences), best of ``--repeat``.

Usage: OMP_NUM_THREADS=1 .venv/bin/python tools/bench_dense.py [--keyframes 8] [--edges 2] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import gtsam
import numpy as np
import torch
from bench_factors import best_time  # tools/ is on the path of a script run from it

from fgslam.backend.keys import pose_key
from fgslam.factors.dense import DenseBlock, DenseEdge, DenseKeyframe, pixel_grid
from fgslam.factors.reprojection import reproject
from fgslam.frontends.flow import DenseFlowSource, grid_intrinsics
from fgslam.io.synth import SynthSequence
from fgslam.io.synth.scenarios import load_synth_config
from fgslam.core.lie import Sim3

STRIDE = 8


def block_bench(width: int, height: int, keyframes: int, edges: int, repeat: int) -> dict:
    h, w = height // STRIDE, width // STRIDE
    K8 = torch.tensor(grid_intrinsics((width / 2, width / 2, width / 2 - 0.5, height / 2 - 0.5), STRIDE))
    xi = torch.zeros(keyframes, 7, dtype=torch.float64)
    xi[:, 3] = 0.05 * torch.arange(keyframes, dtype=torch.float64)
    poses = Sim3.exp(xi)
    gen = torch.Generator().manual_seed(0)
    depths = [0.25 + 0.2 * torch.rand(h, w, generator=gen, dtype=torch.float64) for _ in range(keyframes)]
    keys = [pose_key(k) for k in range(keyframes)]
    grid = pixel_grid(h, w)
    edge_list = []
    for i in range(keyframes):
        for j in range(max(0, i - edges), min(keyframes, i + edges + 1)):
            if i != j:
                uv, _ = reproject(grid, depths[i].reshape(-1), poses[i], poses[j], K8)
                edge_list.append(DenseEdge(keys[i], keys[j], uv.reshape(h, w, 2) + 0.1, np.ones((h, w, 2))))
    block = DenseBlock([DenseKeyframe(keys[k], depths[k]) for k in range(keyframes)], edge_list, K8)
    values = gtsam.Values()
    for k, key in enumerate(keys):
        values.insert(key, poses[k].to_gtsam())
    rows = len(edge_list) * h * w
    t_lin = best_time(lambda: block.linearize(values), repeat)
    return {"image": f"{width}x{height}", "grid": f"{w}x{h}", "keyframes": keyframes, "edges": len(edge_list),
            "rows": rows, "linearize_ms": round(1e3 * t_lin, 2), "linearize_ns_per_row": round(1e9 * t_lin / rows, 1),
            "cost_ms": round(1e3 * best_time(lambda: block.cost(values), repeat), 2),
            "refine_1_step_ms": round(1e3 * best_time(lambda: block.refine_structure(values, 1), repeat), 2)}


def source_bench(width: int, height: int, repeat: int) -> dict:
    seq = SynthSequence(load_synth_config("room-loop", None, [f"camera.width={width}", f"camera.height={height}"]))
    frames = [np.clip(np.rint(seq.frame(i).image0), 0, 255).astype(np.uint8) for i in (100, 104)]
    src = DenseFlowSource(stride=STRIDE)
    t_add = best_time(lambda: src.add_frame(0, frames[0]), repeat)
    src.add_frame(1, frames[1])
    h, w = height // STRIDE, width // STRIDE
    grid = pixel_grid(h, w).numpy().reshape(1, h, w, 2)
    t_rev = best_time(lambda: src.revise([(0, 1)], grid), repeat)
    return {"image": f"{width}x{height}", "preset": src.config.preset, "image_scale": src.config.image_scale,
            "add_frame_ms": round(1e3 * t_add, 2), "revise_ms_per_edge": round(1e3 * t_rev, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=8)
    parser.add_argument("--edges", type=int, default=2, help="neighbours each way per source keyframe")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    out = {"platform": platform.platform(), "load_average": [round(x, 2) for x in os.getloadavg()],
           "torch_threads": torch.get_num_threads(),
           "block": [block_bench(wd, ht, args.keyframes, args.edges, args.repeat) for wd, ht in ((320, 240), (640, 480))],
           "source": [source_bench(wd, ht, args.repeat) for wd, ht in ((320, 240), (640, 480))]}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
