"""Benchmark visual-inertial SLAM (issue 14; fgslam/services/imu.py); prints one JSON object.

Usage: python tools/bench_imu.py [--euroc DIR] [--synth-frames N] [--work DIR] [--skip-synth] [--family F]
       [--runs stereo_visual,stereo_inertial,...] [--skip-black] [-o key=value ...]

``--family`` (patch, dense, pointmap; default patch) picks the presets ``<family>_stereo``,
``<family>_stereo_inertial``, ``<family>_mono``, ``<family>_mono_inertial`` of the synthetic runs and
the black-frame clip (issue 26: every family inertial); ``--runs`` keeps some of the four.

- ``euroc_static``: the static EuRoC clip (``../shared/data/euroc_v101_micro``): static initialisation
  (gravity direction against the ground-truth orientation, gyroscope bias), stereo-inertial and
  visual-only stereo estimated motion (largest distance from the start, path length), mono-inertial
  (frames with a pose, largest distance from the start: "does not diverge").
- ``synthetic``: a moving room-loop clip with simulated IMU rendered into ``--work``: stereo-inertial
  SE(3) ATE in % of the path against visual-only stereo; mono-inertial SE(3) ATE without Sim(3)
  alignment and the scale error (Sim(3) alignment scale - 1); black-frame bridge (2 s of black frames:
  tracking failures, frames posed by the IMU, the largest step error across the gap).
- ``street``: the synthetic street-loop drive (``--street-frames``, 1,100: 665 m, back to the start;
  ``--street DIR`` reuses a written one): stereo-inertial with the driving settings of
  ``driving_stereo``, without and with loop closure ``both`` (SE(3) ATE); monocular-inertial with the
  preset as it is (SE(3) ATE without scale alignment, scale error). ``--skip-street`` leaves it out.
- ``inertial_state``: the IMU service's :class:`~fgslam.services.imu.InertialState` of each run (where
  the tree has it) and the inertial-only optimisations (scale change, sigma of log-scale).
- Runs on this tree's run package (``fgslam.run``): trees from before it are not supported.
- Speed: ``cpu_s`` per run (process CPU, comparable under load), ``cpu_fps``; the IMU service's own time
  per IMU factor built (``imu_update_ms_per_factor``: preintegration, relinking, marginalisation) and the BA stage
  per frame against visual-only (the VI graph update inside the window BA).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np


def _run(root: Path, preset: str, out: Path, overrides: list[str]):
    import fgslam.run.system as imu_mod  # the system builds the service through the name it imported
    from fgslam.io.run_files import SUMMARY_FILE
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import NoPoseError, run_slam

    captured = {}
    original = imu_mod.make_imu_service

    def capture(*args, **kwargs):
        captured["service"] = original(*args, **kwargs)
        return captured["service"]

    imu_mod.make_imu_service = capture
    try:
        cfg = load_slam_config(preset, overrides)
        ds = open_slam_dataset(root, cfg)
        try:
            summary = run_slam(ds, cfg, out, progress=False, overwrite=True)  # the benchmark's own folder
        except NoPoseError:  # no pose at all (monocular on the static clip waits for parallax): its summary
            summary = SimpleNamespace(**json.loads((out / SUMMARY_FILE).read_text()))
    finally:
        imu_mod.make_imu_service = original
    path = out / "trajectory_tum.txt"
    est = np.loadtxt(path, ndmin=2) if path.is_file() else np.zeros((0, 8))  # no pose at all: no file
    return ds, summary, est, captured.get("service")


def _evaluate(ds, est, align):
    from fgslam.eval.trajectory import EvalConfig, evaluate
    from fgslam.io.trajectory import Trajectory

    return evaluate(ds.groundtruth, Trajectory.from_position_quaternion(est[:, 0], est[:, 1:4], est[:, 4:8]),
                    EvalConfig(align=align))


def _speed(summary, service) -> dict:
    out = {"cpu_s": round(summary.cpu_s, 3), "cpu_fps": round(summary.frames_processed / max(summary.cpu_s, 1e-9), 2),
           "keyframes": summary.keyframes, "ba_ms_per_frame": round(summary.stage_ms_per_frame.get("ba", 0.0), 3)}
    if service is not None:
        s = service.summary()
        kfs = max(s["links"], 1)
        out["imu_update_ms_per_factor"] = round(1e3 * s["update_s"] / kfs, 3)
        out["imu"] = {k: s[k] for k in ("initialized", "scale", "links", "unlinked_intervals", "marginalised",
                                          "bad_intervals", "predictions")}
        state = getattr(service, "inertial_state", None)  # trees before issue 26 have none
        if state is not None:
            out["inertial_state"] = state.to_dict()
            out["inertial_only"] = [{k: e[k] for k in ("t", "keyframes", "scale_change", "applied", "log_scale_sigma")}
                                    for e in service.inertial_only]
    loop = getattr(summary, "loop", None)
    if loop:
        out["loop"] = {k: loop.get(k) for k in ("accepted_loops", "corrections_applied") if k in loop}
    return out


def _motion(est) -> dict:
    d = np.linalg.norm(est[:, 1:4] - est[0, 1:4], axis=1) if len(est) else np.zeros(0)
    steps = np.linalg.norm(np.diff(est[:, 1:4], axis=0), axis=1) if len(est) > 1 else np.zeros(0)
    return {"frames_with_pose": int(len(est)), "max_distance_from_start_m": float(d.max(initial=0.0)),
            "path_length_m": float(steps.sum())}


def euroc_static(root: Path, work: Path, overrides: list[str]) -> dict:
    from fgslam.backend import Backend
    from fgslam.services.imu import ImuService
    from fgslam.services.imu_samples import ImuServiceConfig
    from fgslam.io.datasets import DatasetConfig, open_dataset

    ds = open_dataset(root, config=DatasetConfig(load_right=False, load_imu=True))
    backend = Backend()
    service = ImuService(ImuServiceConfig(enabled=True), backend, ds.calibration.T_BC, metric=True,
                         dataset_noise=ds.imu_noise)
    for i, frame in enumerate(ds):
        service.feed(frame.imu, frame.timestamp)
        if i == 0:
            backend.add_keyframe(0, np.eye(4), frame.timestamp)
        service.poll()
    gt = ds.groundtruth
    R_BC = ds.calibration.T_BC[:3, :3]
    R_WB = gt.T_WC[0][:3, :3] @ R_BC.T
    g_true = R_WB.T @ np.array([0.0, 0.0, -1.0])
    g_est = service.static.gravity_B / np.linalg.norm(service.static.gravity_B)
    t0, t1 = float(gt.timestamps[0]), float(gt.timestamps[-1])
    R_gt = R_WB.T @ (gt.T_WC[-1][:3, :3] @ R_BC.T)
    R_est = service.buffer.rotation_between(t0, t1, service.static.gyro_bias)
    import gtsam

    out = {"gravity_error_deg": float(np.degrees(np.arccos(np.clip(g_true @ g_est, -1, 1)))),
           "gyro_bias_rad_s": [float(x) for x in service.static.gyro_bias],
           "gyro_rotation_error_deg_over_gt_span": float(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(R_est.T @ R_gt))))),
           "gt_span_s": t1 - t0}
    for name, preset in (("stereo_inertial", "patch_euroc_stereo_inertial"), ("stereo_visual", "patch_euroc_stereo"),
                         ("mono_inertial", "patch_euroc_mono_inertial")):
        _, summary, est, svc = _run(root, preset, work / f"euroc_{name}", overrides)
        out[name] = {**_motion(est), **_speed(summary, svc), "tracking_failures": summary.failures["tracking"]}
    return out


SYNTH_RUNS = ("stereo_visual", "stereo_inertial", "mono_visual", "mono_inertial")


def synthetic(work: Path, frames: int, overrides: list[str], family: str = "patch",
              runs: tuple[str, ...] = SYNTH_RUNS, black: bool = True) -> dict:
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.scenarios import load_synth_config

    root = work / f"room_{frames}"
    if not (root / "mav0").is_dir():
        write_sequence(SynthSequence(load_synth_config("room-loop", overrides=[f"frames={frames}", "camera.width=320",
                                                                               "camera.height=240"])), root)
    out = {"frames": frames, "family": family}
    presets = {"stereo_visual": (f"{family}_stereo", "se3"), "stereo_inertial": (f"{family}_stereo_inertial", "se3"),
               "mono_visual": (f"{family}_mono", "sim3"), "mono_inertial": (f"{family}_mono_inertial", "se3")}
    for name in runs:
        preset, align = presets[name]
        ds, summary, est, svc = _run(root, preset, work / f"synth_{family}_{name}", overrides)
        res = _evaluate(ds, est, align)
        entry = {"align": align, "ate_m": float(res.ate.rmse), "ate_percent_of_path": float(100 * res.ate.rmse / res.gt_path_length_m),
                 "path_m": float(res.gt_path_length_m), "tracking_failures": summary.failures["tracking"],
                 **_speed(summary, svc)}
        if name.startswith("mono"):
            sim = _evaluate(ds, est, "sim3")
            entry["sim3_scale"] = float(sim.alignment.s)
            entry["scale_error_percent"] = float(100 * (sim.alignment.s - 1.0)) if name == "mono_inertial" else None
            entry["sim3_ate_percent_of_path"] = float(100 * sim.ate.rmse / sim.gt_path_length_m)
        out[name] = entry
    if not black:
        return out
    # black frames: 2 s (40 frames at 20 Hz) from frame 50
    import cv2

    clip = work / f"room_{frames}_black"
    if clip.exists():
        shutil.rmtree(clip)
    shutil.copytree(root, clip)
    black = range(50, 90)
    for cam in ("cam0", "cam1"):
        names = sorted((clip / "mav0" / cam / "data").iterdir())
        for k in black:
            img = cv2.imread(str(names[k]), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(names[k]), np.zeros_like(img))
    ds, summary, est, svc = _run(clip, f"{family}_stereo_inertial", work / f"synth_{family}_black", overrides)
    res = _evaluate(ds, est, "se3")
    P_gt = ds.groundtruth.T_WC[:, :3, 3]
    err = np.linalg.norm(np.diff(est[:, 1:4], axis=0) - np.diff(P_gt[:len(est)], axis=0), axis=1)
    aligned = res.aligned_est.T_WC[:, :3, 3]
    gap_err = np.linalg.norm(aligned[list(black)] - P_gt[list(black)], axis=1)
    out["black_frames"] = {"frames": len(black), "tracking_failures": summary.failures["tracking"],
                           "imu_posed": summary.pose_sources.get("imu", 0), "ate_m": float(res.ate.rmse),
                           "largest_step_error_m": float(err.max()),
                           "step_error_at_gap_end_m": float(err[black[-1]]),
                           "largest_error_in_gap_m": float(gap_err.max())}
    return out


#: driving_stereo's patch settings, for the inertial presets on the street drive
DRIVING = ["patch.lk.auto_width=376", "patch.ba.rounds=1", "patch.ba.iterations=2", "patch.ba.measured_huber=true",
           "patch.ba.stereo_init_inv_depth=0.05", "patch.tracking.motion_damping=1.0"]


def street(work: Path, frames: int, overrides: list[str], root: Path | None = None) -> dict:
    from fgslam.io.synth import SynthSequence, write_sequence
    from fgslam.io.synth.scenarios import load_synth_config

    if root is None:
        root = work / f"street_{frames}"
        if not (root / "mav0").is_dir():
            write_sequence(SynthSequence(load_synth_config("street-loop", overrides=[f"frames={frames}"])), root)
    out = {"frames": frames, "data": str(root)}
    # stereo with driving_stereo's settings; monocular with patch_street_loop's (the patch defaults)
    for name, preset, extra in (("stereo_inertial_no_loops", "patch_stereo_inertial", DRIVING + ["loop_closure.mode=off"]),
                                ("stereo_inertial_loops_both", "patch_stereo_inertial", DRIVING + ["loop_closure.mode=both"]),
                                ("mono_inertial", "patch_mono_inertial", [])):
        ds, summary, est, svc = _run(root, preset, work / f"street_{name}", extra + overrides)
        res = _evaluate(ds, est, "se3")
        entry = {"ate_m": float(res.ate.rmse), "ate_percent_of_path": float(100 * res.ate.rmse / res.gt_path_length_m),
                 "path_m": float(res.gt_path_length_m), "frames_with_pose": int(len(est)),
                 "tracking_failures": summary.failures["tracking"], **_speed(summary, svc)}
        if name.startswith("mono"):
            sim = _evaluate(ds, est, "sim3")
            entry["scale_error_percent"] = float(100 * (sim.alignment.s - 1.0))
            entry["sim3_ate_percent_of_path"] = float(100 * sim.ate.rmse / sim.gt_path_length_m)
        out[name] = entry
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--euroc", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "euroc_v101_micro"))
    parser.add_argument("--synth-frames", type=int, default=400)
    parser.add_argument("--work", default="/tmp/fgslam_bench_imu")
    parser.add_argument("--skip-synth", action="store_true")
    parser.add_argument("--skip-euroc", action="store_true")
    parser.add_argument("--family", default="patch", choices=("patch", "dense", "pointmap"))
    parser.add_argument("--runs", default=",".join(SYNTH_RUNS), help="comma-separated synthetic runs (of %(default)s)")
    parser.add_argument("--skip-black", action="store_true", help="no black-frame clip")
    parser.add_argument("--street-frames", type=int, default=1100)
    parser.add_argument("--street", default=None, help="a written street-loop sequence to reuse")
    parser.add_argument("--skip-street", action="store_true")
    parser.add_argument("-o", "--override", action="append", default=[])
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.ERROR, format="%(asctime)s %(name)s: %(message)s")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    result = {"load_average": [round(v, 2) for v in os.getloadavg()]}
    t0 = time.perf_counter()
    if not args.skip_euroc:
        result["euroc_static"] = euroc_static(Path(args.euroc), work, args.override)
    if not args.skip_synth:
        runs = tuple(r for r in args.runs.split(",") if r)
        unknown = [r for r in runs if r not in SYNTH_RUNS]
        if unknown:
            parser.error(f"--runs: unknown {unknown} (of {', '.join(SYNTH_RUNS)})")
        result["synthetic"] = synthetic(work, args.synth_frames, args.override, args.family, runs, not args.skip_black)
    if not args.skip_street:
        result["street"] = street(work, args.street_frames, args.override, Path(args.street) if args.street else None)
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
