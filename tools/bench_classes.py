"""The class benchmark: every candidate preset on every sensor class it can reproduce, ORB-SLAM3 side
by side; it chooses the recommended presets and generates the README's preset table. Prints JSON.

A sensor class (``CLASSES``) is what a user knows about their camera (hand-held RGB-D, a car's
stereo rig, ...) and names one recommended preset (``handheld_rgbd``, ``driving_stereo``, ...). Its
cases (``CLIPS``) are the shared real clips of that class and reproductions of the held-out classes
(``../shared/findings/held-out-runs.md``): synthetic renders (``fgslam synth``) and the clips
degraded the way real cameras degrade them: strided (faster motion between frames), brightness-varied
(auto-exposure: a slowly drifting gain per camera, each camera its own, clipped at white).

Candidates of a class: every shipped run preset of the class's sensor (``fgslam run --help``) of the
families in ``--families`` (default ``patch,pointmap``; the dense family runs at 2.7-3.1 frames per
CPU second on these clips, below every class's live floor: ``--families patch,pointmap,dense`` adds
it), except presets that need another input (IMU, GPS, a network checkpoint) or a planar vehicle.

Ranking (``rank_class``): a candidate's case score is its ATE over the best ATE any candidate reached
on that case, times ``1 + UNPOSED_WEIGHT x`` its share of frames without a pose; a run that fails or
cannot be evaluated scores ``FAILED_SCORE``. The class score is the geometric mean over the class's
cases. A candidate whose median frames per CPU second falls below the class's live floor (the
clips' camera rate over ``LIVE_CORES`` cores: it could not keep up with the camera on a 2-core
machine) ranks after every candidate that keeps up. The recommended preset must rank first
(``recommended_is_best``); the README table (between ``TABLE_BEGIN`` and ``TABLE_END``) is written
from the report by ``--readme``, and ``--from REPORT`` rewrites it without running anything.

ORB-SLAM3 (GPL-3, a peer in its own venv: ``../shared/peers/orbslam3/setup.sh PEER``; ``--peer PEER``
or ``FGSLAM_ORBSLAM3_PEER``) runs ``--repeats`` times per case fed at camera rate, evaluated by
fgslam's evaluator against the same ground truth with the same alignment (Sim(3) monocular, SE(3)
stereo and RGB-D), each system over its own posed frames. Without the peer its columns are empty.

Usage:
  .venv/bin/python tools/bench_classes.py --peer $HOME/orbslam3-peer [--classes driving_stereo,...] \
      [--families patch,pointmap] [--work DIR] [--readme README.md] > classes.json
  .venv/bin/python tools/bench_classes.py --from docs/benchmarks/classes.json --readme README.md \
      --details docs/benchmarks/classes.md
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from bench_run import DEFAULT_DATA, REPO

# ------------------------------------------------------------------------------------ classes and clips


@dataclass(frozen=True)
class Clip:
    """One case's data: a shared folder (``shared:<folder>``) or a synthetic render (``synth:<preset>``),
    the first ``frames`` frames (synthetic: rendered), every ``stride``-th, and, when ``brightness`` > 0,
    auto-exposure: each camera's log gain drifts by this amplitude (seeded by ``seed``)."""

    source: str
    frames: int
    stride: int = 1
    brightness: float = 0.0
    seed: int = 0
    size: str = ""                   # synthetic: WxH
    synth: tuple[str, ...] = ()      # synthetic: ``fgslam synth -o`` overrides
    rate_hz: float = 10.0            # the camera rate of the stored frames (before the stride)
    what: str = ""                   # what the clip reproduces, for the table


@dataclass(frozen=True)
class SensorClass:
    preset: str                      # the recommended preset of the class
    sensor: str                      # mono | stereo | rgbd
    who: str                         # the README's "your sensor and motion"
    clips: tuple[str, ...]


#: A real road at about 1 m per frame: KITTI's image size and field of view, few near features (most
#: guard-rail segments and poles left out), fine road texture that the 376 px tracking image aliases.
_ROAD = ("highway.speed=10", "highway.rail_gap_prob=0.8", "highway.ground_density=4", "highway.pole_spacing=120")
_SEVEN = "shared:7scenes_redkitchen_0-599"
_KITTI = "shared:kitti00_0-199"

CLIPS: dict[str, Clip] = {
    "kitti00": Clip(_KITTI, 200, what="KITTI 00 0-199 (urban, 145 m)"),
    "kitti00_stride2_bright": Clip(_KITTI, 200, stride=2, brightness=0.3, seed=1,
                                   what="KITTI 00 every 2nd frame with auto-exposure (2 m a frame, highway speed)"),
    "road_stereo_bright": Clip("synth:highway", 51, brightness=0.3, seed=0, size="1241x376", synth=_ROAD,
                               what="real-road stereo render, 1 m a frame, few near features, auto-exposure"),
    "road_stereo": Clip("synth:highway", 51, size="1241x376", synth=_ROAD, what="the same road, steady exposure"),
    "street_stereo_bright": Clip("synth:street-loop", 120, brightness=0.3, seed=2, size="640x200",
                                 what="urban stereo render (street loop), auto-exposure"),
    "7scenes": Clip(_SEVEN, 600, rate_hz=30.0, what="7-Scenes kitchen 0-599"),
    "7scenes_stride3_bright": Clip(_SEVEN, 600, stride=3, brightness=0.3, seed=3, rate_hz=30.0,
                                   what="7-Scenes kitchen every 3rd frame (10 Hz) with auto-exposure"),
    "sweep": Clip("synth:rotation-sweep", 240, size="320x240", rate_hz=30.0,
                  what="rotation-dominant sweep, 30 Hz, strong radial distortion, motion blur"),
    "sweep_bright": Clip("synth:rotation-sweep", 240, brightness=0.3, seed=4, size="320x240", rate_hz=30.0,
                         what="the sweep with auto-exposure"),
    "panel_room": Clip("synth:panel-room", 189, size="320x240",
                       what="texture-poor room (near-white panels), point light"),
    "room_stereo": Clip("synth:room-loop", 200, size="640x480", rate_hz=20.0,
                        what="hand-held stereo in a textured room (EuRoC-like, 11 cm baseline)"),
    "room_stereo_bright": Clip("synth:room-loop", 200, brightness=0.3, seed=5, size="640x480", rate_hz=20.0,
                               what="the same with auto-exposure"),
}

CLASSES: dict[str, SensorClass] = {
    "handheld_rgbd": SensorClass("handheld_rgbd", "rgbd", "hand-held RGB-D camera (Kinect, RealSense; 15-30 Hz colour + depth)",
                                 ("7scenes", "7scenes_stride3_bright", "sweep", "panel_room")),
    "handheld_mono": SensorClass("handheld_mono", "mono", "hand-held monocular video (phone, webcam; 10-30 Hz; scale arbitrary)",
                                 ("7scenes", "7scenes_stride3_bright", "sweep", "sweep_bright")),
    "handheld_stereo": SensorClass("handheld_stereo", "stereo", "hand-held or drone global-shutter stereo (EuRoC-like, ~10 cm baseline)",
                                   ("room_stereo", "room_stereo_bright")),
    "driving_mono": SensorClass("driving_mono", "mono", "car, one forward camera (KITTI-like, 10 Hz; scale arbitrary)",
                                ("kitti00", "kitti00_stride2_bright", "road_stereo_bright")),
    "driving_stereo": SensorClass("driving_stereo", "stereo", "car, forward stereo rig (KITTI-like, ~0.5 m baseline, 10 Hz)",
                                  ("road_stereo_bright", "road_stereo", "street_stereo_bright")),
}

ALIGN = {"mono": "sim3", "stereo": "se3", "rgbd": "se3"}
#: candidates left out: they need another input (IMU, GPS, a checkpoint) or assume planar motion
EXCLUDED_MARKS = ("inertial", "learned", "gps", "planar")
UNPOSED_WEIGHT = 10.0   # a case score grows by this times the share of frames without a pose (10 %: x2)
FAILED_SCORE = 100.0    # a run that failed or could not be evaluated
PEER_DEPTH_FACTOR = 1000.0  # depth PNG units per metre written for the peer (millimetres, as 7-Scenes)
LIVE_CORES = 2          # the live floor: the camera rate over this many cores, in frames per CPU second
TABLE_BEGIN = "<!-- preset table: generated by tools/bench_classes.py --readme; do not edit -->"
TABLE_END = "<!-- end of the generated preset table -->"
DETAILS_BEGIN = "<!-- class results: generated by tools/bench_classes.py --details; do not edit -->"
DETAILS_END = "<!-- end of the generated class results -->"


# ------------------------------------------------------------------------------------ candidates

def preset_sensor_and_family(name: str) -> tuple[str, str]:
    from fgslam.run.config import load_slam_config

    cfg = load_slam_config(name, [])
    return cfg.sensor, cfg.frontend


def config_digest(name: str) -> str:
    """A digest of the preset's resolved config (every field, defaults included): the report is
    stale when a preset or a default it takes has changed since it was measured."""
    from fgslam.core.config import to_dict
    from fgslam.run.config import load_slam_config

    text = json.dumps(to_dict(load_slam_config(name, [])), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def candidates(cls: SensorClass, families: tuple[str, ...]) -> list[str]:
    """Shipped run presets of the class's sensor and one of ``families`` (the recommended one first)."""
    from fgslam.run.presets import run_presets

    out = []
    for name in run_presets():
        if any(mark in name for mark in EXCLUDED_MARKS):
            continue
        sensor, family = preset_sensor_and_family(name)
        if sensor == cls.sensor and family in families:
            out.append(name)
    out.sort(key=lambda n: (n != cls.preset, n))
    return out


# ------------------------------------------------------------------------------------ data

def _gains(n: int, amplitude: float, rng: np.random.Generator, phase: float) -> np.ndarray:
    """Auto-exposure gains of one camera over ``n`` frames: a slow wave of the log gain (30 frames a
    period) plus a random walk, zero-mean over the clip."""
    t = np.arange(n)
    log_gain = amplitude * np.sin(2 * np.pi * t / 30.0 + phase) + np.cumsum(rng.normal(0.0, amplitude / 4, n))
    return np.exp(log_gain - log_gain.mean())


IMAGE_FOLDERS = {  # layout -> folders of the images the gains apply to (one camera each)
    "kitti": ("image_0", "image_1"),
    "euroc": ("mav0/cam0/data", "mav0/cam1/data"),
    "7scenes": ("seq-01",),
}
IMAGE_PATTERN = {"kitti": "*.png", "euroc": "*.png", "7scenes": "frame-*.color.*"}


def layout_of(root: Path) -> str:
    if (root / "mav0").is_dir():
        return "euroc"
    if (root / "image_0").is_dir():
        return "kitti"
    if (root / "seq-01").is_dir():
        return "7scenes"
    raise FileNotFoundError(f"{root}: not a KITTI, EuRoC or 7-Scenes layout")


def brightness_view(src: Path, dst: Path, amplitude: float, seed: int) -> Path:
    """A copy of sequence ``src`` at ``dst`` whose images carry auto-exposure (``_gains``, each camera
    its own phase and walk, clipped to 8 bits); every other file is a link to the original."""
    layout = layout_of(src)
    if dst.exists():
        shutil.rmtree(dst)
    rng = np.random.default_rng(seed)
    image_dirs = [src / f for f in IMAGE_FOLDERS[layout] if (src / f).is_dir()]
    for path in sorted(src.rglob("*")):
        rel = path.relative_to(src)
        if path.is_dir():
            (dst / rel).mkdir(parents=True, exist_ok=True)
        elif not any(path.parent == d and path.match(IMAGE_PATTERN[layout]) for d in image_dirs):
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            (dst / rel).symlink_to(path.resolve())
    for cam, folder in enumerate(image_dirs):
        files = sorted(folder.glob(IMAGE_PATTERN[layout]))
        for f, gain in zip(files, _gains(len(files), amplitude, rng, phase=float(cam))):
            image = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            out = np.clip(image.astype(np.float32) * gain, 0, 255).astype(np.uint8)
            cv2.imwrite(str(dst / f.relative_to(src)), out)
    return dst


def clip_root(clip: Clip, data: Path, work: Path) -> Path:
    """The folder of a clip (rendered and degraded once into ``work``, reused after)."""
    kind, name = clip.source.split(":", 1)
    if kind == "shared":
        root = data / name
        if not root.is_dir():
            raise FileNotFoundError(f"{root}: shared data missing")
    else:
        tag = "_".join([name, clip.size, str(clip.frames), *clip.synth]).replace("=", "-").replace(".", "")
        root = work / "renders" / tag
        if not (root / "mav0").is_dir():
            width, height = clip.size.split("x")
            cmd = [sys.executable, "-m", "fgslam", "-q", "synth", "--preset", name, "--out", str(root),
                   "--frames", str(clip.frames), "--width", width, "--height", height]
            for o in clip.synth:
                cmd += ["-o", o]
            subprocess.run(cmd, check=True, cwd=REPO, capture_output=True)
    if clip.brightness > 0:
        view = work / "views" / f"{root.name}_bright{clip.brightness:g}_seed{clip.seed}"
        if not view.is_dir():
            brightness_view(root, view, clip.brightness, clip.seed)
        root = view
    return root


def clip_overrides(clip: Clip) -> list[str]:
    return [f"dataset.end={clip.frames}", f"dataset.stride={clip.stride}"]


# ------------------------------------------------------------------------------------ scoring

def rank_class(cases: dict[str, dict[str, dict]], live_floor: float, prefer: str = "") -> list[dict]:
    """The candidates of one class, best first (module docstring): ``cases`` maps case -> preset ->
    {"ate_m", "posed", "frames", "frames_per_cpu_s"} (``ate_m`` None: failed). Equal scores: ``prefer``
    (the recommended preset: a tie is not a loss) first, then by name."""
    presets = sorted({p for runs in cases.values() for p in runs})
    scores: dict[str, list[float]] = {p: [] for p in presets}
    speeds: dict[str, list[float]] = {p: [] for p in presets}
    for runs in cases.values():
        ates = [r["ate_m"] for r in runs.values() if r.get("ate_m") is not None and r["ate_m"] > 0]
        best = min(ates) if ates else None
        for p in presets:
            r = runs.get(p) or {}
            if r.get("frames_per_cpu_s") is not None:
                speeds[p].append(r["frames_per_cpu_s"])
            if best is None or r.get("ate_m") is None or not r.get("frames"):
                scores[p].append(FAILED_SCORE)
                continue
            unposed = 1.0 - r["posed"] / r["frames"]
            scores[p].append(max(r["ate_m"], best) / best * (1.0 + UNPOSED_WEIGHT * unposed))
    out = []
    for p in presets:
        score = math.exp(statistics.fmean(math.log(s) for s in scores[p])) if scores[p] else FAILED_SCORE
        speed = statistics.median(speeds[p]) if speeds[p] else 0.0
        out.append({"preset": p, "score": round(score, 4), "frames_per_cpu_s": round(speed, 2),
                    "live": speed >= live_floor})
    out.sort(key=lambda r: (not r["live"], r["score"], r["preset"] != prefer, r["preset"]))
    return out


# ------------------------------------------------------------------------------------ runs

def evaluate_run(run: dict, gt, align: str, max_time_diff: float) -> dict:
    import bench_peers

    ate = bench_peers.own_ate(gt, run.get("trajectory"), align, max_time_diff)
    frames, cpu = run.get("frames"), run.get("cpu_s")
    return {"ate_m": ate, "posed": run.get("posed", 0), "frames": frames,
            "frames_per_cpu_s": frames / cpu if frames and cpu else None,
            "failures": (run.get("failures") or {}).get("tracking"), "keyframes": run.get("keyframes"),
            "error": run.get("error")}


def peer_view(root: Path, clip: Clip, sensor: str, dataset, work: Path) -> tuple[Path, np.ndarray]:
    """The folder the peer reads (KITTI layout for mono and stereo, 7-Scenes layout for RGB-D) with the
    clip's frames (stride applied) and the times they are fed at."""
    import bench_peers

    layout = layout_of(root)
    n = len(dataset)
    idx = np.arange(0, clip.frames, clip.stride)[:n]
    t = np.asarray(dataset.timestamps, np.float64)
    fed_t = t - t[0]
    view = work / "peer_view"
    if view.exists():
        shutil.rmtree(view)
    if sensor == "rgbd":
        (view / "seq-01").mkdir(parents=True)
        colour = sorted((root / IMAGE_FOLDERS[layout][0]).glob(IMAGE_PATTERN[layout]))
        depth_dir = root / ("mav0/depth0/data" if layout == "euroc" else "seq-01")
        depth = sorted(depth_dir.glob("*.png" if layout == "euroc" else "frame-*.depth.png"))
        for i, k in enumerate(idx):
            (view / "seq-01" / f"frame-{i:06d}.color.jpg").symlink_to(colour[k].resolve())
            (view / "seq-01" / f"frame-{i:06d}.depth.png").symlink_to(depth[k].resolve())
        return view, np.arange(n) / 30.0  # the peer's RGB-D reader feeds 7-Scenes frames at 30 Hz
    left = sorted((root / IMAGE_FOLDERS[layout][0]).glob(IMAGE_PATTERN[layout]))
    bench_peers.kitti_view([left[k] for k in idx], fed_t, view)
    if sensor == "stereo":
        right = sorted((root / IMAGE_FOLDERS[layout][1]).glob(IMAGE_PATTERN[layout]))
        (view / "image_1").mkdir()
        for i, k in enumerate(idx):
            (view / "image_1" / f"{i:06d}.png").symlink_to(right[k].resolve())
    return view, fed_t


def undistorted_peer_view(dataset, sensor: str, work: Path) -> tuple[Path, np.ndarray]:
    """The peer's folder written from the loader's undistorted (pinhole) frames, for clips whose stored
    images are distorted (the peer's settings here are pinhole)."""
    view = work / "peer_view"
    if view.exists():
        shutil.rmtree(view)
    t = np.asarray(dataset.timestamps, np.float64)
    for frame in dataset:
        i = frame.index
        if sensor == "rgbd":
            (view / "seq-01").mkdir(parents=True, exist_ok=True)
            colour = frame.image if frame.rgb is None else cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)
            cv2.imwrite(str(view / "seq-01" / f"frame-{i:06d}.color.jpg"), colour, [cv2.IMWRITE_JPEG_QUALITY, 98])
            depth_mm = np.clip(np.nan_to_num(frame.depth) * PEER_DEPTH_FACTOR, 0, np.iinfo(np.uint16).max)
            cv2.imwrite(str(view / "seq-01" / f"frame-{i:06d}.depth.png"), depth_mm.astype(np.uint16))
        else:
            (view / "image_0").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(view / "image_0" / f"{i:06d}.png"), frame.image)
            if sensor == "stereo":
                (view / "image_1").mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(view / "image_1" / f"{i:06d}.png"), frame.image_right)
    if sensor == "rgbd":
        return view, np.arange(len(t)) / 30.0
    np.savetxt(view / "times.txt", t - t[0], fmt="%.9f")
    return view, t - t[0]


def peer_settings(cal, sensor: str, rate: float, out: Path) -> Path:
    """ORB-SLAM3 settings (pinhole, as the peer's wheel needs) for images of calibration ``cal``."""
    import bench_peers

    text = bench_peers.orbslam3_settings(cal.K, cal.width, cal.height, rate, 2000 if sensor != "rgbd" else 1000)
    if sensor == "stereo":
        fx, fy, cx, cy = (float(v) for v in cal.K)
        baseline = float(abs(cal.baseline))
        text += "\n".join([f"Camera2.fx: {fx:.6f}", f"Camera2.fy: {fy:.6f}", f"Camera2.cx: {cx:.6f}",
                           f"Camera2.cy: {cy:.6f}", "Camera2.k1: 0.0", "Camera2.k2: 0.0", "Camera2.p1: 0.0",
                           "Camera2.p2: 0.0", "Stereo.ThDepth: 35.0", "Stereo.T_c1_c2: !!opencv-matrix",
                           "  rows: 4", "  cols: 4", "  dt: f",
                           f"  data: [1.0, 0.0, 0.0, {baseline:.6f}, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, "
                           "0.0, 0.0, 0.0, 1.0]"]) + "\n"
    elif sensor == "rgbd":
        text += f"Stereo.ThDepth: 40.0\nStereo.b: 0.07\nRGBD.DepthMapFactor: {PEER_DEPTH_FACTOR:.1f}\n"
    out.write_text(text)
    return out


def run_case(name: str, clip: Clip, sensor: str, presets: list[str], args: argparse.Namespace) -> dict:
    import bench_peers

    work = args.work / "runs" / f"{name}_{sensor}"
    work.mkdir(parents=True, exist_ok=True)
    root = clip_root(clip, args.data, args.work)
    overrides = clip_overrides(clip)
    dataset = bench_peers.open_dataset(root, presets[0], overrides)
    gt = dataset.groundtruth
    rate = float(dataset.rate)
    max_time_diff = 0.25 / rate
    align = ALIGN[sensor]
    result = {"clip": asdict(clip), "root": str(root), "frames": len(dataset), "rate_hz": rate, "align": align,
              "fgslam": {}, "orbslam3": None}
    for preset in presets:
        out = work / Path(preset).stem
        shutil.rmtree(out, ignore_errors=True)  # a summary left by an earlier run must not be read as this one's
        run = bench_peers.run_fgslam(preset, root, out, overrides, args.timeout)
        result["fgslam"][preset] = evaluate_run(run, gt, align, max_time_diff)
        print(f"bench_classes: {name} {sensor} {preset}: {result['fgslam'][preset]}", file=sys.stderr, flush=True)
    if args.peer is not None:
        result["orbslam3"] = run_peer_case(root, clip, sensor, dataset, gt, rate, work, args)
    return result


def run_peer_case(root: Path, clip: Clip, sensor: str, dataset, gt, rate: float, work: Path,
                  args: argparse.Namespace) -> dict:
    import bench_peers

    raw = dataset.raw_calibration
    if raw.distortion_model != "none" and np.any(raw.distortion):  # the peer gets the loader's undistorted frames
        view, fed_t = undistorted_peer_view(dataset, sensor, work)
        settings = peer_settings(dataset.calibration, sensor, rate, work / "orbslam3_settings.yaml")
    else:
        view, fed_t = peer_view(root, clip, sensor, dataset, work)
        settings = peer_settings(raw, sensor, rate, work / "orbslam3_settings.yaml")
    dataset_t = np.asarray(dataset.timestamps, np.float64)
    runs = []
    for j in range(args.repeats):
        cmd = bench_peers.peer_command(args, sensor, settings, view, len(dataset), work / f"orbslam3_{j}")
        run = bench_peers.run_peer(cmd, work / f"orbslam3_{j}", fed_t, dataset_t, args.timeout)
        runs.append(evaluate_run(run, gt, ALIGN[sensor], 0.25 / rate))
    ates = [r["ate_m"] for r in runs if r["ate_m"] is not None]
    return {"ate_m": statistics.median(ates) if ates else None,
            "posed": statistics.median([r["posed"] for r in runs]), "frames": len(dataset),
            "frames_per_cpu_s": statistics.median([r["frames_per_cpu_s"] for r in runs if r["frames_per_cpu_s"]] or [0.0]),
            "runs": runs}


def add_peer(name: str, cls: SensorClass, saved: dict, args: argparse.Namespace) -> dict:
    """``--peer-only``: the saved class report with ORB-SLAM3 run on the clips it has no result on."""
    import bench_peers

    for clip_name, case in saved["cases"].items():
        peer = case.get("orbslam3") or {}
        if peer.get("ate_m") is not None:
            continue
        clip = CLIPS[clip_name]
        root = clip_root(clip, args.data, args.work)
        dataset = bench_peers.open_dataset(root, cls.preset, clip_overrides(clip))
        work = args.work / "runs" / f"{clip_name}_{cls.sensor}"
        work.mkdir(parents=True, exist_ok=True)
        case["orbslam3"] = run_peer_case(root, clip, cls.sensor, dataset, dataset.groundtruth, float(dataset.rate), work, args)
        print(f"bench_classes: {clip_name} {cls.sensor} ORB-SLAM3: {case['orbslam3'].get('ate_m')}", file=sys.stderr)
    return saved


# ------------------------------------------------------------------------------------ report and table

def class_report(name: str, cls: SensorClass, cases: dict[str, dict]) -> dict:
    rate = min(cases[c]["rate_hz"] for c in cases)
    floor = rate / LIVE_CORES
    ranking = rank_class({c: cases[c]["fgslam"] for c in cases}, floor, prefer=cls.preset)
    return {"preset": cls.preset, "sensor": cls.sensor, "who": cls.who, "live_floor_frames_per_cpu_s": floor,
            "ranking": ranking, "best": ranking[0]["preset"] if ranking else None,
            "recommended_is_best": bool(ranking) and ranking[0]["preset"] == cls.preset, "cases": cases}


def _fmt(v: Optional[float], unit: str = " m") -> str:
    return "-" if v is None else f"{v:.3f}{unit}"


def table(report: dict) -> str:
    """The README's preset table, from a report."""
    lines = [TABLE_BEGIN, "",
             "| your sensor and motion | preset | ranked | per case: ATE of the preset / ORB-SLAM3 (frames posed) |",
             "|---|---|---|---|"]
    for name, c in report["classes"].items():
        rank = next((i for i, r in enumerate(c["ranking"]) if r["preset"] == c["preset"]), None)
        runner = next((r for r in c["ranking"] if r["preset"] != c["preset"]), None)
        ranked = (f"{'1st' if rank == 0 else f'#{rank + 1}'} of {len(c['ranking'])}"
                  + (f" (next: {runner['preset']}, {runner['score']:.2f}x)" if runner else ""))
        cells = []
        for case, r in c["cases"].items():
            mine = r["fgslam"].get(c["preset"], {})
            peer = r.get("orbslam3") or {}
            posed = f"{mine.get('posed', 0)}/{r['frames']}"
            peer_txt = _fmt(peer.get("ate_m")) + (f" ({int(peer['posed'])}/{r['frames']})" if peer.get("ate_m") is not None else "")
            cells.append(f"{case}: {_fmt(mine.get('ate_m'))} ({posed}) / {peer_txt}")
        lines.append(f"| {c['who']} | `{c['preset']}` | {ranked} | {'; '.join(cells)} |")
    lines += ["", f"Measured by `tools/bench_classes.py` ({report['machine']['cpus']} cores, load "
              f"{report['load_average_start'][0]:.1f} at the start); the clips: docs/benchmarks/classes.md.", "",
              TABLE_END]
    return "\n".join(lines)


def details(report: dict) -> str:
    """Every candidate of every class on every clip (ATE, frames posed), its score and frames per CPU
    second, and ORB-SLAM3's row: the benchmark page's generated part."""
    lines = [DETAILS_BEGIN, ""]
    for name, c in report["classes"].items():
        clips = list(c["cases"])
        lines += [f"### `{name}` ({c['sensor']}; live floor {c['live_floor_frames_per_cpu_s']:g} frames per CPU s)", "",
                  "| preset | score | frames per CPU s | " + " | ".join(clips) + " |",
                  "|---|---|---|" + "---|" * len(clips)]
        for r in c["ranking"]:
            cells = []
            for clip in clips:
                run = c["cases"][clip]["fgslam"].get(r["preset"], {})
                cells.append(f"{_fmt(run.get('ate_m'))} ({run.get('posed', 0)}/{c['cases'][clip]['frames']})")
            slow = "" if r["live"] else " (below the floor)"
            name_cell = f"**`{r['preset']}`**" if r["preset"] == c["preset"] else f"`{r['preset']}`"
            lines.append(f"| {name_cell} | {r['score']:.2f} | {r['frames_per_cpu_s']:.1f}{slow} | " + " | ".join(cells) + " |")
        peer = []
        for clip in clips:
            p = c["cases"][clip].get("orbslam3") or {}
            peer.append(f"{_fmt(p.get('ate_m'))} ({int(p['posed'])}/{c['cases'][clip]['frames']})"
                        if p.get("ate_m") is not None else "-")
        lines += ["| ORB-SLAM3 (median of runs) | | | " + " | ".join(peer) + " |", ""]
    lines.append(DETAILS_END)
    return "\n".join(lines)


def _replace_between(path: Path, begin: str, end: str, body: str) -> None:
    text = path.read_text()
    if begin not in text or end not in text:
        raise SystemExit(f"bench_classes: {path} has no generated-table markers ({begin!r} ... {end!r})")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    path.write_text(head + body + tail)


def write_readme(readme: Path, report: dict) -> None:
    _replace_between(readme, TABLE_BEGIN, TABLE_END, table(report))


def write_details(page: Path, report: dict) -> None:
    _replace_between(page, DETAILS_BEGIN, DETAILS_END, details(report))


# ------------------------------------------------------------------------------------ main

def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--classes", default=",".join(CLASSES), help="comma-separated subset of: " + ", ".join(CLASSES))
    p.add_argument("--families", default="patch,pointmap", help="frontend families of the candidates")
    p.add_argument("--presets", default="",
                   help="comma-separated candidates instead (the recommended one is always in); with --update: "
                        "rerun just these inside the saved classes, keeping the other candidates' runs")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    p.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "fgslam_bench_classes",
                   help="renders, degraded views and run outputs (reused between runs)")
    p.add_argument("--peer", type=Path, default=os.environ.get("FGSLAM_ORBSLAM3_PEER"), help="ORB-SLAM3 peer venv")
    p.add_argument("--peer-scripts", type=Path, default=REPO.parent / "shared" / "peers" / "orbslam3")
    p.add_argument("--repeats", type=int, default=3, help="ORB-SLAM3 runs per case (median)")
    p.add_argument("--no-pace", action="store_true", help="feed ORB-SLAM3 as fast as it takes frames")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds after which one run is stopped")
    p.add_argument("--from", dest="from_report", type=Path, default=None, help="a saved report: no runs")
    p.add_argument("--refresh-digests", metavar="REASON", default=None,
                   help="with --update REPORT, no runs: record the presets' config digests as they are now, with "
                        "REASON in the report's updates (only for a config change that computes the same: a "
                        "removed key no preset set, a renamed one); any other change needs the runs")
    p.add_argument("--update", type=Path, default=None,
                   help="a saved report: rerun only --classes and keep its other classes (written back to the file)")
    p.add_argument("--peer-only", action="store_true",
                   help="with --update: keep the saved fgslam runs, run ORB-SLAM3 where the report has no result of it")
    p.add_argument("--readme", type=Path, default=None, help="rewrite the generated preset table in this README")
    p.add_argument("--details", type=Path, default=None,
                   help="rewrite the generated per-class results in this page (docs/benchmarks/classes.md)")
    args = p.parse_args(argv)
    args.names = [c for c in args.classes.split(",") if c]
    unknown = [c for c in args.names if c not in CLASSES]
    if unknown:
        p.error(f"unknown classes {unknown}; known: {', '.join(CLASSES)}")
    if args.peer is not None and bench_peers_problem(args) is not None:
        p.error(bench_peers_problem(args))
    if args.peer_only and (args.update is None or args.peer is None):
        p.error("--peer-only needs --update REPORT and --peer")
    if args.refresh_digests is not None and (args.update is None or not args.refresh_digests.strip()):
        p.error("--refresh-digests needs a reason and --update REPORT")
    return args


def refresh_digests(path: Path, reason: str) -> dict:
    """The report at ``path`` with every preset's digest recomputed and the change recorded (no runs)."""
    report = json.loads(path.read_text())
    now = {p: config_digest(p) for p in report["digests"]}
    changed = sorted(p for p, d in now.items() if report["digests"][p] != d)
    report["digests"] = now
    report["updates"] = [*report.get("updates", []), {"digests_refreshed": reason.strip(), "presets": changed}]
    path.write_text(json.dumps(report, indent=1) + "\n")
    return report


def bench_peers_problem(args: argparse.Namespace) -> Optional[str]:
    import bench_peers

    return bench_peers.peer_problem(args.peer, args.peer_scripts)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.refresh_digests is not None:
        report = refresh_digests(args.update, args.refresh_digests)
        print(json.dumps(report["updates"][-1], indent=1))
        return 0
    if args.from_report is not None:  # the rankings computed again by this version's scoring
        report = json.loads(args.from_report.read_text())
        report["classes"] = {name: class_report(name, CLASSES[name], c["cases"]) for name, c in report["classes"].items()}
    else:
        t0 = time.perf_counter()
        report = {"benchmark": "class benchmark: candidate presets per sensor class, ORB-SLAM3 side by side",
                  "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
                  "load_average_start": [round(v, 2) for v in os.getloadavg()],
                  "peer": str(args.peer) if args.peer else None, "repeats": args.repeats, "classes": {},
                  "digests": {}}
        rerun = args.update is not None and bool(args.presets)
        if args.update is not None:
            kept = json.loads(args.update.read_text())
            report = {**kept, "updates": [*kept.get("updates", []), {
                "classes": args.names, "presets": args.presets or "all", "peer_only": args.peer_only,
                "load_average_start": report["load_average_start"]}]}
        families = tuple(args.families.split(","))
        for name in args.names:
            cls = CLASSES[name]
            listed = [p for p in args.presets.split(",") if p]
            presets = (listed if rerun else [cls.preset] + [p for p in listed if p != cls.preset]) if listed \
                else candidates(cls, families)
            if args.peer_only:
                report["classes"][name] = add_peer(name, cls, report["classes"][name], args)
                continue
            digests = {p: config_digest(p) for p in presets}  # before the runs: what they measure
            cases = {clip: run_case(clip, CLIPS[clip], cls.sensor, presets, args) for clip in cls.clips}
            if rerun:  # the listed candidates rerun inside the saved class; the others' runs are kept
                saved = report["classes"][name]["cases"]
                for clip, case in cases.items():
                    saved[clip]["fgslam"].update(case["fgslam"])
                cases = saved
            report["classes"][name] = class_report(name, cls, cases)
            report["digests"].update(digests)
        report["classes"] = {k: report["classes"][k] for k in CLASSES if k in report["classes"]}
        report["total_s"] = round(time.perf_counter() - t0, 1)
        report["load_average_end"] = [round(v, 2) for v in os.getloadavg()]
        if args.update is not None:
            args.update.write_text(json.dumps(report, indent=1) + "\n")
    if args.readme is not None:
        write_readme(args.readme, report)
    if args.details is not None:
        write_details(args.details, report)
    print(json.dumps(report, indent=1))
    print(table(report), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
