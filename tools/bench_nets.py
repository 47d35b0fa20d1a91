"""Time the learned networks' forward passes on CPU at W x H (320 x 240 by default); JSON to stdout.

DROID-SLAM (:mod:`fgslam.nets.droid`): per frame, the feature + context encoders; per update
iteration on ``E`` edges of the frame graph (``--droid-edges``), the correlation (memory-efficient
``alt``: 8 edges' volumes at a time, ``alt_features``: no volume at all; the all-pairs ``volume`` pyramid
of every edge, its build and lookup timed separately) and the update operator (ConvGRU and heads
with the per-frame aggregation).

DPVO (:mod:`fgslam.nets.dpvo`): per frame, the two 1/4-resolution encoders; per update iteration on
``patches x targets`` edges (``--dpvo-patches``, ``--dpvo-targets``: DPVO's default 96 patches and a
window of about 10 frames), the patch correlation and the update operator.

Random weights (timing does not depend on the values); best of ``--repeat``; torch threads from
``--threads`` (1 by default, the shared machine's fair setting). Also reports the load average and
CPU seconds of the whole run.

Usage: .venv/bin/python tools/bench_nets.py [--width 320 --height 240] [--threads 1] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import time

import torch
from bench_factors import best_time  # tools/ is on the path of a script run from it

from fgslam.nets.dpvo import VONet, patch_correlation, pyramid
from fgslam.nets.droid import AltCorr, CorrVolume, DroidNet, coords_grid


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def droid_bench(width: int, height: int, edges: int, repeat: int) -> dict:
    net = DroidNet().eval()
    frames = max(2, min(edges, 8))
    images = torch.randint(0, 255, (frames, 3, height, width)).float()
    out = {"edges": edges, "frames": frames}
    with torch.inference_mode():
        out["encoders_ms_per_frame"] = best_time(lambda: net.extract(images[:1]), repeat) * 1e3
        fmaps, hidden, inp = net.extract(images)
        h, w = fmaps.shape[-2:]
        ii = torch.arange(edges) % frames
        jj = (ii + 1) % frames
        coords0 = coords_grid(h, w)[None].expand(edges, h, w, 2)
        coords1 = coords0 + 1.5
        net_e, inp_e = hidden[ii], inp[ii]
        alt = AltCorr(fmaps, chunk=8)
        out["corr_alt_ms"] = best_time(lambda: alt(coords1, ii, jj), repeat) * 1e3
        feat = AltCorr(fmaps, chunk=8, mode="features")
        out["corr_alt_features_ms"] = best_time(lambda: feat(coords1, ii, jj), repeat) * 1e3
        out["corr_volume_build_ms"] = best_time(lambda: CorrVolume(fmaps[ii], fmaps[jj]), repeat) * 1e3
        vol = CorrVolume(fmaps[ii], fmaps[jj])
        out["corr_volume_lookup_ms"] = best_time(lambda: vol(coords1), repeat) * 1e3
        corr = alt(coords1, ii, jj)
        motion = net.motion(coords0, coords1, coords1)
        out["update_operator_ms"] = best_time(lambda: net.update(net_e, inp_e, corr, motion, ii), repeat) * 1e3
        out["iteration_ms_alt"] = out["corr_alt_ms"] + out["update_operator_ms"]
        out["iteration_ms_per_edge_alt"] = out["iteration_ms_alt"] / edges
    return out


def dpvo_bench(width: int, height: int, patches: int, targets: int, repeat: int) -> dict:
    net = VONet().eval()
    frames = targets + 1
    images = torch.randint(0, 255, (frames, 3, height, width)).float()
    out = {"patches": patches, "targets": targets, "edges": patches * targets}
    gen = torch.Generator().manual_seed(0)
    with torch.inference_mode():
        out["encoders_ms_per_frame"] = best_time(lambda: net.extract(images[:1]), repeat) * 1e3
        fmap, imap = net.extract(images)
        levels = pyramid(fmap)
        h, w = fmap.shape[-2:]
        centres = torch.stack((torch.rand(patches, generator=gen) * (w - 2) + 1, torch.rand(patches, generator=gen) * (h - 2) + 1), -1)
        src = torch.zeros(patches, dtype=torch.long)
        gmap, ctx = net.patchify.patches(fmap, imap, src, centres)
        kk = torch.arange(patches).repeat(targets)
        jj = torch.arange(1, frames).repeat_interleave(patches)
        ii = torch.zeros_like(kk)
        off = torch.stack(torch.meshgrid(torch.arange(3.0) - 1, torch.arange(3.0) - 1, indexing="ij")[::-1], -1)
        coords = centres[kk][:, None, None, :] + 1.0 + off
        out["corr_ms"] = best_time(lambda: patch_correlation(gmap, levels, coords, kk, jj), repeat) * 1e3
        corr = patch_correlation(gmap, levels, coords, kk, jj)
        state = torch.zeros(len(kk), net.DIM)
        out["update_operator_ms"] = best_time(lambda: net.update(state, ctx[kk], corr, ii, jj, kk), repeat) * 1e3
        out["iteration_ms"] = out["corr_ms"] + out["update_operator_ms"]
        out["iteration_us_per_edge"] = out["iteration_ms"] / len(kk) * 1e3
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--droid-edges", type=int, nargs="+", default=[1, 12])
    ap.add_argument("--dpvo-patches", type=int, default=96)
    ap.add_argument("--dpvo-targets", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0, c0 = time.perf_counter(), cpu_seconds()
    result = {
        "image": [args.width, args.height],
        "threads": args.threads,
        "torch": torch.__version__,
        "machine": platform.processor() or platform.machine(),
        "load_before": os.getloadavg()[0],
        "droid": [droid_bench(args.width, args.height, e, args.repeat) for e in args.droid_edges],
        "dpvo": dpvo_bench(args.width, args.height, args.dpvo_patches, args.dpvo_targets, args.repeat),
    }
    result["load_after"] = os.getloadavg()[0]
    result["wall_s"] = time.perf_counter() - t0
    result["cpu_s"] = cpu_seconds() - c0
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
