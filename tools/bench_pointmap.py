"""Benchmark the pointmap (MASt3R-SLAM) pieces: projective matching of every pixel, the dense descriptors,
the built-in sources and the pose-only block; JSON to stdout.

All on a rendered ``room-loop`` pair at ``--width`` x ``--height`` (frames 40 and 52: 0.21 m apart, with
occlusions), against the generator's ground-truth correspondences:

- ``matching``: :func:`fgslam.frontends.pointmap.matching.match_pointmaps` on all W x H pixels with the
  exact geometry (RGB-D pointmaps, true relative pose): cold (identity start) and warm (started from the
  previous solution) LM alone, and LM + descriptor refinement (the default config; the compiled kernels of
  ``matching_jit``, loaded from numba's cache or compiled by the first call); wall ms (best of
  ``--repeat``) and CPU ms (``time.process_time``, comparable under load), median pixel error, valid
  fraction of the visible pixels, valid fraction of the occluded ones.
- ``descriptors``: each descriptor kind: ms per image, and the refinement of matches whose geometry is
  wrong by a rotation of 1 and 2 degrees (3 and 6 px): median error and fraction within 1 px after
  refinement (the measured reason for the default kind and window).
- ``sources``: ms per ``add_frame`` and ``predict`` of each built-in source (rgbd, stereo, mono).
- ``block``: ms per ``linearize`` and ``cost`` of one edge with every valid match (ray mode).

Usage: .venv/bin/python tools/bench_pointmap.py [--width 320 --height 240] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import cv2
import gtsam
import numpy as np
import torch

from fgslam.backend.keys import pose_key
from fgslam.factors.pointmap_block import PointmapBlock, PointmapEdge
from fgslam.frontends.pointmap.descriptors import DescriptorConfig, dense_descriptors
from fgslam.frontends.pointmap.matching import MatchingConfig, RayImage, match_pointmaps
from fgslam.frontends.pointmap.source import PointmapSourceConfig, make_pointmap_source, unproject_depth
from fgslam.io.synth import SynthSequence
from fgslam.io.synth.scenarios import load_synth_config

FRAMES = (40, 52)


def timed(fn, repeat: int) -> tuple[float, float, object]:
    """(best wall s, best CPU s, last result) of ``fn`` after one warm-up call."""
    out = fn()
    wall, cpu = float("inf"), float("inf")
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        out = fn()
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return wall, cpu, out


def render(seq, index, stereo=False):
    T = seq.camera_poses(seq.frame_times()[[index]])[0]
    out = seq.render_view(T)
    grey = np.clip(np.rint(out.image), 0, 255).astype(np.uint8)
    right = None
    if stereo:
        right = np.clip(np.rint(seq.render_view(T @ seq.T_S0S1).image), 0, 255).astype(np.uint8)
    return T, grey, out.depth.astype(np.float32), right


def truth(K, Ti, Tj, depth_i, depth_j):
    fx, fy, cx, cy = K
    T = np.linalg.inv(Ti) @ Tj
    H, W = depth_j.shape
    Xi = unproject_depth(depth_j, K).reshape(-1, 3).astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    uv = np.stack((fx * Xi[:, 0] / Xi[:, 2] + cx, fy * Xi[:, 1] / Xi[:, 2] + cy), -1)
    zi = cv2.remap(depth_i, uv[:, 0].astype(np.float32).reshape(H, W), uv[:, 1].astype(np.float32).reshape(H, W),
                   cv2.INTER_LINEAR).reshape(-1)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
    return uv, inside & (np.abs(zi - Xi[:, 2]) < 0.01 * Xi[:, 2]), inside & (zi < 0.8 * Xi[:, 2])


def rotated(T, deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    out = T.copy()
    out[:3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ T[:3, :3]
    return out


def accuracy(m, uv_true, visible, occluded) -> dict:
    valid = m.valid.numpy()
    err = np.linalg.norm(m.uv.numpy() - uv_true, axis=-1)[valid & visible]
    return {"median_px_error": round(float(np.median(err)), 3), "within_1px": round(float((err < 1).mean()), 3),
            "valid_of_visible": round(float(valid[visible].mean()), 4),
            "valid_of_occluded": round(float(valid[occluded].mean()), 4) if occluded.any() else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    load_before = [round(x, 2) for x in os.getloadavg()]
    seq = SynthSequence(load_synth_config("room-loop", None, [f"camera.width={args.width}", f"camera.height={args.height}",
                                                              "room.wall_density=80", "room.box_density=100"]))
    K = seq.K
    (Ti, gi, di, ri), (Tj, gj, dj, rj) = (render(seq, f, stereo=True) for f in FRAMES)
    T_true = np.linalg.inv(Ti) @ Tj
    uv_true, visible, occluded = truth(K, Ti, Tj, di, dj)
    N = args.width * args.height
    out = {"platform": platform.platform(), "torch_threads_default": torch.get_num_threads(),
           "image": f"{args.width}x{args.height}", "pixels": N, "pair": list(FRAMES),
           "visible_pixels": int(visible.sum()), "occluded_pixels": int(occluded.sum())}

    # ------------------------------------------------------------------ matching
    src = make_pointmap_source(PointmapSourceConfig(kind="rgbd"), K)
    src.add_frame(0, gi, depth=di)
    src.add_frame(1, gj, depth=dj)
    pair = src.predict(0, 1, T_CiCj=T_true)
    Dj = pair.D_j.reshape(N, -1)
    t_ref, c_ref, ref = timed(lambda: RayImage(pair.X_i_in_i, pair.C_i), args.repeat)
    matching = {"ray_image_ms": round(1e3 * t_ref, 2)}
    lm_only = MatchingConfig(refine_radius=0)
    for name, fn in (
        ("lm_cold", lambda: match_pointmaps(ref, pair.X_j_in_i, config=lm_only)),
        ("lm_warm", lambda: match_pointmaps(ref, pair.X_j_in_i, init_uv=cold.uv_lm, config=lm_only)),
        ("lm_cold_refined_default", lambda: match_pointmaps(ref, pair.X_j_in_i, D_i=pair.D_i, D_j=Dj)),
        ("lm_warm_refined_default", lambda: match_pointmaps(ref, pair.X_j_in_i, init_uv=cold.uv_lm, D_i=pair.D_i, D_j=Dj)),
    ):
        wall, cpu, m = timed(fn, args.repeat)
        if name == "lm_cold":
            cold = m
        matching[name] = {"wall_ms": round(1e3 * wall, 1), "cpu_ms": round(1e3 * cpu, 1),
                          **accuracy(m, uv_true, visible, occluded)}
    cfg = MatchingConfig()
    matching["default_config"] = {"max_iterations": cfg.max_iterations, "refine_radius": cfg.refine_radius,
                                  "refine_dilations": cfg.refine_dilations, "threads": cfg.threads}
    # threads: the same call with torch's default thread count
    wall, cpu, _ = timed(lambda: match_pointmaps(ref, pair.X_j_in_i, D_i=pair.D_i, D_j=Dj,
                                                 config=MatchingConfig(threads=0)), args.repeat)
    matching["lm_cold_refined_torch_default_threads"] = {"wall_ms": round(1e3 * wall, 1), "cpu_ms": round(1e3 * cpu, 1)}
    out["matching"] = matching

    # ------------------------------------------------------------------ descriptors
    descriptors = {}
    for kind in ("patch", "gradient"):
        dcfg = DescriptorConfig(kind=kind)
        wall, cpu, _ = timed(lambda: dense_descriptors(gi, dcfg), args.repeat)
        entry = {"ms_per_image": round(1e3 * wall, 2)}
        s = make_pointmap_source(PointmapSourceConfig(kind="rgbd", descriptor=dcfg), K)
        s.add_frame(0, gi, depth=di)
        s.add_frame(1, gj, depth=dj)
        for deg in (1.0, 2.0):
            p = s.predict(0, 1, T_CiCj=rotated(T_true, deg))
            r = RayImage(p.X_i_in_i, p.C_i)
            coarse = match_pointmaps(r, p.X_j_in_i, config=lm_only)
            entry[f"wrong_by_{deg:g}deg"] = {"lm_only": accuracy(coarse, uv_true, visible, occluded)["median_px_error"]}
            for radius, dil in ((1, [4, 2, 1]), (2, [1]), (3, [2, 1])):
                m = match_pointmaps(r, p.X_j_in_i, D_i=p.D_i, D_j=p.D_j.reshape(N, -1),
                                    config=MatchingConfig(refine_radius=radius, refine_dilations=dil))
                acc = accuracy(m, uv_true, visible, occluded)
                entry[f"wrong_by_{deg:g}deg"][f"r{radius}_d{'-'.join(map(str, dil))}"] = {
                    "median_px_error": acc["median_px_error"], "within_1px": acc["within_1px"]}
        descriptors[kind] = entry
    out["descriptors"] = descriptors

    # ------------------------------------------------------------------ sources
    sources = {}
    for kind in ("rgbd", "stereo", "mono"):
        s = make_pointmap_source(PointmapSourceConfig(kind=kind), K, baseline=seq.cfg.camera.baseline)
        wall_add, _, _ = timed(lambda: s.add_frame(0, gi, depth=di, right=ri), args.repeat)
        s.add_frame(1, gj, depth=dj, right=rj)
        wall, cpu, p = timed(lambda: s.predict(0, 1), args.repeat)
        entry = {"add_frame_ms": round(1e3 * wall_add, 1), "predict_ms": round(1e3 * wall, 1),
                 "predict_cpu_ms": round(1e3 * cpu, 1), "confident_fraction_i": round(float((p.C_i > 0.5).mean()), 3)}
        if p.T_CiCj is not None:
            T = p.T_CiCj
            R_err = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ T_true[:3, :3]) - 1) / 2, -1, 1)))
            t, tt = T[:3, 3], T_true[:3, 3]
            entry["rotation_error_deg"] = round(float(R_err), 3)
            if kind == "mono":
                cos = t @ tt / np.linalg.norm(t) / np.linalg.norm(tt)
                entry["translation_direction_error_deg"] = round(float(np.degrees(np.arccos(min(cos, 1.0)))), 2)
            else:
                entry["translation_error_m"] = round(float(np.linalg.norm(t - tt)), 4)
        sources[kind] = entry
    out["sources"] = sources

    # ------------------------------------------------------------------ block
    m = match_pointmaps(ref, pair.X_j_in_i, D_i=pair.D_i, D_j=Dj)
    q = np.nonzero(m.valid.numpy())[0]
    edge = PointmapEdge(pose_key(0), pose_key(1), pair.X_i_in_i.reshape(-1, 3)[m.index.numpy()[q]],
                        pair.X_j_in_j.reshape(-1, 3)[q], np.ones(q.size))
    block = PointmapBlock([edge])
    values = gtsam.Values()
    values.insert(pose_key(0), gtsam.Similarity3(gtsam.Rot3(Ti[:3, :3]), Ti[:3, 3], 1.0))
    values.insert(pose_key(1), gtsam.Similarity3(gtsam.Rot3(Tj[:3, :3]), Tj[:3, 3], 1.0))
    wall_lin, cpu_lin, _ = timed(lambda: block.linearize(values), args.repeat)
    wall_cost, _, _ = timed(lambda: block.cost(values), args.repeat)
    out["block"] = {"matches": int(q.size), "linearize_ms": round(1e3 * wall_lin, 1), "linearize_cpu_ms": round(1e3 * cpu_lin, 1),
                    "cost_ms": round(1e3 * wall_cost, 1)}
    out["load_average_before"] = load_before
    out["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
