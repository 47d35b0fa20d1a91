"""Benchmark the patch frontend alone on one sequence; prints one JSON object.

Usage: python tools/bench_patch.py DATA [--sensor mono|stereo|rgbd] [--start S] [--end E]
       [--align sim3|se3] [-o key=value ...]   (keys of PatchConfig, e.g. -o ba.rounds=1)

Frames/s exclude reading (``read_s``, ``read_cpu_s``); ``fps`` is wall time, ``cpu_fps`` process CPU
time (all threads; the fairer figure on a shared machine). Stage times (flow / ba / bookkeeping) are
the frontend's wall-clock accounting.
"""

from __future__ import annotations

import argparse
import json
import logging
import time

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("data")
    parser.add_argument("--sensor", default="mono", choices=["mono", "stereo", "rgbd"])
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--end", type=int, default=None)
    parser.add_argument("--align", default=None, choices=["sim3", "se3"])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("-o", "--override", action="append", default=[])
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(asctime)s %(name)s: %(message)s")

    import torch

    torch.set_num_threads(args.threads)
    from fgslam.backend import Backend, BackendConfig
    from fgslam.core.config import from_dict
    from fgslam.eval.trajectory import EvalConfig, evaluate
    from fgslam.frontends.patch import PatchConfig, PatchFrontend
    from fgslam.io.datasets import DatasetConfig, open_dataset
    from fgslam.io.trajectory import Trajectory

    overrides: dict = {}
    import yaml

    for item in args.override:
        key, value = item.split("=", 1)
        node = overrides
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = yaml.safe_load(value)
    config = from_dict(PatchConfig, overrides, "overrides")
    ds = open_dataset(args.data, config=DatasetConfig(
        start=args.start, end=args.end, load_right=args.sensor == "stereo", load_depth=args.sensor == "rgbd",
        load_imu=False, load_rgb=False))
    fe = PatchFrontend(config, sensor_mode=args.sensor, backend=Backend(BackendConfig()))
    t0 = time.perf_counter()
    c0 = time.process_time()
    n = 0
    sources: dict[str, int] = {}
    read_s = read_cpu = 0.0
    it = iter(ds)
    while True:
        tr, cr = time.perf_counter(), time.process_time()
        try:
            frame = next(it)
        except StopIteration:
            break
        read_s += time.perf_counter() - tr
        read_cpu += time.process_time() - cr
        st = fe.process(frame)
        sources[st.pose_source] = sources.get(st.pose_source, 0) + 1
        n += 1
    fe.finish()
    wall = time.perf_counter() - t0 - read_s
    cpu = time.process_time() - c0 - read_cpu
    stamps, poses, _ = fe.trajectory()
    stages = fe.stage_times()
    out = {"frames": n, "posed": len(stamps), "keyframes": fe.num_keyframes(), "fps": n / wall, "cpu_fps": n / cpu,
           "wall_s": wall, "cpu_s": cpu, "stage_s": stages,
           "stage_ms_per_frame": {k: 1000.0 * v / max(n, 1) for k, v in stages.items()},
           "read_s": read_s, "read_cpu_s": read_cpu, "sources": sources}
    gt = ds.groundtruth
    if gt is not None and len(stamps) > 2:
        align = args.align or ("sim3" if args.sensor == "mono" else "se3")
        res = evaluate(gt, Trajectory(stamps, poses), EvalConfig(align=align, max_time_diff=0.02))
        out.update(ate=res.ate.rmse, align=align, scale=res.alignment.s, path_m=res.gt_path_length_m,
                   ate_pct=100 * res.ate.rmse / max(res.gt_path_length_m, 1e-9), matched=res.n_matched)
        est_motion = float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())
        out["est_path_m"] = est_motion
    else:
        out["est_path_m"] = float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()) if len(poses) > 1 else 0.0
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
