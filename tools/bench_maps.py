"""Issue 25's 7-Scenes protocol in one command; prints one JSON object.

For the preset (``--preset``, default ``patch_7scenes_rgbd``): map the kitchen's frames 0-299
(``fgslam run --save-map``), localise frames 300-599 in the map (``fgslam localize``: frames localised,
ATE of the localised poses with the map run's own alignment applied unchanged, and with an alignment of
their own (``ate_own_alignment_m``: what is left once the map's frame is taken out), CPU per frame; with the
sequence's anchored odometry, the default, and without it: ``localize_map_only``), run the preset on frames
300-599 alone without loop closure (``odometry_run_300_599_ate_m``: the odometry's own accuracy), count
the frames 300-599 that share at least 30 % of their view with a map keyframe by ground truth
(``upper_bound``: :mod:`fgslam.eval.overlap`; most to expect of a localiser) and how many of them each
localisation posed (``of_overlapping``: any pose, and the localiser's own), extend
the map with frames 300-599 as a second recording (``fgslam run --map``: both sessions optimised in one
pose graph) and compare the joint trajectory over 0-599 (``joint_trajectory_tum.txt``: every frame of
both sessions in the map's frame; evaluated with the run's alignment: SE(3), Sim(3) for monocular
presets) with a single run over 0-599, and with the recording moved by the one merge transform alone
(``-o output.map_join.enabled=false``: the map run's frames, then the recording's from the merge on). Each step is a plain ``fgslam`` command in its own process, as a user would run it.

``--lost A:B``: the recording again with its frames A up to B (counted from its first; B not included) black, colour and
depth, a covered camera: the run loses its track and starts a new map; reported under ``extend_lost``
are that run's parts (``merge.json`` ``parts``) and the joint trajectory's ATE over the recording's
frames, with the join and with one transform. ``--baseline DIR`` runs the same ``--map`` steps with the
fgslam source tree DIR (``git worktree add DIR main``) for comparison.

Usage:
  nice -n 5 .venv/bin/python tools/bench_maps.py --work /tmp/bench_maps [--preset patch_7scenes_mono] \
      [--lost 100:140 [--baseline DIR]]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "7scenes_redkitchen_0-599"
SPLIT = 300
MIN_OVERLAP = 0.3  # issue 42's bound: frames sharing at least this share of their view with a map keyframe
HALF_OVERLAP = 0.5  # reported beside it
LOCALIZE_KEYS = ("frames", "localised", "tracked", "relocalised", "odometry", "localised_fraction", "cpu_ms_per_frame",
                 "frames_per_cpu_s", "setup_cpu_s", "evaluation")


def fgslam(*args: str, tree: Path | None = None) -> dict:
    env = dict(os.environ, **({} if tree is None else {"PYTHONPATH": str(tree.resolve())}))
    proc = subprocess.run([sys.executable, "-m", "fgslam", *args, "--json"], capture_output=True, text=True, env=env,
                          cwd=tree)
    if proc.returncode != 0:
        raise SystemExit(f"fgslam {' '.join(args)} failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True, type=Path)
    ap.add_argument("--preset", default="patch_7scenes_rgbd")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--lost", default=None, metavar="A:B", help="black frames A up to B (not included) of the recording (extend_lost)")
    ap.add_argument("--baseline", type=Path, default=None, metavar="DIR", help="fgslam source tree to compare --lost with")
    args = ap.parse_args()
    from fgslam.eval.trajectory import EvalConfig, evaluate
    from fgslam.io.datasets import open_dataset
    from fgslam.io.trajectory import Trajectory, read_trajectory

    w, d, p = args.work.resolve(), str(args.data.resolve()), args.preset
    w.mkdir(parents=True, exist_ok=True)
    stored, merged_map = w / "map.fgmap", w / "merged.fgmap"
    common = ["--no-progress", "--overwrite"]
    mapped = fgslam("run", p, "--data", d, "--out", str(w / "map"), *common, "-o", f"dataset.end={SPLIT}",
                    "--save-map", str(stored))
    loc = fgslam("localize", str(stored), "--data", d, "--out", str(w / "loc"), "--start", str(SPLIT),
                 "--overwrite")
    loc_map_only = fgslam("localize", str(stored), "--data", d, "--out", str(w / "loc_map_only"), "--start",
                          str(SPLIT), "--overwrite", "-o", "odometry.enabled=false")
    odometry = fgslam("run", p, "--data", d, "--out", str(w / "odometry"), *common, "-o", f"dataset.start={SPLIT}",
                      "-o", "loop_closure.mode=off")
    ext = fgslam("run", p, "--data", d, "--out", str(w / "ext"), *common, "-o", f"dataset.start={SPLIT}",
                 "--map", str(stored), "--save-map", str(merged_map))
    fgslam("run", p, "--data", d, "--out", str(w / "ext_one_transform"), *common, "-o", f"dataset.start={SPLIT}",
           "--map", str(stored), "-o", "output.map_join.enabled=false")
    single = fgslam("run", p, "--data", d, "--out", str(w / "single"), *common)
    merge = json.loads((w / "ext" / "merge.json").read_text())
    report = {
        "preset": p, "load_average": list(os.getloadavg()),
        "map_run": {"ate_rmse_m": mapped["evaluation"]["ate_rmse_m"], "align": mapped["evaluation"]["align"],
                    "keyframes": mapped["keyframes"], "map_bytes": stored.stat().st_size},
        **{name: {k: summary[k] for k in LOCALIZE_KEYS} for name, summary in (("localize", loc),
                                                                           ("localize_map_only", loc_map_only))},
        "extend": {"merged": merge["merged"], "consistent_keyframes": merge.get("consistent_keyframes"),
                   "recording_ate_own_frame_m": ext["evaluation"]["ate_rmse_m"]},
        "single_run_0_599_ate_m": single["evaluation"]["ate_rmse_m"],
    }
    # where the localisation's error comes from: its poses with an alignment of their own (the map's frame
    # against ground truth where the second half looks at it) and the odometry alone (its own alignment)
    gt_all, own = open_dataset(args.data).groundtruth, EvalConfig(align=mapped["evaluation"]["align"])
    for name in ("localize", "localize_map_only") if gt_all is not None else ():
        est = read_trajectory(w / ("loc" if name == "localize" else "loc_map_only") / "trajectory_tum.txt", "tum")
        report[name]["ate_own_alignment_m"] = evaluate(gt_all, est, own).ate.rmse
    report["odometry_run_300_599_ate_m"] = odometry["evaluation"]["ate_rmse_m"]
    overlap = map_overlap(args.data, stored)
    report["upper_bound"] = {"min_overlap": MIN_OVERLAP, "frames": len(overlap),
                             "overlapping": int(sum(o >= MIN_OVERLAP for o in overlap.values())),
                             "overlapping_half": int(sum(o >= HALF_OVERLAP for o in overlap.values()))}
    for name in ("localize", "localize_map_only"):
        report[name]["of_overlapping"] = coverage_of_bound(w / ("loc" if name == "localize" else "loc_map_only")
                                                           / "localization.csv", overlap)
    if merge["merged"]:
        gt, cfg = open_dataset(args.data).groundtruth, EvalConfig(align=mapped["evaluation"]["align"])
        single_ate = single["evaluation"]["ate_rmse_m"]
        joint = evaluate(gt, read_trajectory(w / "ext" / "joint_trajectory_tum.txt", "tum"), cfg)
        a = read_trajectory(w / "map" / "trajectory_tum.txt", "tum")
        b = read_trajectory(w / "ext_one_transform" / "merged_trajectory_tum.txt", "tum")
        both = Trajectory(np.concatenate([a.timestamps, b.timestamps]), np.concatenate([a.T_WC, b.T_WC]))
        one = evaluate(gt, both, cfg)
        report["extend"].update(joint=merge.get("joint"), joint_ate_m=joint.ate.rmse, joint_matched=joint.n_matched,
                                ratio_to_single=joint.ate.rmse / single_ate, one_transform_ate_m=one.ate.rmse,
                                one_transform_matched=one.n_matched, one_transform_ratio_to_single=one.ate.rmse / single_ate)
    if args.lost is not None:
        a, b = (int(v) for v in args.lost.split(":"))
        report["extend_lost"] = {"frames": [SPLIT + a, SPLIT + b]}
        lost_data = covered_copy(args.data.resolve(), w / "lost_data", range(SPLIT + a, SPLIT + b))
        from fgslam.export.mapfile import load_stored_map

        map_meta = json.dumps(load_stored_map(stored).meta)
        gt = open_dataset(args.data).groundtruth
        for name, tree in (("new", None), ("baseline", args.baseline)):
            if name == "baseline" and tree is None:
                continue
            for how, extra in (("joint", []), ("one_transform", ["-o", "output.map_join.enabled=false"])):
                out = w / f"ext_lost_{name}_{how}"
                summary = fgslam("run", p, "--data", str(lost_data), "--out", str(out), *common, "-o",
                                 f"dataset.start={SPLIT}", "--map", str(stored), *extra, tree=tree)
                merge_lost = json.loads((out / "merge.json").read_text())
                row = {"events": summary.get("events"), "merged": merge_lost["merged"],
                       "parts": merge_lost.get("parts"), "consistent_keyframes": merge_lost.get("consistent_keyframes")}
                if merge_lost["merged"]:
                    rec = read_trajectory(out / "merged_trajectory_tum.txt", "tum")
                    A = np.asarray(json.loads(map_meta)["groundtruth_alignment"]["matrix"])
                    row.update(recording_ate_in_map_m=ate_in_map(gt, rec, A), recording_frames_in_map=len(rec),
                               recording_frames_posed=summary["frames_with_pose"])
                report["extend_lost"][f"{name}_{how}"] = row
    print(json.dumps(report))


def map_overlap(data: Path, stored: Path) -> dict[int, float]:
    """Per frame of the localised part (raw index from ``SPLIT``): the share of its view the map's keyframe
    that saw most of it saw, by ground truth (:func:`fgslam.eval.overlap.view_overlap`: ground-truth poses and
    depth images). Empty when the data has no ground truth or depth; keyframes and frames without either are
    left out."""
    from fgslam.eval.overlap import view_overlap, view_samples
    from fgslam.export.mapfile import load_stored_map
    from fgslam.io.datasets import DatasetConfig, open_dataset

    ds = open_dataset(data, config=DatasetConfig(load_rgb=False, load_imu=False))
    gt = ds.groundtruth
    if gt is None:
        return {}
    T_WC_gt = {round(float(t), 6): T for t, T in zip(gt.timestamps, gt.T_WC)}
    index = {round(float(t), 6): i for i, t in enumerate(ds.timestamps)}
    depths, T_WCk = [], []
    for t in load_stored_map(stored).kf_timestamps:
        i = index.get(round(float(t), 6))
        if i is not None and round(float(t), 6) in T_WC_gt and (depth := ds[i].depth) is not None:
            depths.append(depth)
            T_WCk.append(T_WC_gt[round(float(t), 6)])
    if not depths:
        return {}
    out = {}
    for i in range(SPLIT, len(ds)):
        frame, t = ds[i], round(float(ds.timestamps[i]), 6)
        if t in T_WC_gt and frame.depth is not None:
            K = frame.calibration.K
            out[i] = view_overlap(view_samples(frame.depth, K, T_WC_gt[t]), depths, K, np.stack(T_WCk))
    return out


def coverage_of_bound(csv_path: Path, overlap: dict[int, float]) -> dict:
    """Of the frames overlapping the map by ``MIN_OVERLAP``: how many got a pose, and how many from the
    localiser itself (tracked or relocalised, not the anchored odometry)."""
    import csv

    with open(csv_path, newline="", encoding="utf-8") as f:
        status = {int(r["frame"]): r["status"] for r in csv.DictReader(f)}
    frames = [i for i, o in overlap.items() if o >= MIN_OVERLAP]
    posed = sum(status.get(i, "not_localised") != "not_localised" for i in frames)
    by_localiser = sum(status.get(i) in ("tracked", "relocalised") for i in frames)
    n = len(frames)
    return {"posed": posed, "posed_fraction": posed / n if n else None, "by_localiser": by_localiser,
            "by_localiser_fraction": by_localiser / n if n else None}


def ate_in_map(gt, est, A: np.ndarray) -> float:
    """RMSE of ``est``'s positions (the map's frame) moved by the map run's alignment ``A`` (4x4) against
    the ground truth at the same times (the localisation benchmark's measure: no alignment of its own)."""
    from fgslam.eval.trajectory import EvalConfig, evaluate
    from fgslam.io.trajectory import Trajectory
    from fgslam.localize.anchor import rigid_in_map

    return evaluate(gt, Trajectory(est.timestamps, rigid_in_map(A, est.T_WC)), EvalConfig(align="none")).ate.rmse


def covered_copy(data: Path, dst: Path, lost: range) -> Path:
    """``data`` (7-Scenes layout) with the colour and depth images of frames ``lost`` black: links to
    every other file."""
    import cv2

    for seq in sorted(q for q in data.iterdir() if q.is_dir()):
        (dst / seq.name).mkdir(parents=True, exist_ok=True)
        for f in sorted(seq.iterdir()):
            target = dst / seq.name / f.name
            if target.exists() or target.is_symlink():
                target.unlink()
            index = int(f.name.split(".")[0].split("-")[1])
            if index in lost and (f.name.endswith(".color.jpg") or f.name.endswith(".depth.png")):
                cv2.imwrite(str(target), np.zeros_like(cv2.imread(str(f), cv2.IMREAD_UNCHANGED)))
            else:
                target.symlink_to(f.resolve())
    for f in data.iterdir():
        if f.is_file() and not (dst / f.name).exists():
            (dst / f.name).symlink_to(f.resolve())
    return dst


if __name__ == "__main__":
    main()
