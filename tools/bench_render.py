"""Benchmark of the synthetic renderer (fgslam.io.synth): frames per second per preset and size.

Prints one JSON object: for every preset and resolution, ``view_fps`` (one camera: image + depth,
what a mono/RGB-D consumer needs) and ``stereo_fps`` (``SynthSequence.frame``: left + right + depth),
both single process and wall-clock, plus ``*_fps_cpu`` from the process CPU time (what an idle core
would give), the scene build time and ``os.getloadavg()`` before and after (the machine is shared,
so wall-clock numbers must be read together with the load).

Usage: OMP_NUM_THREADS=1 .venv/bin/python tools/bench_render.py [--frames 20] [--presets ...] [--sizes 320x96 ...]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from fgslam.io.synth import SynthSequence
from fgslam.io.synth.scenarios import PRESET_NAMES, load_synth_config

SIZES = ((320, 240), (640, 480))


def bench(preset: str, width: int, height: int, n_frames: int) -> dict:
    t0 = time.perf_counter()
    seq = SynthSequence(load_synth_config(preset, None, [f"camera.width={width}", f"camera.height={height}"]))
    build_s = time.perf_counter() - t0
    idx = np.linspace(0, seq.n_frames - 1, n_frames).round().astype(int)
    poses = seq.camera_poses(seq.frame_times()[idx])
    seq.render_view(poses[0])  # warm-up
    t0, c0 = time.perf_counter(), time.process_time()
    for T_WC in poses:
        seq.render_view(T_WC)
    view_s = (time.perf_counter() - t0) / n_frames
    view_cpu_s = (time.process_time() - c0) / n_frames
    t0, c0 = time.perf_counter(), time.process_time()
    for i in idx:
        seq.frame(int(i))
    stereo_s = (time.perf_counter() - t0) / n_frames
    stereo_cpu_s = (time.process_time() - c0) / n_frames
    return {"preset": preset, "width": width, "height": height, "quads": len(seq.scene),
            "texels_M": round(seq.atlas.texels.size / 1e6, 2), "build_s": round(build_s, 2),
            "view_fps": round(1.0 / view_s, 1), "stereo_fps": round(1.0 / stereo_s, 1),
            "view_fps_cpu": round(1.0 / view_cpu_s, 1), "stereo_fps_cpu": round(1.0 / stereo_cpu_s, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20, help="frames timed per preset and size")
    parser.add_argument("--presets", nargs="+", default=list(PRESET_NAMES), choices=PRESET_NAMES)
    parser.add_argument("--sizes", nargs="+", default=[f"{w}x{h}" for w, h in SIZES], metavar="WxH",
                        help="resolutions (default: 320x240 640x480; kitti00-drive renders 320x96)")
    args = parser.parse_args()
    sizes = [tuple(int(v) for v in size.lower().split("x")) for size in args.sizes]
    load_before = os.getloadavg()
    results = [bench(p, w, h, args.frames) for p in args.presets for (w, h) in sizes]
    print(json.dumps({"results": results, "cpu_count": os.cpu_count(),
                      "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
                      "loadavg_before": [round(x, 2) for x in load_before],
                      "loadavg_after": [round(x, 2) for x in os.getloadavg()]}, indent=1))


if __name__ == "__main__":
    main()
