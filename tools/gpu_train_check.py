"""GPU check of issue 29 item 4: the old and the new training speed, a short training run on the GPU,
and the trained network as the dense source beside the built-in DIS source. JSON to stdout (every
child's lines echoed as they come, the result last); files under ``$OUT``.

Stages (each bounded in time; about 8 minutes in all with the defaults, estimated: not yet run on a GPU):

a. **old**: ``tools/train.py`` as of commit 8f6499f (batch 1, the BA in float64 on the CPU, the clip
   tensors built on the CPU each step), at 128x96 with its defaults, for ``OLD_S`` seconds; its
   per-step time from the difference of its log lines (start-up, pool and evaluation excluded). The
   old file is read from ``$OLD_TRAIN``, ``.whl/train_old.py`` or ``git show 8f6499f:tools/train.py``;
   without any of them, this stage reports ``skipped`` (the issue measured 0.39 s per step on an H100).
b. **new**: the current ``tools/train.py`` at batch 1 for ``B1_S`` seconds (the same clip size, the
   pool on the GPU, float32 BA), then at ``--batch BATCH`` for ``TRAIN_S`` seconds on a pool of
   ``POOL_SEEDS`` scenes (seeds 1..POOL_SEEDS of the preset, rendered in worker processes), the
   checkpoint in ``$OUT/droid.pth``; steps/s, clips/s and GPU use from its log lines.
c. **dense**: the default room-loop render (seed 0: a scene not in the pool), ``EVAL_FRAMES`` frames
   at 10 Hz and 128x96 (the training size), run with ``dense_mono`` on the built-in DIS source and on
   the trained checkpoint (``dense.source.kind=droid``, on the GPU; the setting of the issue's table),
   then the checkpoint on ``dense_learned_mono`` (DROID-SLAM's demo schedule); ATE in % of the path
   (Sim(3) alignment) per run, through ``tools/bench_dense_run.py``'s runner.

Usage, on the GPU machine from the repository root (gtsam installed; nothing is downloaded)::

  PYTHONUNBUFFERED=1 OUT=/some/dir python3 tools/gpu_train_check.py

Environment: ``OUT`` (required), ``SMOKE=1`` (every stage shrunk to seconds, on the CPU: the check of
this script itself), ``DEVICE`` (cuda; smoke: cpu), ``BATCH`` (16), ``TRAIN_S`` (225), ``OLD_S`` (30),
``B1_S`` (10), ``POOL_SEEDS`` (8), ``WORKERS`` (CPU count), ``EVAL_FRAMES`` (201),
``EVAL_EVERY`` (200: each evaluation writes the checkpoint), ``SKIP`` (comma list of the stages a, b1,
b, c to leave out).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OLD_COMMIT = "8f6499f"  # tools/train.py before the batched GPU path
ISSUE_S_PER_STEP = 0.39  # issue 29: the old training's time per step (one clip) at 128x96 on an H100


def env(name: str, default, smoke_default=None):
    smoke = os.environ.get("SMOKE") == "1"
    value = os.environ.get(name)
    if value is None:
        value = smoke_default if smoke and smoke_default is not None else default
    return type(default)(value)


def emit(obj: dict) -> None:
    print(json.dumps(obj), flush=True)


def stream(cmd: list[str], limit_s: float, log_path: Path, enough=None) -> tuple[list[str], int | None, float]:
    """Run ``cmd`` echoing its output lines, stop it (its process group) after ``limit_s`` seconds or
    once ``enough(lines)`` holds. Returns the lines, the exit code (None: stopped) and the wall time."""
    t0 = time.perf_counter()
    lines: list[str] = []
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
                            start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})

    def read() -> None:
        with open(log_path, "w") as log:
            for line in proc.stdout:
                lines.append(line.rstrip("\n"))
                log.write(line)
                print(line, end="", flush=True)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    rc = None
    while time.perf_counter() - t0 < limit_s and not (enough and enough(lines)):
        try:
            rc = proc.wait(timeout=0.5)
            break
        except subprocess.TimeoutExpired:
            continue
    if rc is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    reader.join(timeout=10)
    return lines, rc, time.perf_counter() - t0


def json_lines(lines: list[str]) -> list[dict]:
    out = []
    for line in lines:
        if line.startswith("{"):
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return out


def old_script(out: Path) -> Path | None:
    """The old tools/train.py (module docstring), copied to ``out``; None when not found."""
    for candidate in (os.environ.get("OLD_TRAIN"), REPO / ".whl" / "train_old.py"):
        if candidate and Path(candidate).is_file():
            return Path(shutil.copy(candidate, out / "train_old.py"))
    try:
        text = subprocess.run(["git", "show", f"{OLD_COMMIT}:tools/train.py"], cwd=REPO, capture_output=True,
                              text=True, timeout=30, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    path = out / "train_old.py"
    path.write_text(text)
    return path


def old_stage(cfg: dict, out: Path, work: Path) -> dict:
    script = old_script(work)
    if script is None:
        return {"skipped": f"no old tools/train.py (OLD_TRAIN, .whl/train_old.py or git show {OLD_COMMIT})"}
    cmd = [sys.executable, str(script), "--device", cfg["device"], "--steps", "100000", "--eval-clips", "1",
           "--eval-every", "100000", "--log-every", str(cfg["old_log_every"]), "--out", str(work / "old.pth"),
           *cfg["size"]]
    # its own s_per_step counts from before the pool: the per-step time is the slope between log lines
    def logged(lines):
        return [(d["step"], d["s_per_step"] * d["step"]) for d in json_lines(lines) if "s_per_step" in d]

    def enough(lines):
        times = logged(lines)
        return len(times) >= 2 and times[-1][1] - times[0][1] >= cfg["old_s"]

    lines, rc, wall = stream(cmd, cfg["old_s"] + cfg["startup_s"], out / "old_train.log", enough)
    logged = logged(lines)
    result = {"cmd": " ".join(cmd[1:]), "wall_s": wall, "exit": rc}
    if len(logged) < 2:
        return {**result, "error": "fewer than two log lines (raise OLD_S)"}
    (s0, e0), (s1, e1) = logged[0], logged[-1]
    return {**result, "steps_timed": s1 - s0, "s_per_step": (e1 - e0) / (s1 - s0), "s_per_clip": (e1 - e0) / (s1 - s0)}


def new_stage(cfg: dict, out: Path, work: Path, batch: int, seconds: float, pool_seeds: int, log_name: str,
              checkpoint: Path) -> dict:
    cmd = [sys.executable, str(REPO / "tools" / "train.py"), "--device", cfg["device"], "--batch", str(batch),
           "--steps", "1000000", "--time-limit-s", str(seconds), "--eval-every", str(cfg["eval_every"]), "--log-every",
           str(cfg["log_every"]), "--eval-clips", str(cfg["eval_clips"]), "--seed", "1", "--pool-seeds", str(pool_seeds),
           "--workers", str(cfg["workers"]), "--out", str(checkpoint), *cfg["size"]]
    lines, rc, wall = stream(cmd, seconds + cfg["startup_s"] + cfg["eval_s"], out / log_name)
    records = json_lines(lines)
    logs = [d for d in records if "steps_per_s" in d]
    summary = next((d["summary"] for d in records if "summary" in d), None)
    result = {"cmd": " ".join(cmd[1:]), "wall_s": wall, "exit": rc}
    if not logs:
        return {**result, "error": "no training log line"}
    timed = logs[1:] or logs  # the first window holds the warm-up (cudnn autotuning, allocator)
    steps = sum(d["window_steps"] for d in timed)
    seconds_timed = sum(d["window_s"] for d in timed)
    util = [d["gpu_util_percent"] for d in timed if d.get("gpu_util_percent") is not None]
    result.update({"batch": batch, "s_per_step": seconds_timed / steps, "steps_per_s": steps / seconds_timed,
                   "clips_per_s": steps * batch / seconds_timed, "s_per_clip": seconds_timed / (steps * batch),
                   "gpu_util_percent_mean": sum(util) / len(util) if util else None,
                   "gpu_util_source": timed[-1].get("gpu_util_source"), "gpu_max_mem_mib": timed[-1].get("gpu_max_mem_mib")})
    pool = next((d["pool"] for d in records if "pool" in d), None)
    if pool:
        result["pool"] = pool
    if summary:
        result.update({"steps": summary["throughput"]["steps"], "clips": summary["throughput"]["clips"],
                       "skipped_steps": summary["throughput"].get("skipped_steps"),
                       "train_s": summary["throughput"]["train_s"], "eval": summary["eval"],
                       "initial_state": summary["initial_state"]})
    return result


def dense_stage(cfg: dict, work: Path, checkpoint: Path, save) -> dict:
    spec = importlib.util.spec_from_file_location("bench_dense_run", REPO / "tools" / "bench_dense_run.py")
    bench = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = bench
    spec.loader.exec_module(bench)
    args = argparse.Namespace(synth_size=cfg["eval_size"], synth_frames=cfg["eval_frames"], synth_rate=10.0,
                              synth_dir=work / "synth")
    t0 = time.perf_counter()
    root = bench.synth_root("room-loop", args)
    result = {"sequence": {"preset": "room-loop", "seed": 0, "size": cfg["eval_size"], "frames": cfg["eval_frames"],
                           "rate_hz": 10.0, "render_s": time.perf_counter() - t0}}
    weights = [f"dense.source.checkpoint={checkpoint}", f"dense.source.droid.device={cfg['device']}"]
    runs = {  # name: (preset, overrides)
        "droid": ("dense_mono", ["dense.source.kind=droid", *weights]),  # the issue's table: dense_mono's schedule
        "dis": ("dense_mono", []),
        "droid_official_schedule": ("dense_learned_mono", weights),  # DROID-SLAM's demo schedule (issue 29 item 3)
    }
    for name, (preset, overrides) in runs.items():
        if name != "dis" and not checkpoint.is_file():
            result[name] = {"error": f"no checkpoint {checkpoint}"}
            continue
        t0 = time.perf_counter()
        r = bench.run_one(preset, root, work / f"run_{name}", overrides)
        r["wall_s"] = time.perf_counter() - t0
        result[name] = r
        save(result)
        emit({"dense_run": name, **{k: r.get(k) for k in ("ate_percent_of_path", "ate_m", "fps", "frames_with_pose",
                                                            "keyframes", "error", "wall_s")}})
    return result


def main() -> int:
    if "OUT" not in os.environ:
        print("gpu_train_check: set OUT to the folder for the results", file=sys.stderr)
        return 2
    out = Path(os.environ["OUT"])
    out.mkdir(parents=True, exist_ok=True)
    smoke = os.environ.get("SMOKE") == "1"
    skip = set(filter(None, os.environ.get("SKIP", "").split(",")))
    cfg = {
        "device": env("DEVICE", "cuda", "cpu"),
        "batch": env("BATCH", 16, 2),
        "train_s": env("TRAIN_S", 225.0, 8.0),
        "old_s": env("OLD_S", 30.0, 8.0),
        "b1_s": env("B1_S", 10.0, 4.0),
        "pool_seeds": env("POOL_SEEDS", 8, 2),
        "workers": env("WORKERS", os.cpu_count() or 1, 2),
        "eval_frames": env("EVAL_FRAMES", 201, 21),
        "eval_clips": env("EVAL_CLIPS", 16, 2),
        "log_every": env("LOG_EVERY", 10, 1),
        "eval_every": env("EVAL_EVERY", 200, 3),  # steps between evaluations (each writes the checkpoint)
        "old_log_every": env("OLD_LOG_EVERY", 5, 1),
        "startup_s": env("STARTUP_S", 60.0, 180.0),  # imports, pool rendering, first evaluation
        "eval_s": env("EVAL_S", 60.0, 120.0),  # the final evaluation and checkpoint
        "eval_size": "128x96",
        # smoke: a tiny clip graph; full: the training defaults at 128x96
        "size": (["--width", "64", "--height", "64", "--pool-frames", "24", "--iterations", "2", "--ba-steps", "1",
                  "--edge-radius", "1", "--clip-frames", "3", "--threads", "1"] if smoke else
                 ["--width", "128", "--height", "96"]),
    }
    work = Path(tempfile.mkdtemp(prefix="gpu_train_check_"))
    import torch  # after the settings: the check runs even where the import is slow

    info = {"smoke": smoke, "device": cfg["device"], "torch": torch.__version__, "cuda": torch.cuda.is_available(),
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None, "cpus": os.cpu_count(),
            "settings": {k: v for k, v in cfg.items() if k != "size"}, "load": os.getloadavg()[0]}
    emit({"gpu_train_check": info})
    result: dict = {"info": info}
    t_start = time.perf_counter()
    checkpoint = out / "droid.pth"

    def save(part: dict | None = None, key: str | None = None) -> None:
        """``$OUT/result.json`` after every stage and dense run: a run stopped early keeps what it got."""
        if key:
            result[key] = part
        result["total_wall_s"] = time.perf_counter() - t_start
        (out / "result.json").write_text(json.dumps(result, indent=1))

    if "a" not in skip:
        result["old"] = old_stage(cfg, out, work)
        save()
        emit({"old": result["old"]})
    if "b1" not in skip:
        result["new_batch1"] = new_stage(cfg, out, work, 1, cfg["b1_s"], 1, "train_batch1.log", work / "b1.pth")
        save()
        emit({"new_batch1": {k: v for k, v in result["new_batch1"].items() if k != "eval"}})
    if "b" not in skip:
        result["new"] = new_stage(cfg, out, work, cfg["batch"], cfg["train_s"], cfg["pool_seeds"], "train.log", checkpoint)
        save()
        emit({"new": result["new"]})
    old_clip = (result.get("old") or {}).get("s_per_clip")
    new_clip = (result.get("new") or {}).get("s_per_clip")
    result["speedup_per_clip"] = {
        "vs_old_measured": old_clip / new_clip if old_clip and new_clip else None,
        "vs_issue_0.39_s": ISSUE_S_PER_STEP / new_clip if new_clip else None,
        "target": ">= 10x (<= 0.039 s per clip)"}
    save()
    if "c" not in skip:
        result["dense"] = dense_stage(cfg, work, checkpoint, lambda part: save(part, "dense"))
    save()
    emit({"result": {k: v for k, v in result.items() if k not in ("info",)}})
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
