"""Benchmark of classical loop closure (fgslam.loop.closure) on a synthetic street-loop; JSON to stdout.

Keyframes every ``--stride`` frames of one loop, then (offset by half a stride) the first
``--revisit`` frames again. Odometry: ground-truth keyframe steps with a scale drift growing to
``exp(--scale-drift)`` and a heading drift of ``--heading-drift-deg`` over the run, continued from the
corrected poses after every correction (as a frontend would). Reports the keyframe ATE (sim3
alignment) of the drifted odometry and of the run with loop closure, the loops verified / accepted,
the per-stage time per keyframe (describe = ORB + BoW, detect, verify, pose graph) and the wall time.

``--patch N``: instead, run the patch frontend (mono, ``PatchFrontend`` with its built-in loop
closure) on the first N frames of the street-loop with ``loop_closure.mode`` classical and off
(``--no-baseline``: classical only; ``--threaded``: closer in its worker thread, else synchronous);
reports the ATE (sim3) over all frames of each run, their ratio and the loop counts.

    python tools/bench_loop.py [--stride 4] [--revisit 80] [--threaded] [--patch 1100 [--no-baseline]]
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.io.trajectory import Trajectory
from fgslam.loop.closure import LoopCloser
from fgslam.loop.records import LoopClosureConfig


def _rigid(T: np.ndarray) -> np.ndarray:
    out = np.array(T, dtype=np.float64, copy=True)
    s = np.cbrt(np.linalg.det(out[..., :3, :3]))
    out[..., :3, :3] /= s[..., None, None]
    return out


def _ate(t, T_gt, T_est) -> float:
    res = evaluate(Trajectory(t, T_gt), Trajectory(t, _rigid(np.stack(T_est))),
                   EvalConfig(align="sim3", rpe_delta_meters=None))
    return float(res.ate.rmse)


def _patch_run(n_frames: int, baseline: bool = True, threaded: bool = True) -> dict:
    """The patch frontend (mono, default config) on the first ``n_frames`` of the street-loop with
    loop closure classical (and, with ``baseline``, off): ATE (sim3) over all frames of each run."""
    import torch

    from fgslam.backend import Backend, BackendConfig
    from fgslam.frontends.patch import PatchConfig, PatchFrontend
    from fgslam.io.calibration import Calibration
    from fgslam.run.system import SlamSystem
    from fgslam.io.frame import Frame
    from fgslam.io.synth import SynthSequence, default_config

    torch.set_num_threads(1)
    cfg = default_config("street-loop")
    seq = SynthSequence(cfg)
    cal = Calibration(cfg.camera.width, cfg.camera.height, np.array(seq.K))
    t = np.arange(n_frames) / cfg.camera.rate_hz
    T_gt = seq.camera_poses(t)
    t0 = time.perf_counter()
    images = [np.clip(seq.render_view(T).image, 0, 255).astype(np.uint8) for T in T_gt]
    out: dict = {"frontend": "patch", "frames": n_frames, "render_s": round(time.perf_counter() - t0, 1)}

    def ate(traj) -> float:
        ts, T, _ = traj
        idx = np.round(ts * cfg.camera.rate_hz).astype(int)
        return round(_ate(ts, T_gt[idx], T), 3)

    for mode in ("classical", "off") if baseline else ("classical",):
        fe = PatchFrontend(PatchConfig(), cal, "mono", backend=Backend(BackendConfig()))
        system = SlamSystem.around(fe, LoopClosureConfig(mode=mode, run_in_thread=threaded))
        t0 = time.perf_counter()
        for i in range(n_frames):
            system.step(Frame(i, i, float(t[i]), images[i], cal))
        system.finish()
        run = {"wall_s": round(time.perf_counter() - t0, 1), "keyframes": fe.num_keyframes(),
               "tracking_failures": fe.num_failures, "ate_m": ate(fe.trajectory())}
        summary = system.loop_summary()
        if summary is not None:
            summary["closer_s"] = {k: round(v, 2) for k, v in summary["closer_s"].items()}
            run["loop"] = summary
        out[f"loop_{mode}"] = run
    if baseline and out["loop_off"]["ate_m"] > 0:
        out["ate_ratio_with_over_without"] = round(out["loop_classical"]["ate_m"] / out["loop_off"]["ate_m"], 3)
    return out


def main() -> int:
    from fgslam.io.synth import SynthSequence, default_config

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stride", type=int, default=4, help="frames between keyframes")
    ap.add_argument("--revisit", type=int, default=80, help="frames of the return stretch")
    ap.add_argument("--scale-drift", type=float, default=0.6, help="log scale drift at the end")
    ap.add_argument("--heading-drift-deg", type=float, default=15.0, help="heading drift at the end")
    ap.add_argument("--threaded", action="store_true", help="worker thread, polled without waiting")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--patch", type=int, default=0, metavar="N", help="patch frontend on N frames instead")
    ap.add_argument("--no-baseline", action="store_true", help="--patch: skip the run without loop closure")
    args = ap.parse_args()
    if args.patch:
        print(json.dumps(_patch_run(args.patch, baseline=not args.no_baseline, threaded=args.threaded), indent=2))
        return 0

    cfg = default_config("street-loop")
    cfg.seed = args.seed
    seq = SynthSequence(cfg)
    loop = cfg.frames - 1
    frames = np.array(list(range(0, loop, args.stride))
                      + list(range(loop + args.stride // 2, loop + args.revisit, args.stride)))
    t = frames / cfg.camera.rate_hz
    T_gt = seq.camera_poses(t)
    t0 = time.perf_counter()
    images = [np.clip(seq.render_view(T).image, 0, 255).astype(np.uint8) for T in T_gt]
    render_s = time.perf_counter() - t0
    n = len(frames)
    rate, yaw = args.scale_drift / n, math.radians(args.heading_drift_deg) / n
    c, s_ = math.cos(yaw), math.sin(yaw)
    R_yaw = np.array([[c, 0.0, s_], [0.0, 1.0, 0.0], [-s_, 0.0, c]])
    steps = []
    for k in range(1, n):
        D = np.linalg.inv(T_gt[k - 1]) @ T_gt[k]
        S = np.eye(4)
        S[:3, :3] = R_yaw @ D[:3, :3]
        S[:3, 3] = math.exp(rate * (k - 1)) * D[:3, 3]
        steps.append(S)
    drifted = [T_gt[0]]
    for S in steps:
        drifted.append(drifted[-1] @ S)

    closer = LoopCloser(LoopClosureConfig(mode="classical", run_in_thread=args.threaded))
    poses, unit, n_corr = [T_gt[0].copy()], 1.0, 0
    t0 = time.perf_counter()

    def poll() -> None:
        nonlocal poses, unit, n_corr
        corr = closer.poll()
        if corr is not None:
            new, factors = corr.apply(dict(enumerate(poses)))
            poses = [new[i] for i in range(len(poses))]
            unit *= factors[len(poses) - 1]
            n_corr += 1

    for k in range(n):
        if k:
            S = steps[k - 1].copy()
            S[:3, 3] *= unit
            poses.append(poses[-1] @ S)
        closer.add_keyframe(k, float(t[k]), images[k], seq.K, poses[k])
        poll()
    closer.close()
    poll()
    wall = time.perf_counter() - t0
    loops = closer.loops
    times = closer.stage_times()
    out = {
        "keyframes": n, "resolution": [cfg.camera.width, cfg.camera.height], "threaded": args.threaded,
        "render_s": round(render_s, 3), "wall_s": round(wall, 3),
        "ms_per_keyframe": {k: round(1e3 * v / n, 3) for k, v in times.items()},
        "verifications": len(closer.verifications),
        "verified_loops": len(loops), "accepted_loops": sum(l.status == "accepted" for l in loops),
        "corrections_applied": n_corr,
        "ate_drift_m": round(_ate(t, T_gt, drifted), 3), "ate_loop_closure_m": round(_ate(t, T_gt, poses), 3),
    }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
