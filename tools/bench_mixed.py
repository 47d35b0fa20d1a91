"""Benchmark mixing families (issue 13 item 9): patch alone, pointmap alone, and both on one backend; JSON.

Datasets (``--datasets``): the synthetic ``low-texture`` preset (RGB-D, 201 frames at 10 Hz, 320x240,
rendered once into ``--synth-dir``), where patches find little texture, and 7-Scenes kitchen 0-599
RGB-D (``--data``). Per dataset, three ``fgslam run``s through :func:`fgslam.run.runner.run_slam`:

- ``patch``: the patch preset (``patch_rgbd`` / ``patch_7scenes_rgbd``) with ``loop_closure.mode:
  classical``: the patch family keeps keyframe images only with loop closure on, and the mixed run
  needs them, so both patch runs close loops alike;
- ``pointmap``: the pointmap preset (``pointmap_rgbd`` / ``pointmap_7scenes_rgbd``);
- ``both``: the patch run plus the pointmap contributor
  (``factors: [{class: fgslam.frontends.pointmap.mix:PointmapMix}]``): pointmap edges between the patch
  family's keyframes in the same graph.

Each reports SE(3) ATE (m, % of path), frames/s, CPU s, keyframes, failures and the load average.

Usage: OMP_NUM_THREADS=1 .venv/bin/python tools/bench_mixed.py [--datasets low_texture,7scenes]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"
MIX = {"class": "fgslam.frontends.pointmap.mix:PointmapMix", "options": {}}
DATASETS = {  # name -> (patch preset, pointmap preset, data folder or a synthetic preset)
    "low_texture": ("patch_rgbd", "pointmap_rgbd", "synthetic:low-texture"),
    "7scenes": ("patch_7scenes_rgbd", "pointmap_7scenes_rgbd", "7scenes_redkitchen_0-599"),
}


def _root(spec: str, args) -> Path:
    if not spec.startswith("synthetic:"):
        return args.data / spec
    from fgslam.run.demo import DemoSceneConfig, render_scene

    preset = spec.split(":", 1)[1]
    root = args.synth_dir / f"{preset}_320x240_201_10hz"
    render_scene(DemoSceneConfig(preset=preset, frames=201, rate_hz=10.0, width=320, height=240), root)
    return root


def _run(root: Path, preset: str, overrides: list[str], factors: list) -> dict:
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam

    config = load_slam_config(preset, ["output.plot=false", *overrides])
    config.factors = factors
    out = Path(tempfile.mkdtemp(prefix="bench_mixed_"))
    load = os.getloadavg()
    t0 = time.perf_counter()
    try:
        s = run_slam(open_slam_dataset(root, config), config, out, progress=False).to_dict()
    except Exception as exc:  # noqa: BLE001 - reported, the benchmark goes on
        return {"preset": preset, "error": f"{type(exc).__name__}: {exc}"}
    ev = s["evaluation"] or {}
    return {"preset": preset, "overrides": overrides, "mix": bool(factors), "ate_rmse_m": ev.get("ate_rmse_m"),
            "ate_percent_of_path": ev.get("ate_percent_of_path"), "fps": s["fps"], "cpu_s": s["cpu_s"],
            "wall_s": time.perf_counter() - t0, "keyframes": s["keyframes"], "failures": s["failures"],
            "stage_ms_per_frame": s["stage_ms_per_frame"], "load_before": [round(x, 2) for x in load],
            "load_after": [round(x, 2) for x in os.getloadavg()]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--datasets", default="low_texture,7scenes")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--synth-dir", type=Path, default=Path(tempfile.gettempdir()) / "fgslam_bench_synth")
    args = p.parse_args()
    report = {"cpus": os.cpu_count(), "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "datasets": {}}
    for name in [n.strip() for n in args.datasets.split(",") if n.strip()]:
        patch, pointmap, spec = DATASETS[name]
        root = _root(spec, args)
        loops = ["loop_closure.mode=classical"]
        report["datasets"][name] = {
            "data": str(root),
            "patch": _run(root, patch, loops, []),
            "pointmap": _run(root, pointmap, [], []),
            "both": _run(root, patch, loops, [MIX]),
        }
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
