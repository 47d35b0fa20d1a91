"""fgslam side by side with ORB-SLAM3 on the same sequences; prints one JSON object.

ORB-SLAM3 (GPL-3) is a benchmark peer only: it lives in a venv of its own, outside the project
(``../shared/peers/orbslam3/setup.sh PEER``), and runs here as a subprocess
(``../shared/peers/orbslam3/run_orbslam3.py``); fgslam never imports it. Without the peer venv
(``--peer PATH`` or the ``FGSLAM_ORBSLAM3_PEER`` environment variable) this script says how to
create it and exits 0.

Sequences (``--list``): 7-Scenes kitchen 0-599 RGB-D and monocular, KITTI 00 frames 0-199
monocular, and the synthetic ``highway`` clip monocular (rendered once into ``--synth-dir``).
ORB-SLAM3 reads monocular sequences in the KITTI layout (``image_0/*.png``, ``times.txt``), so
each gets a view of symbolic links with fgslam's own timestamps; RGB-D reads the 7-Scenes folder.
Its settings YAML is the shared one where there is one (KITTI, 7-Scenes RGB-D) and is generated
from fgslam's calibration otherwise (``orbslam3_settings``).

Per sequence: ORB-SLAM3 runs ``--repeats`` times fed at camera rate (``--pace``, as a live camera
would; unpaced, monocular ORB-SLAM3 loses track on a 2-core machine), fgslam ``--fgslam-repeats``
times (``fgslam run PRESET``, one process each), the two alternating run by run (a machine whose speed
drifts over the minutes weighs on both alike). Both trajectories are mapped to fgslam's
timestamps and evaluated by fgslam's evaluator against the same ground truth, with the same
alignment (Sim(3) monocular, SE(3) RGB-D), over **only the frames both posed**, for every pair of
runs; medians are reported, with each system's ATE over all its own posed frames, frames posed,
frames/s (ORB-SLAM3's paced figure is capped at the camera rate), CPU seconds, frames per CPU
second (all threads; less sensitive to a shared machine's load than frames/s) and the ratios
fgslam / ORB-SLAM3 (ATE below 1 and frames/s above 1 favour fgslam). ORB-SLAM3's runner decodes
every image before its timed loop, fgslam's run decodes them in its reader thread while it tracks:
fgslam's frames per CPU second are also given without that thread's CPU (``summary.json``
``read_cpu_s``), the like-for-like figure. The machine may be shared:
the load average is recorded around every run.

Usage:
  .venv/bin/python tools/bench_peers.py --peer $HOME/orbslam3-peer [--sequences kitti00_mono,highway_mono] \
      [--repeats 3] [--fgslam-repeats 1] [-o key=value ...] [--keep-outputs DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

from bench_run import CASES, DEFAULT_DATA, REPO

PEER_ENV = "FGSLAM_ORBSLAM3_PEER"
DEFAULT_PEER_SCRIPTS = REPO.parent / "shared" / "peers" / "orbslam3"
SYNTH = "synthetic highway"


@dataclass(frozen=True)
class Sequence:
    """One side-by-side case: fgslam preset, data (folder under ``--data`` or SYNTH), ORB-SLAM3 mode,
    its settings file in the peer folder (None: generated from the calibration) and ORB features."""

    preset: str
    data: str
    mode: str  # "mono" | "rgbd"
    layout: str  # "kitti" | "7scenes" | "euroc": where the raw images are (see raw_image_files)
    settings: Optional[str]
    orb_features: int = 2000


HIGHWAY_PRESET = "patch_highway_mono"
SEQUENCES: dict[str, Sequence] = {
    # 7-Scenes monocular: the RGB-D settings (same camera; ORB-SLAM3 reads no depth keys in mono)
    "7scenes_rgbd": Sequence(CASES["7scenes_rgbd"].preset, CASES["7scenes_rgbd"].data, "rgbd", "7scenes", "7scenes_rgbd.yaml"),
    "7scenes_mono": Sequence(CASES["7scenes_mono"].preset, CASES["7scenes_mono"].data, "mono", "7scenes", "7scenes_rgbd.yaml"),
    "kitti00_mono": Sequence(CASES["kitti00_mono"].preset, CASES["kitti00_mono"].data, "mono", "kitti", "kitti00-02_mono.yaml"),
    "highway_mono": Sequence(HIGHWAY_PRESET, SYNTH, "mono", "euroc", None, 2000),
}
ALIGN = {"mono": "sim3", "rgbd": "se3"}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--peer", type=Path, default=None,
                   help=f"ORB-SLAM3 peer venv made by setup.sh (default: ${PEER_ENV})")
    p.add_argument("--peer-scripts", type=Path, default=DEFAULT_PEER_SCRIPTS,
                   help="folder of run_orbslam3.py and settings/ (default: ../shared/peers/orbslam3)")
    p.add_argument("--sequences", default=",".join(SEQUENCES), help="comma-separated subset of: " + ", ".join(SEQUENCES))
    p.add_argument("--list", action="store_true", help="list the sequences and exit")
    p.add_argument("--repeats", type=int, default=3, help="ORB-SLAM3 runs per sequence (median; it is not deterministic)")
    p.add_argument("--fgslam-repeats", type=int, default=1, help="fgslam runs per sequence (median)")
    p.add_argument("--no-pace", action="store_true", help="feed ORB-SLAM3 as fast as it takes frames (default: camera rate)")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    p.add_argument("--synth-dir", type=Path, default=Path(tempfile.gettempdir()) / "fgslam_bench_synth",
                   help="cache folder of the synthetic highway clip (reused when the scene is the same)")
    p.add_argument("--highway-frames", type=int, default=201, help="frames of the highway clip (10 Hz)")
    p.add_argument("--highway-seed", type=int, default=0, help="scene layout / texture seed of the highway clip")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds after which one run is stopped")
    p.add_argument("--keep-outputs", type=Path, default=None, help="write every run's outputs under DIR")
    p.add_argument("-o", "--override", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="fgslam SlamConfig override applied to every sequence (repeatable)")
    p.add_argument("--preset", dest="presets", action="append", default=[], metavar="SEQUENCE=PRESET",
                   help="run this fgslam preset on the sequence instead of its default (repeatable; e.g. "
                        "7scenes_rgbd=handheld_rgbd, the class benchmark's recommended preset)")
    p.add_argument("--baseline", type=Path, default=None, metavar="DIR",
                   help="also run every fgslam run on the fgslam source tree in DIR (e.g. `git worktree add /tmp/main "
                        "main`), alternating with this tree's run by run; the report adds the baseline's figures and "
                        "this tree's ratios to them")
    args = p.parse_args(argv)
    names = [n.strip() for n in args.sequences.split(",") if n.strip()]
    unknown = [n for n in names if n not in SEQUENCES]
    if unknown or not names:
        p.error(f"unknown sequence(s): {', '.join(unknown) or '(none given)'} (known: {', '.join(SEQUENCES)})")
    if args.repeats < 1 or args.fgslam_repeats < 1:
        p.error("--repeats and --fgslam-repeats must be >= 1")
    if args.highway_frames < 2:
        p.error("--highway-frames must be >= 2")
    args.names = names
    args.preset_of = {}
    for item in args.presets:
        name, _, preset = item.partition("=")
        if name not in SEQUENCES or not preset:
            p.error(f"--preset {item}: expected SEQUENCE=PRESET with a sequence of: {', '.join(SEQUENCES)}")
        args.preset_of[name] = preset
    if args.baseline is not None and not (args.baseline / "fgslam" / "__init__.py").is_file():
        p.error(f"--baseline {args.baseline}: not an fgslam source tree (no fgslam/__init__.py)")
    if args.peer is None and os.environ.get(PEER_ENV):
        args.peer = Path(os.environ[PEER_ENV])
    return args


def peer_problem(peer: Optional[Path], scripts: Path) -> Optional[str]:
    """Why the peer cannot run (None: it can)."""
    if peer is None:
        return f"no ORB-SLAM3 peer venv given (--peer PATH or ${PEER_ENV})"
    for path, what in ((peer / "bin" / "python", "its python"), (peer / "orbvoc.txt", "its vocabulary"),
                       (scripts / "run_orbslam3.py", "the peer script")):
        if not path.is_file():
            return f"{path}: {what} is missing"
    return None


def setup_hint(scripts: Path) -> str:
    return (f"create the peer venv (a few minutes, outside the project) with: {scripts / 'setup.sh'} $HOME/orbslam3-peer ; "
            f"then: .venv/bin/python tools/bench_peers.py --peer $HOME/orbslam3-peer (or export {PEER_ENV}=$HOME/orbslam3-peer)")


# ------------------------------------------------------------------------------------ sequences

def highway_root(args: argparse.Namespace) -> Path:
    """Render (or reuse) the synthetic highway clip; returns its root (EuRoC layout)."""
    from fgslam.run.demo import DemoSceneConfig, render_scene
    from fgslam.io.synth.scenarios import default_config

    cam = default_config("highway").camera
    scene = DemoSceneConfig(preset="highway", frames=args.highway_frames, rate_hz=cam.rate_hz, width=cam.width,
                            height=cam.height, seed=args.highway_seed)
    root = args.synth_dir / f"highway_{cam.width}x{cam.height}_{args.highway_frames}_{cam.rate_hz:g}hz_seed{args.highway_seed}"
    render_scene(scene, root)
    return root


def open_dataset(root: Path, preset: str, overrides: list[str]):
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset

    return open_slam_dataset(root, load_slam_config(preset, overrides))


def raw_image_files(root: Path, layout: str, n: int) -> list[Path]:
    """The first ``n`` left / colour image files of a sequence as stored (what the peer's own readers
    take): KITTI ``image_0/*.png``, 7-Scenes ``seq-01/frame-*.color.jpg``, EuRoC ``mav0/cam0/data/*.png``."""
    patterns = {"kitti": ("image_0", "*.png"), "7scenes": ("seq-01", "frame-*.color.*"),
                "euroc": ("mav0/cam0/data", "*.png")}
    folder, pattern = patterns[layout]
    files = sorted((root / folder).glob(pattern))
    if len(files) < n:
        raise FileNotFoundError(f"{root / folder}: {len(files)} images matching {pattern}, {n} needed")
    return files[:n]


def orbslam3_settings(K, width: int, height: int, rate_hz: float, features: int) -> str:
    """A monocular ORB-SLAM3 settings YAML (the peer's format, undistorted pinhole) for intrinsics K."""
    fx, fy, cx, cy = (float(v) for v in K)
    return "\n".join([
        "%YAML:1.0", 'File.version: "1.0"', 'Camera.type: "PinHole"',
        f"Camera1.fx: {fx:.6f}", f"Camera1.fy: {fy:.6f}", f"Camera1.cx: {cx:.6f}", f"Camera1.cy: {cy:.6f}",
        "Camera1.k1: 0.0", "Camera1.k2: 0.0", "Camera1.p1: 0.0", "Camera1.p2: 0.0",
        f"Camera.width: {int(width)}", f"Camera.height: {int(height)}", f"Camera.fps: {int(round(rate_hz))}",
        "Camera.RGB: 1", f"ORBextractor.nFeatures: {int(features)}", "ORBextractor.scaleFactor: 1.2",
        "ORBextractor.nLevels: 8", "ORBextractor.iniThFAST: 20", "ORBextractor.minThFAST: 7",
        "Viewer.KeyFrameSize: 0.1", "Viewer.KeyFrameLineWidth: 1.0", "Viewer.GraphLineWidth: 1.0",
        "Viewer.PointSize: 2.0", "Viewer.CameraSize: 0.15", "Viewer.CameraLineWidth: 2.0",
        "Viewer.ViewpointX: 0.0", "Viewer.ViewpointY: -10.0", "Viewer.ViewpointZ: -0.1", "Viewer.ViewpointF: 2000.0",
    ]) + "\n"


def kitti_view(files: list[Path], times: np.ndarray, out: Path) -> Path:
    """A KITTI-layout folder (``image_0/NNNNNN.png`` links to ``files``, ``times.txt``) for the peer's
    monocular reader; OpenCV reads an image by its content, so a linked JPEG works."""
    (out / "image_0").mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(files):
        link = out / "image_0" / f"{i:06d}.png"
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(Path(f).resolve())
    np.savetxt(out / "times.txt", np.asarray(times, np.float64), fmt="%.9f")
    return out


# ------------------------------------------------------------------------------------ trajectories

def to_dataset_time(peer_t: np.ndarray, fed_t: np.ndarray, dataset_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map the peer's pose stamps to fgslam's timestamps: each stamp is matched to the nearest time
    the peer was fed (frame i; at least two frames) and, when within a quarter of the smallest frame
    period, replaced by ``dataset_t[i]``. Returns (kept mask over ``peer_t``, mapped stamps of the kept)."""
    peer_t, fed_t = np.asarray(peer_t, np.float64), np.asarray(fed_t, np.float64)
    idx = np.clip(np.searchsorted(fed_t, peer_t), 1, len(fed_t) - 1)
    nearest = np.where(peer_t - fed_t[idx - 1] <= fed_t[idx] - peer_t, idx - 1, idx)
    ok = np.abs(fed_t[nearest] - peer_t) <= 0.25 * np.min(np.diff(fed_t))
    return ok, np.asarray(dataset_t, np.float64)[nearest[ok]]


def read_tum(path: Path):
    """A TUM trajectory file as a fgslam Trajectory (None when missing or empty)."""
    from fgslam.io.trajectory import read_trajectory

    if not path.is_file() or not path.read_text().strip():
        return None
    return read_trajectory(path, "tum")


def ate_on_common_frames(gt, est_a, est_b, align: str, max_time_diff: float) -> dict:
    """ATE of ``est_a`` and of ``est_b`` against ``gt`` by fgslam's evaluator with the same ``align``,
    each over only the frames both posed (one-to-one timestamp match within ``max_time_diff``)."""
    from fgslam.core.errors import FGSlamError
    from fgslam.eval.trajectory import EvalConfig, associate_timestamps, evaluate

    out = {"common_frames": 0, "ate_a_m": None, "ate_b_m": None, "ate_a_percent": None, "ate_b_percent": None,
           "scale_a": None, "scale_b": None, "path_m": None, "error": None}
    if est_a is None or est_b is None or len(est_a) == 0 or len(est_b) == 0:
        out["error"] = "a trajectory is empty"
        return out
    try:
        ia, ib = associate_timestamps(est_a.timestamps, est_b.timestamps, max_time_diff)
        a, b = est_a.subset(ia), est_b.subset(ib)
        cfg = EvalConfig(align=align, max_time_diff=max_time_diff, rpe_delta_meters=None)
        ra, rb = evaluate(gt, a, cfg), evaluate(gt, b, cfg)
    except (FGSlamError, ValueError, np.linalg.LinAlgError) as exc:
        out["error"] = f"{type(exc).__name__}: {exc}"
        return out
    path = ra.gt_path_length_m
    out.update(common_frames=int(min(ra.n_matched, rb.n_matched)), ate_a_m=ra.ate.rmse, ate_b_m=rb.ate.rmse,
               scale_a=ra.alignment.s, scale_b=rb.alignment.s, path_m=path,
               ate_a_percent=100.0 * ra.ate.rmse / path if path > 0 else None,
               ate_b_percent=100.0 * rb.ate.rmse / path if path > 0 else None)
    return out


def own_ate(gt, est, align: str, max_time_diff: float) -> Optional[float]:
    """ATE over all the frames one system posed (None when it cannot be evaluated)."""
    from fgslam.core.errors import FGSlamError
    from fgslam.eval.trajectory import EvalConfig, evaluate

    if est is None or len(est) < 3:
        return None
    try:
        return evaluate(gt, est, EvalConfig(align=align, max_time_diff=max_time_diff, rpe_delta_meters=None)).ate.rmse
    except (FGSlamError, ValueError, np.linalg.LinAlgError):
        return None


# ------------------------------------------------------------------------------------ runs

def fgslam_command(preset: str, data: Path, out: Path, overrides: list[str]) -> list[str]:
    cmd = [sys.executable, "-m", "fgslam", "-q", "run", preset, "--data", str(data), "--out", str(out), "--no-progress"]
    for o in overrides:
        cmd += ["-o", o]
    return cmd


def run_fgslam(preset: str, data: Path, out: Path, overrides: list[str], timeout: float,
               tree: Optional[Path] = None) -> dict:
    """One ``fgslam run`` in its own process (the fgslam source tree ``tree``; None: this one): its
    summary figures and trajectory."""
    load = os.getloadavg()
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = str(Path(tree).resolve())
    try:
        proc = subprocess.run(fgslam_command(preset, data, out, overrides), capture_output=True, text=True,
                              cwd=tree or REPO, timeout=timeout, env=env)
        rc, err = proc.returncode, proc.stderr.strip()[-1000:]
    except subprocess.TimeoutExpired:
        rc, err = None, f"stopped after {timeout:.0f} s"
    summary_path = out / "summary.json"
    if not summary_path.is_file():
        return {"error": f"exit {rc}: {err}", "trajectory": None}
    s = json.loads(summary_path.read_text())
    return {"posed": s["frames_with_pose"], "frames": s["frames_processed"], "fps": s["fps"], "cpu_s": s["cpu_s"],
            "read_cpu_s": s.get("read_cpu_s"), "wall_s": s["wall_s"], "keyframes": s["keyframes"], "failures": s["failures"],
            "error": s.get("error") or (None if rc == 0 else f"exit {rc}: {err}"),
            "load_before": [round(v, 2) for v in load], "load_after": [round(v, 2) for v in os.getloadavg()],
            "trajectory": read_tum(out / "trajectory_tum.txt")}


def peer_command(args: argparse.Namespace, mode: str, settings: Path, seq: Path, n: int, out_prefix: Path) -> list[str]:
    cmd = [str(args.peer / "bin" / "python"), str(args.peer_scripts / "run_orbslam3.py"), "--mode", mode,
           "--vocab", str(args.peer / "orbvoc.txt"), "--settings", str(settings), "--seq", str(seq), "--n", str(n),
           "--out", str(out_prefix)]
    return cmd if args.no_pace else cmd + ["--pace"]


def run_peer(cmd: list[str], out_prefix: Path, fed_t: np.ndarray, dataset_t: np.ndarray, timeout: float) -> dict:
    """One ORB-SLAM3 run: its stats and final trajectory mapped to fgslam's timestamps."""
    load = os.getloadavg()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        rc, err = proc.returncode, proc.stderr.strip()[-1000:]
    except subprocess.TimeoutExpired:
        rc, err = None, f"stopped after {timeout:.0f} s"
    stats_path = Path(f"{out_prefix}.json")
    if rc != 0 or not stats_path.is_file():
        return {"error": f"exit {rc}: {err}", "trajectory": None}
    st = json.loads(stats_path.read_text())
    traj = read_tum(Path(f"{out_prefix}.tum"))
    if traj is not None:
        from fgslam.io.trajectory import Trajectory

        # frames lost after the last good one repeat its stamp and pose in ORB-SLAM3's file: kept once
        ok, t = to_dataset_time(traj.timestamps, fed_t, dataset_t)
        t, first = np.unique(t, return_index=True)
        traj = Trajectory(t, traj.T_WC[ok][first]) if ok.any() else None
    return {"posed": 0 if traj is None else len(traj), "online_posed": st.get("online_posed"), "frames": st.get("frames"),
            "fps": st.get("fps"), "cpu_s": st.get("cpu_s"), "states": st.get("states"), "paced": st.get("paced"),
            "error": None, "load_before": [round(v, 2) for v in load],
            "load_after": [round(v, 2) for v in os.getloadavg()], "trajectory": traj}


def _median(values) -> Optional[float]:
    vals = [float(v) for v in values if v is not None]
    return statistics.median(vals) if vals else None


def _ratio(a: Optional[float], b: Optional[float]) -> Optional[float]:
    return a / b if a is not None and b not in (None, 0) else None


def _public(gt, align: str, max_time_diff: float, r: dict) -> dict:
    """A run's figures for the report: its trajectory replaced by its ATE over its own posed frames."""
    d = {k: v for k, v in r.items() if k != "trajectory"}
    d["ate_own_m"] = own_ate(gt, r.get("trajectory"), align, max_time_diff)
    return d


def _per_cpu(runs: list[dict]) -> Optional[float]:
    """Median frames per CPU second (all threads; less sensitive to a shared machine than frames/s)."""
    return _median(r["frames"] / r["cpu_s"] for r in runs if r.get("frames") and r.get("cpu_s"))


def _per_cpu_without_reading(runs: list[dict]) -> Optional[float]:
    """Median frames per CPU second less the reader thread's (image decoding): ORB-SLAM3's runner decodes
    every image before its timed loop, so this is the like-for-like figure."""
    return _median(r["frames"] / (r["cpu_s"] - r["read_cpu_s"]) for r in runs
                   if r.get("frames") and r.get("cpu_s") and r.get("read_cpu_s") is not None
                   and r["cpu_s"] > r["read_cpu_s"])


def compare(gt, align: str, max_time_diff: float, fg_runs: list[dict], peer_runs: list[dict]) -> dict:
    """Per-system medians, every (fgslam run, peer run) pair's common-frame ATE, their medians and ratios."""
    fg = [_public(gt, align, max_time_diff, r) for r in fg_runs]
    pe = [_public(gt, align, max_time_diff, r) for r in peer_runs]
    pairs = []
    for i, a in enumerate(fg_runs):
        for j, b in enumerate(peer_runs):
            c = ate_on_common_frames(gt, a.get("trajectory"), b.get("trajectory"), align, max_time_diff)
            pairs.append({"fgslam_run": i, "orbslam3_run": j, **c})
    good = [p for p in pairs if p["error"] is None]
    common = {
        "frames": _median(p["common_frames"] for p in good),
        "ate_fgslam_m": _median(p["ate_a_m"] for p in good),
        "ate_orbslam3_m": _median(p["ate_b_m"] for p in good),
        "ate_fgslam_percent_of_path": _median(p["ate_a_percent"] for p in good),
        "ate_orbslam3_percent_of_path": _median(p["ate_b_percent"] for p in good),
        "path_m": _median(p["path_m"] for p in good),
        "pairs": pairs,
    }
    fg_fps, pe_fps = _median(r.get("fps") for r in fg), _median(r.get("fps") for r in pe)
    fg_cpu, pe_cpu = _per_cpu(fg), _per_cpu(pe)
    fg_cpu_tracking = _per_cpu_without_reading(fg)
    return {
        "fgslam": {"posed": _median(r.get("posed") for r in fg), "fps": fg_fps, "frames_per_cpu_s": fg_cpu,
                   "frames_per_cpu_s_without_reading": fg_cpu_tracking,
                   "cpu_s": _median(r.get("cpu_s") for r in fg), "ate_own_m": _median(r["ate_own_m"] for r in fg),
                   "runs": fg},
        "orbslam3": {"posed": _median(r.get("posed") for r in pe), "fps": pe_fps, "frames_per_cpu_s": pe_cpu,
                     "cpu_s": _median(r.get("cpu_s") for r in pe), "ate_own_m": _median(r["ate_own_m"] for r in pe),
                     "runs": pe},
        "common": common,
        "ratios": {"ate_fgslam_over_orbslam3": _ratio(common["ate_fgslam_m"], common["ate_orbslam3_m"]),
                   "fps_fgslam_over_orbslam3": _ratio(fg_fps, pe_fps),
                   "frames_per_cpu_s_fgslam_over_orbslam3": _ratio(fg_cpu, pe_cpu),
                   "frames_per_cpu_s_without_reading_fgslam_over_orbslam3": _ratio(fg_cpu_tracking, pe_cpu)},
    }


def run_sequence(name: str, args: argparse.Namespace, work: Path,
                 fgslam_runner: Callable[..., dict] = run_fgslam, peer_runner: Callable[..., dict] = run_peer) -> dict:
    """Every run of one sequence and their comparison."""
    seq = SEQUENCES[name]
    root = highway_root(args) if seq.data == SYNTH else args.data / seq.data
    dataset = open_dataset(root, seq.preset, args.overrides)
    gt = dataset.groundtruth
    if gt is None:
        return {"sequence": name, "error": f"{root}: no ground truth"}
    n = len(dataset)
    dataset_t = np.asarray(dataset.timestamps, np.float64)
    rate = float(dataset.rate)
    max_time_diff = 0.25 / rate
    work.mkdir(parents=True, exist_ok=True)
    if seq.mode == "rgbd":
        peer_seq, fed_t = root, np.arange(n) / rate  # the peer reads the 7-Scenes folder at i / 30 s
    else:
        # stamps from 0: ORB-SLAM3 writes its trajectory's nanoseconds with 6 significant digits
        files = raw_image_files(root, seq.layout, n)
        fed_t = dataset_t - dataset_t[0]
        peer_seq = kitti_view(files, fed_t, work / "peer_view")
    if seq.settings is not None:
        settings = args.peer_scripts / "settings" / seq.settings
    else:  # generated from fgslam's calibration of the images as stored (synthetic: no distortion)
        cal = dataset.calibration
        h, w = cv2.imread(str(files[0]), cv2.IMREAD_GRAYSCALE).shape
        if (w, h) != (cal.width, cal.height) or cal.distortion_model != "none" and np.any(cal.distortion):
            return {"sequence": name, "error": f"{root}: the calibration is not that of the stored {w}x{h} images"}
        settings = work / "orbslam3_settings.yaml"
        settings.write_text(orbslam3_settings(cal.K, cal.width, cal.height, rate, seq.orb_features))
    preset = args.preset_of.get(name, seq.preset)
    fg_runs, base_runs, peer_runs = [], [], []
    for i in range(max(args.fgslam_repeats, args.repeats)):  # alternating: every side sees the same load
        if i < args.fgslam_repeats:
            fg_runs.append(fgslam_runner(preset, root, work / f"fgslam_{i}", args.overrides, args.timeout))
            if args.baseline is not None:
                base_runs.append(fgslam_runner(preset, root, work / f"baseline_{i}", args.overrides, args.timeout,
                                               tree=args.baseline))
        if i < args.repeats:
            peer_runs.append(peer_runner(peer_command(args, seq.mode, settings, peer_seq, n, work / f"orbslam3_{i}"),
                                         work / f"orbslam3_{i}", fed_t, dataset_t, args.timeout))
    result = {"sequence": name, "data": str(root), "mode": seq.mode, "align": ALIGN[seq.mode], "frames": n,
              "rate_hz": rate, "fgslam_preset": preset, "orbslam3_settings": str(settings),
              "orbslam3_paced": not args.no_pace}
    result.update(compare(gt, ALIGN[seq.mode], max_time_diff, fg_runs, peer_runs))
    if base_runs:
        result["baseline"] = baseline_comparison(gt, ALIGN[seq.mode], max_time_diff, fg_runs, base_runs, args.baseline)
    return result


def baseline_comparison(gt, align: str, max_time_diff: float, fg_runs: list[dict], base_runs: list[dict],
                        tree: Path) -> dict:
    """The baseline tree's medians and this tree's ratios to them (frames per CPU second above 1: faster)."""
    runs = [_public(gt, align, max_time_diff, r) for r in base_runs]
    ate_new = _median(own_ate(gt, r.get("trajectory"), align, max_time_diff) for r in fg_runs)
    ate_base = _median(r["ate_own_m"] for r in runs)
    return {"tree": str(tree), "posed": _median(r.get("posed") for r in runs), "fps": _median(r.get("fps") for r in runs),
            "frames_per_cpu_s": _per_cpu(runs), "ate_own_m": ate_base, "runs": runs,
            "ratios": {"frames_per_cpu_s_new_over_baseline": _ratio(_per_cpu(fg_runs), _per_cpu(runs)),
                       "ate_new_over_baseline": _ratio(ate_new, ate_base)}}


def main(argv=None, fgslam_runner: Callable[..., dict] = run_fgslam, peer_runner: Callable[..., dict] = run_peer) -> int:
    args = parse_args(argv)
    if args.list:
        for name, s in SEQUENCES.items():
            print(f"{name:14s} {s.preset:22s} {s.data:28s} {s.mode} ({ALIGN[s.mode]})")
        return 0
    problem = peer_problem(args.peer, args.peer_scripts)
    if problem is not None:
        hint = setup_hint(args.peer_scripts)
        print(f"bench_peers: {problem}; {hint}", file=sys.stderr)
        print(json.dumps({"benchmark": "fgslam vs ORB-SLAM3", "skipped": problem, "how_to_create_the_peer": hint}))
        return 0
    work = args.keep_outputs or Path(tempfile.mkdtemp(prefix="bench_peers_"))
    t0 = time.perf_counter()
    results = {}
    try:
        for name in args.names:
            results[name] = run_sequence(name, args, work / name, fgslam_runner, peer_runner)
    finally:
        if args.keep_outputs is None:
            shutil.rmtree(work, ignore_errors=True)
    report = {
        "benchmark": "fgslam vs ORB-SLAM3 (same frames, same evaluator)",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "peer": str(args.peer), "repeats": args.repeats, "fgslam_repeats": args.fgslam_repeats,
        "overrides": args.overrides, "total_s": time.perf_counter() - t0,
        "load_average_end": [round(v, 2) for v in os.getloadavg()],
        "sequences": results,
    }
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
