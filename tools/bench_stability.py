"""Stability benchmark: each case (a preset on a sequence) run under tiny perturbations that must not
change the result, reporting the median, min and max ATE per case and the max/min ratio; prints one
JSON object.

A perturbation is what differs between two users' machines or two innocent choices, never a change
of the input that a SLAM system should notice:

- ``base``: the case as it is;
- ``focal+1ppm`` / ``focal-1ppm``: the calibration's focal lengths (fx, fy; KITTI's ``fx * baseline``
  with them) scaled by 1 +- 1e-6 in a copy of the sequence whose other files are links;
- ``threads1`` / ``threads2``: ``-o threads=N`` (torch and OpenCV threads of the run);
- ``oldcpu``: another CPU's kernels (torch, oneDNN, MKL, OpenBLAS, OpenCV): the variables of
  ``tools/old-cpu.env``, which CI's second step also uses;
- ``pixels``: one grey level added or taken on a seeded tenth of every camera image's pixel values
  (each channel of a colour image; depth untouched), in a copy of the sequence written losslessly: the
  size of a decoder's rounding (libpng's colour-to-grey is one level off OpenCV's on about 40 % of a
  render's pixels).

Targets (issue 36): max/min ATE <= 1.25 for the recommended presets, <= 1.5 for each family's main
presets. Runs are separate ``fgslam run`` processes (``--jobs`` at a time); synthetic sequences are
rendered once into ``--synth-dir`` and reused.

Usage:
  .venv/bin/python tools/bench_stability.py [--cases handheld_rgbd,pointmap_7scenes_mono] \\
      [--perturbations base,focal+1ppm,...] [--jobs 2] [--keep-outputs DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple, Optional

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"
RECOMMENDED_RATIO = 1.25  # max/min ATE across perturbations, a recommended preset
FAMILY_RATIO = 1.5  # the same, a family's main preset
FOCAL_PPM = 1e-6
OLD_CPU_ENV_FILE = REPO / "tools" / "old-cpu.env"  # another CPU's kernels on this one (also used by .ci/run)
CALIBRATION_NAMES = ("camera-intrinsics.txt", "calib.txt", "sensor.yaml")


class Case(NamedTuple):
    """A preset on a sequence: ``data`` is a folder under --data or ``synth:PRESET:FRAMES[:WxH[:SEED]]``;
    ``target`` the largest allowed max/min ATE ratio."""

    preset: str
    data: str
    target: float
    overrides: tuple[str, ...] = ()


KITCHEN, KITTI, EUROC = "7scenes_redkitchen_0-599", "kitti00_0-199", "euroc_v101_micro"
CASES: dict[str, Case] = {
    # the five recommended presets, on the sequences docs/benchmarks/presets.md quotes
    "handheld_rgbd": Case("handheld_rgbd", KITCHEN, RECOMMENDED_RATIO),
    "handheld_mono": Case("handheld_mono", KITCHEN, RECOMMENDED_RATIO),
    "handheld_stereo": Case("handheld_stereo", EUROC, RECOMMENDED_RATIO),
    "driving_mono": Case("driving_mono", KITTI, RECOMMENDED_RATIO),
    "driving_stereo": Case("driving_stereo", "synth:street-loop:200", RECOMMENDED_RATIO),
    # the synthetic reproductions of the held-out classes (../shared/findings)
    "handheld_rgbd_panel_room": Case("handheld_rgbd", "synth:panel-room:189", RECOMMENDED_RATIO),
    "handheld_mono_rotation_sweep": Case("handheld_mono", "synth:rotation-sweep:240", RECOMMENDED_RATIO),
    # each family's main presets
    "patch_kitti_mono": Case("patch_kitti_mono", KITTI, FAMILY_RATIO),
    "dense_kitti_mono": Case("dense_kitti_mono", KITTI, FAMILY_RATIO),
    "dense_7scenes_rgbd": Case("dense_7scenes_rgbd", KITCHEN, FAMILY_RATIO),
    "dense_kitti_stereo": Case("dense_kitti_stereo", "synth:kitti00-drive:101:1241x376", FAMILY_RATIO),
    "pointmap_7scenes_mono": Case("pointmap_7scenes_mono", KITCHEN, FAMILY_RATIO),
    "pointmap_7scenes_rgbd": Case("pointmap_7scenes_rgbd", KITCHEN, FAMILY_RATIO),
}
PERTURBATIONS = ("base", "focal+1ppm", "focal-1ppm", "threads1", "threads2", "oldcpu", "pixels")
PIXEL_SHARE = 0.1  # ``pixels``: the share of each camera image's pixel values moved by one grey level
PIXEL_SEED = 0
#: camera images a ``pixels`` copy rewrites (depth maps, being 16-bit or named depth, are linked unchanged)
CAMERA_IMAGE = re.compile(r"(\.color\.(png|jpg)|/(image_[0-3]|cam[0-3]/data)/[^/]+\.png)$")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", default=",".join(CASES), help="comma-separated subset of: " + ", ".join(CASES))
    p.add_argument("--perturbations", default=",".join(PERTURBATIONS),
                   help="comma-separated subset of: " + ", ".join(PERTURBATIONS))
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    p.add_argument("--synth-dir", type=Path, default=Path(tempfile.gettempdir()) / "fgslam_bench_synth",
                   help="cache folder of the synthetic renders (reused)")
    p.add_argument("--jobs", type=int, default=1, help="runs at a time (each run's result does not depend on load)")
    p.add_argument("--keep-outputs", type=Path, default=None, help="keep each run's outputs in DIR/<case>/<perturbation>")
    p.add_argument("-o", "--override", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override applied to every run (repeatable)")
    args = p.parse_args(argv)
    for label, names, known in (("case", args.cases, CASES), ("perturbation", args.perturbations, PERTURBATIONS)):
        unknown = [n for n in names.split(",") if n not in known]
        if unknown:
            p.error(f"unknown {label} {', '.join(unknown)} (known: {', '.join(known)})")
    return args


def fgslam_command() -> list[str]:
    return [sys.executable, "-m", "fgslam"]


def sequence_root(case: Case, args: argparse.Namespace) -> Path:
    """The case's sequence: a shared folder, or a synthetic render (made once, then reused)."""
    if not case.data.startswith("synth:"):
        return args.data / case.data
    return synth_sequence(case.data, args.synth_dir, "stability")


def synth_sequence(spec: str, synth_dir: Path, prefix: str) -> Path:
    """The render of ``synth:PRESET:FRAMES[:WxH[:SEED]]`` under ``synth_dir`` (made once, then reused;
    without a size the preset's own)."""
    _, preset, frames, *rest = spec.split(":")
    cmd = fgslam_command() + ["-q", "synth", "--preset", preset, "--frames", frames]
    if rest:
        width, height = rest[0].lower().split("x")
        cmd += ["--width", width, "--height", height]
    if len(rest) > 1:
        cmd += ["--seed", rest[1]]
    root = synth_dir / "_".join([prefix, preset, frames, *rest])
    if not (root / ".complete").exists():
        shutil.rmtree(root, ignore_errors=True)
        subprocess.run(cmd + ["--out", str(root)], check=True, stdout=sys.stderr)  # stdout carries the report alone
        (root / ".complete").write_text("")
    return root


def _scale_numbers(text: str, positions: tuple[int, ...], factor: float) -> str:
    """``text`` with its numbers at ``positions`` (0-based among the numbers) multiplied by ``factor``."""
    numbers = list(re.finditer(r"[-+]?\d*\.?\d+(?:[eE][-+]?\d+)?", text))
    out, last = [], 0
    for i, m in enumerate(numbers):
        if i in positions:
            out += [text[last:m.start()], repr(float(m.group()) * factor)]
            last = m.end()
    return "".join(out) + text[last:]


def perturbed_calibration(path: Path, factor: float) -> str:
    """The calibration file's text with its focal lengths scaled by ``factor``."""
    text = path.read_text()
    if path.name == "camera-intrinsics.txt":  # 3 x 3 K, row-major
        return _scale_numbers(text, (0, 4), factor)
    if path.name == "calib.txt":  # KITTI: 'Pn: fx 0 cx tx 0 fy cy ty 0 0 1 tz', tx = -fx * baseline
        return "\n".join(_scale_numbers(line, (1, 4, 6), factor) if re.match(r"P\d:", line) else line
                         for line in text.splitlines()) + "\n"
    lines = text.splitlines()  # EuRoC sensor.yaml: 'intrinsics: [fu, fv, cu, cv]'
    return "\n".join(_scale_numbers(line, (0, 1), factor) if line.lstrip().startswith("intrinsics:") else line
                     for line in lines) + "\n"


def perturbed_copy(root: Path, dest: Path, factor: float) -> Path:
    """``root`` mirrored under ``dest`` by links, its calibration files rewritten with the focal scaled."""
    def mirror(src: Path, dst: Path) -> None:
        dst.mkdir(parents=True, exist_ok=True)
        for item in sorted(src.iterdir()):
            holds_calibration = item.is_dir() and any(p.name in CALIBRATION_NAMES for p in item.rglob("*"))
            if item.name in CALIBRATION_NAMES:
                (dst / item.name).write_text(perturbed_calibration(item, factor))
            elif holds_calibration:
                mirror(item, dst / item.name)
            else:
                (dst / item.name).symlink_to(item.resolve())

    mirror(root, dest)
    return dest


def pixels_copy(root: Path, dest: Path, share: float = PIXEL_SHARE, seed: int = PIXEL_SEED) -> Path:
    """``root`` mirrored under ``dest`` by links, every camera image (:data:`CAMERA_IMAGE`) rewritten with one
    grey level added or taken on ``share`` of its pixel values (seeded by ``seed`` and the file's path in the
    sequence: a stereo pair's two images differ), as PNG bytes under the same name (the loaders decode by
    content). RuntimeError: no camera image found (a layout :data:`CAMERA_IMAGE` does not know)."""
    import cv2
    import numpy as np

    if (dest / ".complete").exists():
        return dest
    shutil.rmtree(dest, ignore_errors=True)
    rewritten = 0
    for src in sorted(root.rglob("*")):
        dst = dest / src.relative_to(root)
        if src.is_dir():
            dst.mkdir(parents=True, exist_ok=True)
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        image = cv2.imread(str(src), cv2.IMREAD_UNCHANGED) if CAMERA_IMAGE.search(src.as_posix()) else None
        if image is None or image.dtype != np.uint8:
            dst.symlink_to(src.resolve())
            continue
        rng = np.random.default_rng([seed, *src.relative_to(root).as_posix().encode()])
        step = np.where(rng.random(image.shape) < share, rng.choice(np.array([-1, 1], np.int16), image.shape), 0)
        ok, png = cv2.imencode(".png", np.clip(image.astype(np.int16) + step, 0, 255).astype(np.uint8))
        if not ok:
            raise RuntimeError(f"{src}: could not encode the changed image")
        dst.write_bytes(png.tobytes())
        rewritten += 1
    if not rewritten:
        raise RuntimeError(f"{root}: no camera image to change (pixels perturbation)")
    (dest / ".complete").write_text("")
    return dest


def old_cpu_env() -> dict[str, str]:
    """The ``VAR=VALUE`` lines of ``tools/old-cpu.env``."""
    lines = (line.strip() for line in OLD_CPU_ENV_FILE.read_text().splitlines())
    return dict(line.split("=", 1) for line in lines if line and not line.startswith("#"))


def perturbation_setup(name: str, root: Path, work: Path) -> tuple[Path, list[str], dict[str, str]]:
    """(sequence root, overrides, environment additions) of one perturbation."""
    if name.startswith("focal"):
        sign = 1.0 if name[len("focal")] == "+" else -1.0
        return perturbed_copy(root, work / f"data_{name}", 1.0 + sign * FOCAL_PPM), [], {}
    if name.startswith("threads"):
        return root, [f"threads={name[len('threads'):]}"], {}
    if name == "oldcpu":
        return root, [], old_cpu_env()
    if name == "pixels":
        return pixels_copy(root, work / "data_pixels"), [], {}
    return root, [], {}


def run_one(case: Case, root: Path, perturbation: str, out: Path, args: argparse.Namespace) -> dict:
    """One ``fgslam run`` under one perturbation; its ATE, frames posed and CPU seconds."""
    data, overrides, env_add = perturbation_setup(perturbation, root, out.parent)
    cmd = fgslam_command() + ["-q", "run", case.preset, "--data", str(data), "--out", str(out), "--overwrite",
                              "--no-progress", "-o", "output.plot=false", "-o", "output.write_map=false"]
    for item in (*case.overrides, *args.overrides, *overrides):
        cmd += ["-o", item]
    env = {**os.environ, **env_add}
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=err, text=True)
        _, status, usage = os.wait4(proc.pid, 0)  # this child's own CPU time (runs may overlap: --jobs)
        proc.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        stderr = err.read()
    result = {"perturbation": perturbation, "returncode": proc.returncode, "wall_s": round(time.perf_counter() - t0, 1),
              "cpu_s": round(usage.ru_utime + usage.ru_stime, 1)}
    summary_file = out / "summary.json"
    if proc.returncode != 0 or not summary_file.exists():
        result["error"] = (stderr.strip().splitlines() or ["no output"])[-1]
        return result
    s = json.loads(summary_file.read_text())
    ate = ((s.get("evaluation") or {}).get("ate") or {}).get("rmse")
    result.update(ate_rmse_m=ate, frames=s.get("frames"), frames_with_pose=s.get("frames_with_pose"),
                  keyframes=s.get("keyframes"))
    return result


def summarise(name: str, case: Case, runs: list[dict]) -> dict:
    ates = [r["ate_rmse_m"] for r in runs if r.get("ate_rmse_m") is not None]
    out = {"case": name, "preset": case.preset, "data": case.data, "target_ratio": case.target, "runs": runs}
    if len(ates) < len(runs) or not ates:
        out.update(ok=False, reason="a run gave no ATE")
        return out
    ratio = max(ates) / min(ates) if min(ates) > 0 else float("inf")
    out.update(median_ate_m=statistics.median(ates), min_ate_m=min(ates), max_ate_m=max(ates),
               ratio=round(ratio, 4), ok=ratio <= case.target)
    return out


def load_average() -> Optional[list[float]]:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def main(argv=None) -> int:
    args = parse_args(argv)
    names = args.cases.split(",")
    perturbations = args.perturbations.split(",")
    work = Path(tempfile.mkdtemp(prefix="fgslam_stability_")) if args.keep_outputs is None else args.keep_outputs
    report = {"machine": {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count()},
              "load_before": load_average(), "perturbations": perturbations, "cases": []}
    for name in names:
        case = CASES[name]
        root = sequence_root(case, args)
        outs = [work / name / p / "run" for p in perturbations]
        for out in outs:
            out.parent.mkdir(parents=True, exist_ok=True)
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            runs = list(pool.map(lambda po: run_one(case, root, po[0], po[1], args), zip(perturbations, outs)))
        report["cases"].append(summarise(name, case, runs))
        print(json.dumps({k: v for k, v in report["cases"][-1].items() if k != "runs"}), file=sys.stderr, flush=True)
    report["load_after"] = load_average()
    if args.keep_outputs is None:
        shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
