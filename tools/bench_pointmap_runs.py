"""Benchmark the pointmap frontend end to end on a synthetic sequence: trajectory and reconstruction; JSON.

For each source (``--sources rgbd,mono,stereo``) the frontend runs over the rendered clip (default: the
``room-loop`` preset, 201 frames at 10 Hz, 320x240, 7.2 m: the issue-13 target clip; rendered once into
``--synth-dir``) and reports:

- ATE (SE(3) for metric sources, Sim(3) for mono) in metres and % of the ground-truth path (targets:
  RGB-D <= 0.5 %, mono <= 1.5 %), frames/s and CPU ms per frame (with the load average), keyframes,
  failures, ms per frame of each stage;
- reconstruction against the ground-truth depth, MASt3R-SLAM table 3's Chamfer-style metrics: the
  canonical pointmaps (``keyframe_points``) brought into the ground-truth world by the trajectory's
  alignment (the ATE's Umeyama SE(3) / Sim(3)); the reference cloud is every keyframe's rendered depth
  unprojected with its true pose (the same pixel stride); ``accuracy`` = mean distance of a
  reconstructed point to the nearest reference point, ``completion`` = mean distance of a reference
  point to the nearest reconstructed point, ``chamfer`` their mean (metres; also the medians).

Usage: .venv/bin/python tools/bench_pointmap_runs.py [--sources rgbd,mono] [--preset room-loop]
       [--frames 201 --rate 10 --size 320x240] [-o key=value ...]  (pointmap config overrides)
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def render(preset: str, frames: int, rate: float, size: str, folder: Path) -> Path:
    from fgslam.run.demo import DemoSceneConfig, render_scene

    w, h = (int(v) for v in size.lower().split("x"))
    root = folder / f"{preset}_{w}x{h}_{frames}_{rate:g}hz"
    render_scene(DemoSceneConfig(preset=preset, frames=frames, rate_hz=rate, width=w, height=h), root)
    return root


def reconstruction(fe, frames, alignment) -> dict:
    """Chamfer-style accuracy / completion (module docstring)."""
    from scipy.spatial import cKDTree

    from fgslam.frontends.pointmap.source import unproject_depth

    pts = fe.keyframe_points()
    if pts is None:
        return {"error": "no keyframe points"}
    X = pts[0]
    s, R, t = alignment
    X = s * X @ R.T + t
    by_time = {f.timestamp: f for f in frames}
    stride = fe.config.ply_stride
    ref = []
    for kf in fe.state.kfs.values():  # the keyframes' true depth with their true poses
        f = by_time[kf.timestamp]
        depth = f.depth[::stride, ::stride]
        K = np.asarray(f.calibration.K, float) / stride  # pixel (u, v) of the strided grid is (stride u, stride v)
        P = unproject_depth(depth, K).reshape(-1, 3)[depth.reshape(-1) > 0].astype(np.float64)
        ref.append(P @ f.T_WC_gt[:3, :3].T + f.T_WC_gt[:3, 3])
    Y = np.concatenate(ref)
    acc = cKDTree(Y).query(X)[0]
    comp = cKDTree(X).query(Y)[0]
    return {"points": int(len(X)), "reference_points": int(len(Y)), "accuracy_m": float(acc.mean()),
            "completion_m": float(comp.mean()), "chamfer_m": float(0.5 * (acc.mean() + comp.mean())),
            "accuracy_median_m": float(np.median(acc)), "completion_median_m": float(np.median(comp))}


def run(root: Path, source: str, overrides: list[str]) -> dict:
    from fgslam.backend import Backend, BackendConfig
    from fgslam.core.config import from_dict, to_dict
    from fgslam.eval.trajectory import EvalConfig, evaluate
    from fgslam.frontends.pointmap.config import PointmapConfig
    from fgslam.frontends.pointmap.frontend import PointmapFrontend
    from fgslam.io.datasets import DatasetConfig, open_dataset
    from fgslam.io.trajectory import Trajectory

    data = to_dict(PointmapConfig())
    data["source"]["kind"] = source
    for item in overrides:
        key, value = item.split("=", 1)
        node = data
        *path, last = key.split(".")
        for p in path:
            node = node[p]
        node[last] = json.loads(value) if value[:1] in "[{0123456789-tf" and value not in ("-",) else value
    config = from_dict(PointmapConfig, data)
    frames = list(open_dataset(root, config=DatasetConfig(load_right=source == "stereo", load_depth=True,
                                                          load_imu=False)))
    fe = PointmapFrontend(config, sensor_mode="mono" if source == "mono" else source, backend=Backend(BackendConfig()))
    load_before = os.getloadavg()
    c0, t0 = time.process_time(), time.perf_counter()
    sources = {}
    for f in frames:
        st = fe.process(f)
        sources[st.pose_source] = sources.get(st.pose_source, 0) + 1
    fe.finish()
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    t, T, _ = fe.trajectory()
    gt = {f.timestamp: f.T_WC_gt for f in frames}
    G = np.stack([gt[x] for x in t])
    align = "sim3" if source == "mono" else "se3"
    res = evaluate(Trajectory(t, G), Trajectory(t, T), EvalConfig(align=align))
    path = float(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1).sum())
    n = len(frames)
    out = {"source": source, "frames": n, "frames_with_pose": int(len(t)), "keyframes": fe.num_keyframes(),
           "pose_sources": sources, "align": align, "ate_rmse_m": float(res.ate.rmse),
           "ate_percent_of_path": 100.0 * float(res.ate.rmse) / path, "path_m": path,
           "fps": n / wall, "cpu_ms_per_frame": 1e3 * cpu / n,
           "stage_ms_per_frame": {k: round(1e3 * v / n, 1) for k, v in fe.stage_times().items()},
           "counts": dict(fe.state.counts), "load_before": [round(x, 2) for x in load_before],
           "load_after": [round(x, 2) for x in os.getloadavg()]}
    alignment = (float(res.alignment.s), np.asarray(res.alignment.R), np.asarray(res.alignment.t))
    out["reconstruction"] = reconstruction(fe, frames, alignment)
    out["target"] = {"rgbd": 0.5, "stereo": 0.5, "mono": 1.5}[source]
    out["met"] = out["ate_percent_of_path"] <= out["target"]
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sources", default="rgbd,mono")
    p.add_argument("--preset", default="room-loop")
    p.add_argument("--frames", type=int, default=201)
    p.add_argument("--rate", type=float, default=10.0)
    p.add_argument("--size", default="320x240")
    p.add_argument("--synth-dir", type=Path, default=Path(tempfile.gettempdir()) / "fgslam_bench_synth")
    p.add_argument("-o", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="pointmap config override (JSON value), e.g. -o block.mode=calibrated")
    args = p.parse_args()
    root = render(args.preset, args.frames, args.rate, args.size, args.synth_dir)
    out = {"preset": args.preset, "data": str(root), "overrides": args.overrides, "cpus": os.cpu_count(),
           "runs": [run(root, s.strip(), args.overrides) for s in args.sources.split(",") if s.strip()]}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
