"""Scaling of the loop-closure back end with the number of keyframes N; one JSON document on stdout.

Parts (``--parts``), each measured at every N of ``--keyframes`` (default 100 1000 5000):

- ``retrieval``: BoW place recognition (``fgslam.loop.bow.PlaceRecognizer``): time per keyframe of
  ``detector.process`` (database add + query + DBoW2 island / consistency logic) while the database
  grows to N keyframes; mean / p95 / max over all N keyframes and over the last 10 % (database ~N).
  Keyframe BoW vectors: ``--base-images`` rendered street-loop views (ORB + quantisation, timed as
  ``describe``) repeated in laps, the word ids of each lap after the first permuted (one permutation
  per lap), so consecutive keyframes look alike (the prior-score test passes and queries run) while
  laps describe distinct places with real word statistics (as in tools/bench_retrieval.py).
- ``pose_graph``: one ``optimize_sim3_pose_graph`` call over N keyframes on laps of a closed path
  (:func:`lap_trajectory`) with the drift and true + false loop simulation of
  tools/bench_pose_graph.py (one loop per ``--loop-every`` revisit keyframes); ATE before / after.
- ``global_ba``: ``fgslam.backend.global_ba.global_bundle_adjustment`` on a synthetic
  patch-graph problem (:func:`make_ba_problem`): the same kind of lap trajectory, 96 patches per
  keyframe (centres uniform in a 640 x 480 image, depths uniform in 2-30 m) observed in the frames
  at most 5 positions before and after (in-image projections only, 0.5 px Gaussian noise) plus
  two-way loop edges between revisits; perturbed poses and inverse depths as the start, the first
  two keyframes fixed (gauge). Reports seconds, iterations, edges, time per iteration and the
  reprojection RMS per pixel axis at the truth, the start and the result (vs. the noise sigma).
  Each N runs in a child process (unless ``--in-process``) watched for ``--ba-timeout-s`` and
  ``--ba-memory-gb`` of resident memory; a child that is stopped or fails is recorded, not fatal.
  ``--ba-option iterations=1 --ba-option robust_rounds=1`` (GlobalBAConfig fields) times one step.
  Each entry has the seconds and process CPU seconds (``cpu_s``: comparable under load), LM steps
  (= damped solves), linearisations, solve time per step (GTSAM elimination and damping), factor
  construction time per linearisation, the time per stage, peak memory and the final RMS.

Every entry carries ``os.getloadavg()`` before and after it (the machine is shared). Progress goes
to stderr.

    OMP_NUM_THREADS=1 .venv/bin/python tools/bench_loop_scaling.py [--keyframes 100 1000 5000]
        [--parts retrieval pose_graph global_ba] [--seed 0]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
import resource
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

logger = logging.getLogger("bench_loop_scaling")

TOOLS_DIR = Path(__file__).resolve().parent
PARTS = ("retrieval", "pose_graph", "global_ba")
RECENT_FRACTION = 0.1  # "at database size ~N": statistics over the last 10 % of the keyframes
RSS_POLL_S = 0.25  # how often the parent reads the child's resident memory


# ------------------------------------------------------------------------------------------ helpers


def _load_tool(name: str):
    """Import a sibling benchmark script (tools/ is not a package) once per process."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, TOOLS_DIR / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses resolve their module through sys.modules
    spec.loader.exec_module(module)
    return module


def _loadavg() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _ms_stats(seconds: np.ndarray) -> dict:
    ms = 1e3 * np.asarray(seconds, dtype=np.float64)
    if ms.size == 0:
        return {"count": 0}
    return {"count": int(ms.size), "mean_ms": round(float(ms.mean()), 4),
            "p95_ms": round(float(np.percentile(ms, 95)), 4), "max_ms": round(float(ms.max()), 4)}


def _peak_rss_gb() -> float:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 3)  # ru_maxrss in KiB


# ------------------------------------------------------------------------------------------ trajectory


@dataclass
class LapConfig:
    """Laps of a closed, slightly wavy loop (world y axis vertical, pointing down like the camera's)."""

    step_m: float = 1.0  # distance between consecutive keyframes
    min_lap_keyframes: int = 50  # keyframes per lap: N / 2 clipped to [min, max] (>= 2 laps)
    max_lap_keyframes: int = 500
    shape_amplitude: float = 0.3  # radius r(a) = r0 (1 + A sin 2a): a rounded, non-circular loop
    lap_offset_sigma_m: float = 0.5  # per-lap radial offset (revisits are near, not identical)
    height_wobble_m: float = 0.3  # vertical sinusoid amplitude along a lap


def lap_trajectory(n: int, cfg: LapConfig, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """``(T_WC (n, 4, 4) rigid camera-to-world poses, keyframes per lap)``: the camera z axis looks
    along the direction of travel, its y axis as close to the world's vertical (+y) as it allows."""
    lap_kf = int(np.clip(n // 2, cfg.min_lap_keyframes, cfg.max_lap_keyframes))
    dense = np.linspace(0.0, 2 * np.pi, 4096)
    shape = 1.0 + cfg.shape_amplitude * np.sin(2 * dense)
    xy = np.column_stack([shape * np.sin(dense), shape * np.cos(dense)])
    r0 = lap_kf * cfg.step_m / np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1))  # perimeter = lap length

    k = np.arange(n + 1)  # one extra sample for the last heading
    a = 2 * np.pi * k / lap_kf
    offset = rng.normal(0.0, cfg.lap_offset_sigma_m, n // lap_kf + 2)[k // lap_kf]
    r = r0 * (1.0 + cfg.shape_amplitude * np.sin(2 * a)) + offset
    pos = np.column_stack([r * np.sin(a), cfg.height_wobble_m * np.sin(3 * a), r * np.cos(a)])
    z = np.diff(pos, axis=0)
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    T_WC = np.tile(np.eye(4), (n, 1, 1))
    T_WC[:, :3, :3] = np.stack([x, y, z], axis=-1)
    T_WC[:, :3, 3] = pos[:n]
    return T_WC, lap_kf


# ------------------------------------------------------------------------------------------ retrieval


def base_bows(recognizer, n_images: int) -> tuple[list, np.ndarray]:
    """BoW vectors of ``n_images`` street-loop renders spread over one loop (seed 0) and the time of
    ``recognizer.describe`` (ORB + quantisation) per image."""
    from fgslam.io.synth import SynthSequence, default_config

    cfg = default_config("street-loop")
    cfg.seed = 0
    seq = SynthSequence(cfg)
    times = seq.frame_times()
    poses = seq.camera_poses(times[np.linspace(0, len(times) - 1, n_images).astype(int)])
    bows, seconds = [], []
    for T in poses:
        image = seq.render_view(T).image
        t0 = time.perf_counter()
        bows.append(recognizer.describe(image).bow)
        seconds.append(time.perf_counter() - t0)
    return bows, np.array(seconds)


def lap_bows(base: list, n: int, n_words: int, rng: np.random.Generator) -> list:
    """``n`` keyframe vectors: ``base`` repeated in laps, lap c >= 1 with its own word permutation."""
    relabel_words = _load_tool("bench_retrieval").relabel_words
    out, perm = [], None
    for i in range(n):
        lap, k = divmod(i, len(base))
        if lap > 0 and k == 0:
            perm = rng.permutation(n_words)
        out.append(relabel_words(base[k], perm) if lap > 0 else base[k])
    return out


def bench_retrieval(n: int, vocabulary, base: list, rng: np.random.Generator) -> dict:
    """Time ``PlaceRecognizer.detector.process`` for each of ``n`` keyframes (database grows to n)."""
    from fgslam.loop.bow import PlaceRecognizer

    load_before = _loadavg()
    recognizer = PlaceRecognizer(vocabulary=vocabulary)
    bows = lap_bows(base, n, vocabulary.n_words, rng)
    seconds = np.empty(n)
    status: dict[str, int] = {}
    for i, bow in enumerate(bows):
        t0 = time.perf_counter()
        result = recognizer.detector.process(i, bow, float(i))
        seconds[i] = time.perf_counter() - t0
        status[result.status] = status.get(result.status, 0) + 1
    recent = seconds[n - max(1, int(np.ceil(RECENT_FRACTION * n))):]
    return {"keyframes": n, "database_postings": int(sum(len(b) for b in bows)),
            "process_per_keyframe": _ms_stats(seconds), "process_per_keyframe_last_10pct": _ms_stats(recent),
            "total_s": round(float(seconds.sum()), 4), "status_counts": status,
            "load_average_before": load_before, "load_average_after": _loadavg()}


def run_retrieval(sizes: list[int], n_images: int, seed: int) -> dict:
    from fgslam.loop.bow import PlaceRecognizer
    from fgslam.loop.vocabulary import load_default_vocabulary

    vocabulary = load_default_vocabulary()
    base, describe_s = base_bows(PlaceRecognizer(vocabulary=vocabulary), n_images)
    describe_ms = 1e3 * float(np.mean(describe_s))
    entries = []
    for n in sizes:
        logger.info("retrieval: %d keyframes", n)
        entry = bench_retrieval(n, vocabulary, base, np.random.default_rng(seed))
        entry["describe_plus_process_mean_ms"] = round(describe_ms + entry["process_per_keyframe"]["mean_ms"], 4)
        entries.append(entry)
    return {"vocabulary_words": vocabulary.n_words, "base_images": n_images,
            "base_words_mean": round(float(np.mean([len(b) for b in base])), 1),
            "describe_per_image": _ms_stats(describe_s), "sizes": entries}


# ------------------------------------------------------------------------------------------ pose graph


def bench_pose_graph(n: int, seed: int, lap_cfg: LapConfig, loop_every: int) -> dict:
    """One Sim(3) pose-graph solve over ``n`` keyframes of drifted laps (bench_pose_graph's simulation)."""
    from fgslam.loop.pose_graph import PoseGraphConfig

    bpg = _load_tool("bench_pose_graph")
    rng = np.random.default_rng(seed)
    G, lap_kf = lap_trajectory(n, lap_cfg, rng)
    extent = float(np.max(np.ptp(G[:, :3, 3], axis=0)))
    sim = bpg.DriftSimConfig(stride=1, loop_every=loop_every, seed=seed,
                             false_loop_min_dist_m=min(bpg.DriftSimConfig.false_loop_min_dist_m, 0.5 * extent))
    frame_dt_s = sim.min_loop_gap_s / (0.5 * lap_kf)  # a revisit is at least half a lap later
    scn = bpg.simulate_kitti_drift(G, sim, frame_dt_s)
    load_before = _loadavg()
    out = bpg.run_scenario(scn, PoseGraphConfig())
    out.pop("result")
    out.update(keyframes_per_lap=lap_kf, laps=round(n / lap_kf, 2), path_length_m=round(n * lap_cfg.step_m, 1),
               load_average_before=load_before, load_average_after=_loadavg())
    return out


# ------------------------------------------------------------------------------------------ global BA


@dataclass
class BAScenarioConfig:
    """Synthetic patch-graph bundle adjustment problem (pixels, metres, radians)."""

    laps: LapConfig = field(default_factory=lambda: LapConfig(step_m=0.5))  # keyframe every 0.5 m
    patches_per_keyframe: int = 96
    window: int = 5  # a patch is observed in the frames at most this many positions before / after
    width: int = 640
    height: int = 480
    K: tuple[float, float, float, float] = (320.0, 320.0, 320.0, 240.0)  # fx, fy, cx, cy
    min_depth_m: float = 2.0
    max_depth_m: float = 30.0
    min_z_m: float = 1.0  # a patch is not tracked closer than this to the target camera
    pixel_noise_px: float = 0.5  # Gaussian noise sigma per pixel axis
    loop_every: int = 10  # every this many revisit keyframes get loop edges (both ways)
    fixed_keyframes: int = 2  # first keyframes held at the truth (monocular Sim(3) gauge)
    rot_noise_rad: float = 0.005  # start: per-pose rotation perturbation sigma
    trans_noise_m: float = 0.05  # start: per-pose translation perturbation sigma
    log_scale_noise: float = 0.01  # start: per-pose log-scale perturbation sigma
    inv_depth_noise_rel: float = 0.1  # start: relative inverse-depth perturbation sigma


@dataclass
class BAScenario:
    """Arrays of one problem (the fields of GlobalBAProblem) plus the truth."""

    T_WC: np.ndarray  # (F, 4, 4) start (perturbed) Sim(3) camera-to-world
    fixed: np.ndarray  # (F,) bool
    src: np.ndarray  # (N,) int64
    tgt: np.ndarray  # (N,) int64
    right: np.ndarray  # (N,) bool, all False (monocular)
    uv_src: np.ndarray  # (N, 2)
    uv: np.ndarray  # (N, 2) noisy observations
    weight: np.ndarray  # (N,)
    struct_idx: np.ndarray  # (N,) int64
    inv_depth: np.ndarray  # (P,) start (perturbed)
    K: np.ndarray  # (4,)
    T_WC_true: np.ndarray  # (F, 4, 4)
    inv_depth_true: np.ndarray  # (P,)
    n_loop_edges: int


def _sim3_exp_small(rng: np.random.Generator, n: int, cfg: BAScenarioConfig) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    D = np.tile(np.eye(4), (n, 1, 1))
    s = np.exp(rng.normal(0.0, cfg.log_scale_noise, n))
    D[:, :3, :3] = s[:, None, None] * Rotation.from_rotvec(rng.normal(0.0, cfg.rot_noise_rad, (n, 3))).as_matrix()
    D[:, :3, 3] = rng.normal(0.0, cfg.trans_noise_m, (n, 3))
    return D


def project_edges(T_WC: np.ndarray, inv_depth: np.ndarray, src: np.ndarray, tgt: np.ndarray,
                  uv_src: np.ndarray, struct_idx: np.ndarray, K) -> tuple[np.ndarray, np.ndarray]:
    """``(uv (N, 2), z (N,))``: patch centre ``uv_src`` of frame ``src`` at inverse depth
    ``inv_depth[struct_idx]`` projected into frame ``tgt`` (Sim(3) T_WC, pinhole K = fx, fy, cx, cy)."""
    fx, fy, cx, cy = K
    X = np.column_stack([(uv_src[:, 0] - cx) / fx, (uv_src[:, 1] - cy) / fy, np.ones(len(src))])
    X /= inv_depth[struct_idx][:, None]
    T_tgt_src = np.linalg.inv(T_WC)[tgt] @ T_WC[src] if len(src) else np.zeros((0, 4, 4))
    Xt = np.einsum("nij,nj->ni", T_tgt_src[:, :3, :3], X) + T_tgt_src[:, :3, 3]
    z = Xt[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.column_stack([fx * Xt[:, 0] / z + cx, fy * Xt[:, 1] / z + cy])
    return uv, z


def _residuals(scn: BAScenario, T_WC: np.ndarray, inv_depth: np.ndarray, weight: np.ndarray | None) -> np.ndarray:
    """(M, 2) pixel residuals of the edges with positive weight (all when None)."""
    uv, _ = project_edges(T_WC, inv_depth, scn.src, scn.tgt, scn.uv_src, scn.struct_idx, scn.K)
    keep = np.ones(len(uv), bool) if weight is None else np.asarray(weight) > 0
    return (uv - scn.uv)[keep]


def reprojection_rms(scn: BAScenario, T_WC: np.ndarray, inv_depth: np.ndarray,
                     weight: np.ndarray | None = None) -> float:
    """RMS per pixel axis of the residuals of the edges with positive weight (all when None)."""
    r = _residuals(scn, T_WC, inv_depth, weight)
    return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")


def median_error_px(scn: BAScenario, T_WC: np.ndarray, inv_depth: np.ndarray) -> float:
    """Median reprojection error norm (pixels) over all edges (robust to the few extreme ones)."""
    return float(np.median(np.linalg.norm(_residuals(scn, T_WC, inv_depth, None), axis=1)))


def make_ba_problem(n: int, cfg: BAScenarioConfig, seed: int) -> BAScenario:
    """Synthetic global BA over ``n`` keyframes (see the module docstring); edges are grouped by
    source frame, then target frame."""
    rng = np.random.default_rng(seed)
    T_true, lap_kf = lap_trajectory(n, cfg.laps, rng)
    P = cfg.patches_per_keyframe
    K = np.asarray(cfg.K, dtype=np.float64)
    uv_patch = rng.uniform([0.0, 0.0], [cfg.width, cfg.height], (n * P, 2))
    inv_depth_true = 1.0 / rng.uniform(cfg.min_depth_m, cfg.max_depth_m, n * P)

    # frame pairs: window neighbours, then loop pairs (revisit keyframe j <-> nearest earlier keyframe)
    pairs = [(k, k + o) for k in range(n) for o in range(-cfg.window, cfg.window + 1) if o and 0 <= k + o < n]
    n_window_pairs = len(pairs)
    pos = T_true[:, :3, 3]
    for j in range(lap_kf, n, cfg.loop_every):
        i = int(np.argmin(np.linalg.norm(pos[: j - lap_kf // 2] - pos[j], axis=1)))
        pairs += [(i, j), (j, i)]
    pairs = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    src = np.repeat(pairs[:, 0], P)
    tgt = np.repeat(pairs[:, 1], P)
    is_loop = np.repeat(np.arange(len(pairs)) >= n_window_pairs, P)
    struct_idx = src * P + np.tile(np.arange(P), len(pairs))
    uv_src = uv_patch[struct_idx]
    uv_true, z = project_edges(T_true, inv_depth_true, src, tgt, uv_src, struct_idx, K)
    inside = ((z > cfg.min_z_m) & (uv_true[:, 0] >= 0) & (uv_true[:, 0] < cfg.width)
              & (uv_true[:, 1] >= 0) & (uv_true[:, 1] < cfg.height))
    src, tgt, struct_idx = src[inside], tgt[inside], struct_idx[inside]
    uv_src, uv_true = uv_src[inside], uv_true[inside]
    uv = uv_true + rng.normal(0.0, cfg.pixel_noise_px, uv_true.shape)

    fixed = np.zeros(n, bool)
    fixed[: cfg.fixed_keyframes] = True
    T_start = T_true @ _sim3_exp_small(rng, n, cfg)
    T_start[fixed] = T_true[fixed]
    inv_depth = inv_depth_true * np.exp(rng.normal(0.0, cfg.inv_depth_noise_rel, n * P))
    return BAScenario(T_WC=T_start, fixed=fixed, src=src, tgt=tgt, right=np.zeros(len(src), bool),
                      uv_src=uv_src, uv=uv, weight=np.ones(len(src)), struct_idx=struct_idx,
                      inv_depth=inv_depth, K=K, T_WC_true=T_true, inv_depth_true=inv_depth_true,
                      n_loop_edges=int(is_loop[inside].sum()))


def bench_global_ba(n: int, seed: int, cfg: BAScenarioConfig, threads: int = 1, ba_options: dict | None = None) -> dict:
    """Build the problem for ``n`` keyframes and time one ``global_bundle_adjustment`` call
    (``GlobalBAConfig`` defaults with ``threads`` and the fields in ``ba_options``)."""
    from fgslam.core.config import from_dict
    from fgslam.backend.config import GlobalBAConfig
    from fgslam.backend.global_ba import GlobalBAProblem, global_bundle_adjustment

    t0 = time.perf_counter()
    scn = make_ba_problem(n, cfg, seed)
    build_s = time.perf_counter() - t0
    names = {f.name for f in fields(GlobalBAProblem)}
    problem = GlobalBAProblem(**{k: v for k, v in vars(scn).items() if k in names})
    ba_cfg = from_dict(GlobalBAConfig, {"threads": threads, **(ba_options or {})}, "--ba-option")
    entry = {"keyframes": n, "status": "ok", "patches": int(scn.inv_depth.size), "edges": int(scn.src.size),
             "loop_edges": scn.n_loop_edges, "edges_per_keyframe": round(scn.src.size / n, 1),
             "problem_build_s": round(build_s, 3), "pixel_noise_px": cfg.pixel_noise_px,
             "rms_px_at_truth": round(reprojection_rms(scn, scn.T_WC_true, scn.inv_depth_true), 4),
             "rms_px_start": round(reprojection_rms(scn, scn.T_WC, scn.inv_depth), 4),
             "median_error_px_at_truth": round(median_error_px(scn, scn.T_WC_true, scn.inv_depth_true), 4),
             "median_error_px_start": round(median_error_px(scn, scn.T_WC, scn.inv_depth), 4),
             "config": asdict(ba_cfg)}
    logger.info("global_ba: %d keyframes, %d edges: solving", n, scn.src.size)
    entry["load_average_before"] = _loadavg()
    c0, t0 = time.process_time(), time.perf_counter()
    res = global_bundle_adjustment(problem, ba_cfg)
    wall_s, cpu_s = time.perf_counter() - t0, time.process_time() - c0
    entry["load_average_after"] = _loadavg()
    T_WC = np.asarray(res.T_WC, dtype=np.float64)
    inv_depth = np.asarray(res.inv_depth, dtype=np.float64)
    robust = np.asarray(res.robust, dtype=np.float64)
    iterations = int(res.iterations)
    timings = dict(getattr(res, "timings", {}))
    linearizations = int(getattr(res, "linearizations", 0))
    entry.update(
        wall_s=round(wall_s, 3), cpu_s=round(cpu_s, 3), seconds=round(float(res.seconds), 3), iterations=iterations,
        seconds_per_iteration=round(float(res.seconds) / iterations, 4) if iterations else None,
        linear_solver=getattr(res, "linear_solver", ""), linearizations=linearizations,
        solve_s_per_step=round(timings["solve"] / iterations, 4) if iterations and "solve" in timings else None,
        construct_s_per_linearization=(round(timings["construct"] / linearizations, 4)
                                       if linearizations and "construct" in timings else None),
        timings_s={k: round(float(v), 3) for k, v in timings.items()},
        initial_cost=float(res.initial_cost), final_cost=float(res.final_cost),
        rms_px_final=round(reprojection_rms(scn, T_WC, inv_depth), 4),
        rms_px_final_inliers=round(reprojection_rms(scn, T_WC, inv_depth, robust), 4),
        median_error_px_final=round(median_error_px(scn, T_WC, inv_depth), 4),
        zero_weight_edges=int(np.sum(robust <= 0)), peak_rss_gb=_peak_rss_gb())
    return entry


def _rss_gb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return 0.0


def run_global_ba_isolated(n: int, seed: int, threads: int, timeout_s: float, memory_gb: float,
                           ba_options: dict | None = None) -> dict:
    """:func:`bench_global_ba` for ``n`` keyframes in a child process; stopped (and recorded) when it
    runs longer than ``timeout_s`` or its resident memory exceeds ``memory_gb``."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--in-process", "--parts", "global_ba",
           "--keyframes", str(n), "--seed", str(seed), "--threads", str(threads)]
    for key, value in (ba_options or {}).items():
        cmd += ["--ba-option", f"{key}={json.dumps(value)}"]
    if logger.isEnabledFor(logging.INFO):
        cmd.append("--verbose")
    load_before = _loadavg()
    t0 = time.perf_counter()
    child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak, stopped = 0.0, None
    while child.poll() is None:
        peak = max(peak, _rss_gb(child.pid))
        elapsed = time.perf_counter() - t0
        if elapsed > timeout_s or peak > memory_gb:
            stopped = (f"stopped after {elapsed:.0f} s (limit {timeout_s:.0f} s)" if elapsed > timeout_s
                       else f"stopped at {peak:.2f} GB resident memory (limit {memory_gb:.1f} GB)")
            child.kill()
            break
        time.sleep(RSS_POLL_S)
    out, err = child.communicate()
    elapsed = time.perf_counter() - t0
    sys.stderr.write(err)
    if stopped is None and child.returncode == 0:
        try:
            return json.loads(out)["global_ba"]["sizes"][0]
        except (ValueError, KeyError, IndexError) as exc:
            stopped = f"unreadable child output ({exc})"
    return {"keyframes": n, "status": stopped or f"child exited with code {child.returncode}",
            "elapsed_s": round(elapsed, 1), "peak_rss_gb_seen": round(peak, 3),
            "stderr_tail": err[-2000:], "load_average_before": load_before, "load_average_after": _loadavg()}


def run_global_ba(sizes: list[int], seed: int, in_process: bool, threads: int, timeout_s: float,
                  memory_gb: float, ba_options: dict | None = None) -> dict:
    """Every size in ``sizes``."""
    cfg = BAScenarioConfig()
    entries = []
    for n in sizes:
        logger.info("global_ba: %d keyframes", n)
        if not in_process:
            entry = run_global_ba_isolated(n, seed, threads, timeout_s, memory_gb, ba_options)
        else:
            try:
                entry = bench_global_ba(n, seed, cfg, threads, ba_options)
            except Exception as exc:  # recorded in the JSON: a failure at one size is a result too
                logger.exception("global_ba: %d keyframes failed", n)
                entry = {"keyframes": n, "status": f"{type(exc).__name__}: {exc}", "peak_rss_gb": _peak_rss_gb()}
        entries.append(entry)
    return {"scenario": asdict(cfg), "ba_options": ba_options or {}, "sizes": entries}


# ------------------------------------------------------------------------------------------ main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--keyframes", nargs="+", type=int, default=[100, 1000, 5000])
    ap.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the machine is shared)")
    ap.add_argument("--base-images", type=int, default=50, help="rendered images behind the retrieval BoW vectors")
    ap.add_argument("--loop-every", type=int, default=10, help="pose graph: one loop per this many revisit keyframes")
    ap.add_argument("--ba-timeout-s", type=float, default=180.0, help="global BA: stop a size after this long")
    ap.add_argument("--ba-memory-gb", type=float, default=6.0, help="global BA: stop a size above this resident memory")
    ap.add_argument("--ba-option", action="append", default=[], metavar="KEY=VALUE",
                    help="global BA: a GlobalBAConfig field (value parsed as YAML), e.g. iterations=1")
    ap.add_argument("--in-process", action="store_true", help="global BA in this process (no limits)")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(asctime)s %(name)s: %(message)s")
    logger.setLevel(logging.INFO if args.verbose else logging.WARNING)
    import torch
    import yaml

    torch.set_num_threads(args.threads)
    ba_options = {}
    for item in args.ba_option:
        key, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--ba-option {item!r}: expected KEY=VALUE")
        ba_options[key] = yaml.safe_load(value)
    report = {"command": ["tools/bench_loop_scaling.py"] + (sys.argv[1:] if argv is None else list(argv)),
              "cpu_count": os.cpu_count(), "torch_threads": args.threads, "seed": args.seed,
              "load_average_start": _loadavg()}
    for part in args.parts:
        print(f"bench_loop_scaling: {part} at {args.keyframes} keyframes", file=sys.stderr)
        t0 = time.perf_counter()
        if part == "retrieval":
            report[part] = run_retrieval(args.keyframes, args.base_images, args.seed)
        elif part == "pose_graph":
            lap_cfg = LapConfig()
            bench_pose_graph(min(args.keyframes), args.seed, lap_cfg, args.loop_every)  # warm-up: imports, caches
            report[part] = {"laps": asdict(lap_cfg), "loop_every": args.loop_every,
                            "sizes": [bench_pose_graph(n, args.seed, lap_cfg, args.loop_every) for n in args.keyframes]}
        else:
            report[part] = run_global_ba(args.keyframes, args.seed, args.in_process, args.threads,
                                         args.ba_timeout_s, args.ba_memory_gb, ba_options)
        report[part]["part_wall_s"] = round(time.perf_counter() - t0, 2)
    report["load_average_end"] = _loadavg()
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
