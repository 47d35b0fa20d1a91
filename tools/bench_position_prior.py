"""End-to-end benchmark of the PositionPrior factor plugin: ``fgslam run`` (monocular patch frontend)
on a synthetic street drive with and without GPS-like positions.

Renders (or reuses) a ``street-loop`` clip, writes a positions file from its ground truth (camera
centres at ``--rate`` Hz on the dataset's clock plus N(0, ``--noise``^2) per axis, seeded), then runs
``patch_mono`` and ``patch_mono_gps`` (its factors section pointed at that file) on the same frames
and prints one JSON object: per run the ATE without scale (SE(3) alignment) and with Sim(3)
alignment (its scale), in metres and % of the path, keyframes, position priors, CPU seconds; and
the machine's load average (shared machine).

    .venv/bin/python tools/bench_position_prior.py --work /tmp/bench_gps [--frames 300] [-o key=value ...]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.io.synth import SynthSequence, write_sequence
from fgslam.io.synth.scenarios import load_synth_config
from fgslam.io.trajectory import read_trajectory
from fgslam.run.config import load_slam_config
from fgslam.run.prepare import open_slam_dataset
from fgslam.run.runner import run_slam

POSITION_PRIOR = "fgslam.services.plugins:PositionPrior"


def write_positions(path: Path, t: np.ndarray, T_WC: np.ndarray, rate_hz: float, sigma: float, seed: int) -> Path:
    """True camera centres at ``rate_hz`` (linear between frames) plus N(0, sigma^2) per axis."""
    rng = np.random.default_rng(seed)
    ts = np.arange(t[0], t[-1] + 1e-9, 1.0 / rate_hz)
    p = np.stack([np.interp(ts, t, T_WC[:, k, 3]) for k in range(3)], axis=1) + rng.normal(scale=sigma, size=(len(ts), 3))
    path.write_text("# t x y z\n" + "".join(f"{a:.6f} {x:.6f} {y:.6f} {z:.6f}\n" for a, (x, y, z) in zip(ts, p)))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True, help="folder for the clip, positions and runs")
    parser.add_argument("--frames", type=int, default=300, help="street-loop frames (10 Hz)")
    parser.add_argument("--rate", type=float, default=1.0, help="positions per second")
    parser.add_argument("--noise", type=float, default=1.0, help="position noise per axis (m)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the position noise")
    parser.add_argument("-o", dest="overrides", action="append", default=[], help="override for both runs")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    data = args.work / f"street{args.frames}"
    if not (data / "mav0").is_dir():
        write_sequence(SynthSequence(load_synth_config("street-loop", None, [f"frames={args.frames}"])), data)
    base = load_slam_config("patch_mono", args.overrides)
    gt = open_slam_dataset(data, base).groundtruth
    gps = write_positions(args.work / "positions.txt", gt.timestamps, gt.T_WC, args.rate, args.noise, args.seed)
    out = {"frames": args.frames, "path_m": gt.path_length(), "positions": str(gps), "rate_hz": args.rate,
           "noise_m": args.noise, "load_average": [round(v, 2) for v in os.getloadavg()], "runs": {}}
    gps_factor = [{"class": POSITION_PRIOR, "options": {"file": str(gps), "sigma": args.noise, "max_dt": 0.25}}]
    for name, preset in (("patch_mono", "patch_mono"), ("patch_mono_gps", "patch_mono_gps")):
        config = load_slam_config(preset, args.overrides)
        if config.factors:
            config.factors = gps_factor
        summary = run_slam(open_slam_dataset(data, config), config, args.work / name, progress=False,
                           overwrite=True)  # the benchmark's own work folder: reruns replace
        est = read_trajectory(args.work / name / "trajectory_tum.txt", "tum")
        run = {"keyframes": summary.keyframes, "cpu_s": summary.cpu_s, "frames_with_pose": summary.frames_with_pose}
        for align in ("se3", "sim3"):
            r = evaluate(gt, est, replace(EvalConfig(), align=align))
            run[f"ate_{align}_m"] = r.ate.rmse
            run[f"ate_{align}_percent"] = 100.0 * r.ate.rmse / r.gt_path_length_m
            if align == "sim3":
                run["sim3_scale"] = r.alignment.s
        out["runs"][name] = run
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
