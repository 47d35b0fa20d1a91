"""Long-sequence benchmark (issue 24 item 3): every family over the synthetic KITTI-length drive.

Renders (or reuses) the ``kitti00-drive`` synthetic sequence (``fgslam synth --preset kitti00-drive``:
KITTI 00's 4,541 camera poses at 10 Hz through a street scene, stereo + depth + exact ground truth) and
runs each family (``--families`` patch dense pointmap) in each mode (``--modes`` mono stereo) with loop
closure on and off (``--loops`` on off), every run in its own process (its own peak RSS). Per frame it
records the wall and CPU seconds of the run's tracking step (the time from handing the frame to the
run until it asks for the next one: frontend, backend and the safe points; reading excluded) and the
resident memory (``/proc/self/statm``). Reported per run: ATE (the run's own evaluation), frames/s
(wall and per CPU second) of the first and of the last 500 frames, peak RSS at frame 500 and at the
end and their ratio (target <= 1.5), the ratio of last-500 to first-500 frames per CPU second (target
>= 0.8: within 20 %), keyframes, failures, and ``os.getloadavg()`` before and after. A PNG plots RSS
and time per frame (CPU ms, median over a sliding window) against the frame index, one line per run.

``--tracemalloc`` also snapshots the Python heap at frame ``--window`` and at the end and lists the
source lines whose allocations grew the most (slower: for finding what grows, not for timing).

Presets per family and mode (``PRESETS``): patch = driving_mono / driving_stereo, dense =
dense_kitti_mono (at full size: ``dataset.resize_scale=1``) / dense_stereo, pointmap = pointmap_mono /
pointmap_stereo. Loop closure on = ``loop_closure.mode`` both for the patch family, classical for the
others (``LOOP_MODE``).

Usage (prefix of 1,000 frames, patch only, both modes, loops on and off)::

    OMP_NUM_THREADS=1 nice -n 5 .venv/bin/python tools/bench_long_drive.py --frames 1000 --families patch \\
        --json-out long_drive.json --plot long_drive.png
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PRESET = "kitti00-drive"
PRESETS = {("patch", "mono"): ("driving_mono", ()), ("patch", "stereo"): ("driving_stereo", ()),
           ("dense", "mono"): ("dense_kitti_mono", ("dataset.resize_scale=1.0",)),
           ("dense", "stereo"): ("dense_stereo", ()),
           ("pointmap", "mono"): ("pointmap_mono", ()), ("pointmap", "stereo"): ("pointmap_stereo", ())}
LOOP_MODE = {"patch": "both", "dense": "classical", "pointmap": "classical"}
PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")
MIB = 1024 ** 2
TARGET_RSS_RATIO = 1.5   # peak RSS at the end / at frame `window` (issue 24)
TARGET_FPS_RATIO = 0.8   # last-window frames per CPU s / first-window (within 20 %)
PLOT_SMOOTH = 51         # frames of the sliding median of the plotted time per frame
PROGRESS_EVERY = 100     # frames between the child's progress-file updates


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=None, help="run only the first N frames (default: all 4,541)")
    p.add_argument("--families", nargs="+", default=["patch", "dense", "pointmap"], choices=["patch", "dense", "pointmap"])
    p.add_argument("--modes", nargs="+", default=["mono", "stereo"], choices=["mono", "stereo"])
    p.add_argument("--loops", nargs="+", default=["on", "off"], choices=["on", "off"])
    p.add_argument("--window", type=int, default=500, help="frames of the first / last window (default 500)")
    p.add_argument("--data-dir", type=Path, default=Path(tempfile.gettempdir()) / "fgslam_long_drive",
                   help="cache folder of the rendered drive (reused when present)")
    p.add_argument("--synth-override", action="append", default=[], metavar="KEY=VALUE",
                   help="SynthConfig override of the rendered drive (a different cache folder)")
    p.add_argument("-o", "--override", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="SlamConfig override applied to every run (repeatable)")
    p.add_argument("--json-out", type=Path, default=None, help="also write the JSON report here")
    p.add_argument("--plot", type=Path, default=None, help="PNG of RSS and time per frame against frame index")
    p.add_argument("--runs-dir", type=Path, default=None, help="keep each run's outputs and per-frame record here")
    p.add_argument("--tracemalloc", action="store_true", help="list the Python allocations that grew (slow)")
    p.add_argument("--from-runs", type=Path, nargs="+", default=None, metavar="DIR",
                   help="no runs: report (JSON, --plot) the per-run records already in these --runs-dir folders")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)  # internal: family,mode,loops,out_json
    p.add_argument("--root", type=Path, default=None, help=argparse.SUPPRESS)
    return p.parse_args(argv)


def drive_root(args: argparse.Namespace) -> Path:
    """Render (or reuse) the full drive; returns its root. The whole drive is rendered once whatever
    ``--frames`` is (a prefix is run with ``dataset.end``), so prefixes of one cache are comparable."""
    tag = "_".join(o.replace("=", "-").replace(".", "-") for o in args.synth_override)
    root = args.data_dir / (f"{PRESET}_{tag}" if tag else PRESET)
    done = root / "synth_done.json"
    if done.is_file():
        return root
    if root.exists():
        shutil.rmtree(root)
    root.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "fgslam", "synth", "--preset", PRESET, "--out", str(root), "--json"]
    for o in args.synth_override:
        cmd += ["-o", o]
    print(f"rendering the drive into {root} ...", file=sys.stderr, flush=True)
    t0, c0 = time.perf_counter(), _children_cpu()
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise SystemExit(f"rendering failed:\n{res.stderr[-3000:]}")
    info = json.loads(res.stdout.strip().splitlines()[-1])
    info.update(render_wall_s=round(time.perf_counter() - t0, 1), render_cpu_s=round(_children_cpu() - c0, 1))
    done.write_text(json.dumps(info))
    return root


def _children_cpu() -> float:
    u = resource.getrusage(resource.RUSAGE_CHILDREN)
    return u.ru_utime + u.ru_stime


def _rss_bytes() -> int:
    with open("/proc/self/statm", "rb") as f:
        return int(f.read().split()[1]) * PAGE_BYTES


class TimedDataset:
    """The run's dataset, recording per frame the wall / CPU seconds of the run's step on it (from
    handing the frame out until the next one is asked for) and the RSS after it."""

    def __init__(self, dataset, on_frame=None) -> None:
        self._dataset = dataset
        self._on_frame = on_frame
        self.wall_s: list[float] = []
        self.cpu_s: list[float] = []
        self.rss: list[int] = []

    def __getattr__(self, name):
        return getattr(self._dataset, name)

    def __len__(self) -> int:
        return len(self._dataset)

    def __iter__(self):
        for frame in self._dataset:
            handed = (time.perf_counter(), time.process_time())
            yield frame
            self._close(handed)  # resumed: the run asks for the next frame, so this one's step is over

    def _close(self, handed) -> None:
        self.wall_s.append(time.perf_counter() - handed[0])
        self.cpu_s.append(time.process_time() - handed[1])
        self.rss.append(_rss_bytes())
        if self._on_frame is not None:
            self._on_frame(len(self.rss))


def run_child(args: argparse.Namespace) -> None:
    """One run in this process; writes its record (JSON) to the path in ``--child``."""
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset
    from fgslam.run.runner import run_slam

    family, mode, loops, out_json = args.child.split(",", 3)
    preset, preset_overrides = PRESETS[(family, mode)]
    overrides = list(preset_overrides) + [f"loop_closure.mode={LOOP_MODE[family] if loops == 'on' else 'off'}"]
    if args.frames:
        overrides.append(f"dataset.end={args.frames}")
    overrides += args.overrides
    config = load_slam_config(preset, overrides)
    snapshots = {}
    if args.tracemalloc:
        import tracemalloc

        tracemalloc.start(4)

    progress = Path(out_json).with_suffix(".progress")

    def on_frame(n: int) -> None:
        if args.tracemalloc and n == args.window:
            snapshots["window"] = tracemalloc.take_snapshot()
        if n % PROGRESS_EVERY == 0:  # a long run can be followed: frames done and RSS
            progress.write_text(f"{n} frames, RSS {_rss_bytes() / MIB:.1f} MiB, CPU {time.process_time():.1f} s\n")

    dataset = TimedDataset(open_slam_dataset(args.root, config), on_frame)
    out = Path(out_json).with_suffix("")
    if out.exists():
        shutil.rmtree(out)
    load_before = [round(v, 2) for v in os.getloadavg()]
    error = None
    try:
        summary = run_slam(dataset, config, out, progress=False).to_dict()
    except Exception as exc:  # noqa: BLE001 - the benchmark reports failures instead of stopping
        error = f"{type(exc).__name__}: {exc}"
        path = out / "summary.json"
        summary = json.loads(path.read_text()) if path.is_file() else {}
    record = {"family": family, "mode": mode, "loops": loops, "preset": preset, "overrides": overrides,
              "error": error, "summary": summary, "wall_s": dataset.wall_s, "cpu_s": dataset.cpu_s,
              "rss": dataset.rss, "ru_maxrss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
              "loadavg_before": load_before, "loadavg_after": [round(v, 2) for v in os.getloadavg()]}
    if args.tracemalloc and "window" in snapshots:
        import tracemalloc

        end = tracemalloc.take_snapshot()
        diff = end.compare_to(snapshots["window"], "traceback")
        record["tracemalloc_growth"] = [
            {"kib": round(d.size_diff / 1024, 1), "count": d.count_diff,
             "where": [f"{fr.filename}:{fr.lineno}" for fr in d.traceback]} for d in diff[:25]]
    Path(out_json).write_text(json.dumps(record))


def _proximity_count(loop: dict | None):
    """Accepted proximity edges of a run's loop summary (None when there were none to count)."""
    prox = (loop or {}).get("proximity")
    if not isinstance(prox, dict):
        return None
    return {k: v for k, v in prox.items() if isinstance(v, (int, float))}


def window_stats(rec: dict, window: int) -> dict:
    """The report entry of one run's record."""
    import numpy as np

    s = rec.get("summary") or {}
    ev = s.get("evaluation") or {}
    wall, cpu, rss = (np.asarray(rec[k], np.float64) for k in ("wall_s", "cpu_s", "rss"))
    n = len(rss)
    out = {"family": rec["family"], "mode": rec["mode"], "loops": rec["loops"], "preset": rec["preset"],
           "overrides": rec["overrides"], "error": rec["error"], "frames": n,
           "frames_with_pose": s.get("frames_with_pose"), "keyframes": s.get("keyframes"),
           "failures": s.get("failures"), "ate_rmse_m": ev.get("ate_rmse_m"),
           "ate_percent_of_path": ev.get("ate_percent_of_path"), "align": ev.get("align"),
           "accepted_loops": (s.get("loop") or {}).get("accepted_loops"),
           "proximity_loops": _proximity_count(s.get("loop")),
           "fps_run": s.get("fps"), "cpu_s_run": s.get("cpu_s"), "max_frame_s": s.get("max_frame_s"),
           "ru_maxrss_mib": round(rec["ru_maxrss_mib"], 1),
           "loadavg_before": rec["loadavg_before"], "loadavg_after": rec["loadavg_after"]}
    if n == 0:
        return out
    w = min(window, n)
    first, last = slice(0, w), slice(n - w, n)
    out.update(
        window=w,
        fps_first=round(w / wall[first].sum(), 2), fps_last=round(w / wall[last].sum(), 2),
        fps_cpu_first=round(w / cpu[first].sum(), 2), fps_cpu_last=round(w / cpu[last].sum(), 2),
        peak_rss_at_window_mib=round(rss[:w].max() / MIB, 1), peak_rss_end_mib=round(rss.max() / MIB, 1),
        rss_at_window_mib=round(rss[w - 1] / MIB, 1), rss_end_mib=round(rss[-1] / MIB, 1))
    out["rss_ratio"] = round(out["peak_rss_end_mib"] / out["peak_rss_at_window_mib"], 3)
    out["fps_cpu_ratio"] = round(out["fps_cpu_last"] / out["fps_cpu_first"], 3)
    out["rss_target_met"] = bool(out["rss_ratio"] <= TARGET_RSS_RATIO)
    out["fps_target_met"] = bool(out["fps_cpu_ratio"] >= TARGET_FPS_RATIO)
    if n >= 2 * window:  # RSS growth per 1,000 frames after the first window (least squares)
        idx = np.arange(window, n)
        out["rss_slope_mib_per_1000_frames"] = round(float(np.polyfit(idx, rss[window:] / MIB, 1)[0]) * 1000, 2)
    if "tracemalloc_growth" in rec:
        out["tracemalloc_growth"] = rec["tracemalloc_growth"]
    return out


def plot(records: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, (ax_rss, ax_t) = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    for rec in records:
        if not rec["rss"]:
            continue
        label = f"{rec['family']} {rec['mode']} loops {rec['loops']}"
        x = np.arange(1, len(rec["rss"]) + 1)
        ax_rss.plot(x, np.asarray(rec["rss"]) / MIB, label=label)
        cpu = np.asarray(rec["cpu_s"]) * 1000.0
        k = min(PLOT_SMOOTH, len(cpu))
        pad = np.pad(cpu, (k // 2, k - 1 - k // 2), mode="edge")
        smooth = np.median(np.lib.stride_tricks.sliding_window_view(pad, k), axis=1)
        ax_t.plot(x, smooth, label=label)
    ax_rss.set_ylabel("RSS (MiB)")
    ax_t.set_ylabel(f"CPU ms per frame (median of {PLOT_SMOOTH})")
    ax_t.set_xlabel("frame index")
    ax_rss.set_title(f"{PRESET}: memory and time per frame")
    ax_rss.legend(fontsize=7)
    ax_rss.grid(alpha=0.3)
    ax_t.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.child:
        run_child(args)
        return
    if args.from_runs:
        records = [json.loads(p.read_text()) for d in args.from_runs for p in sorted(d.glob("*.json"))]
        report(args, None, records, [window_stats(rec, args.window) for rec in records], args.from_runs)
        return
    root = drive_root(args)
    runs_dir = args.runs_dir or Path(tempfile.mkdtemp(prefix="bench_long_drive_"))
    runs_dir.mkdir(parents=True, exist_ok=True)
    records, entries = [], []
    for family in args.families:
        for mode in args.modes:
            for loops in args.loops:
                name = f"{family}_{mode}_loops-{loops}"
                rec_path = runs_dir / f"{name}.json"
                cmd = [sys.executable, __file__, "--child", f"{family},{mode},{loops},{rec_path}", "--root", str(root),
                       "--window", str(args.window)]
                if args.frames:
                    cmd += ["--frames", str(args.frames)]
                if args.tracemalloc:
                    cmd.append("--tracemalloc")
                for o in args.overrides:
                    cmd += ["-o", o]
                print(f"running {name} ...", file=sys.stderr, flush=True)
                res = subprocess.run(cmd, capture_output=True, text=True, check=False)
                if res.returncode != 0 or not rec_path.is_file():
                    entries.append({"family": family, "mode": mode, "loops": loops,
                                   "error": f"child failed ({res.returncode}): {res.stderr[-2000:]}"})
                    continue
                rec = json.loads(rec_path.read_text())
                records.append(rec)
                entries.append(window_stats(rec, args.window))
                print(json.dumps({k: entries[-1].get(k) for k in ("family", "mode", "loops", "frames", "ate_rmse_m",
                                                                 "fps_cpu_first", "fps_cpu_last", "rss_ratio", "error")}),
                      file=sys.stderr, flush=True)
    report(args, root, records, entries, [runs_dir])


def report(args: argparse.Namespace, root: Path | None, records: list[dict], entries: list[dict], runs_dirs) -> None:
    """Print (and write) the JSON report and the plot."""
    done = root / "synth_done.json" if root is not None else None
    result = {"preset": PRESET, "data": str(root), "render": json.loads(done.read_text()) if done and done.is_file() else None,
              "frames_asked": args.frames, "window": args.window, "runs": entries, "runs_dirs": [str(d) for d in runs_dirs],
              "cpu_count": os.cpu_count(), "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
              "targets": {"rss_ratio_max": TARGET_RSS_RATIO, "fps_cpu_ratio_min": TARGET_FPS_RATIO}}
    if args.plot and records:
        plot(records, args.plot)
        result["plot"] = str(args.plot)
    text = json.dumps(result, indent=1)
    if args.json_out:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
