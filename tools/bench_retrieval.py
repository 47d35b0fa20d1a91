"""Benchmark of bag-of-words retrieval (fgslam.loop.bow); prints JSON to stdout.

Measures: vocabulary load time; ORB extraction and quantisation (BoW transform) time per image on
KITTI 00 frames (from ../shared/data when present) and on synthetic street-loop renders; database
add + query time per keyframe (LoopDetector.process and BowDatabase.query) at database sizes
100 / 1,000 / 5,000 (the large databases hold BoW vectors of real quantised images whose word ids
are permuted per copy, so they keep real word statistics but describe distinct places); and, unless
``--no-revisits``, precision / recall of loop detection on held-out synthetic sequences (seed 0,
never used for training) that run 25 % past their start, true revisits from ground-truth poses.

    python tools/bench_retrieval.py [--sizes 100,1000,5000] [--no-revisits]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from fgslam.loop.bow import LoopDetectionConfig, LoopDetector, same_place
from fgslam.loop.vocabulary import BowVector, Vocabulary, default_vocabulary_path
from fgslam.loop.features import OrbExtractor

KITTI_IMAGES = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti00_0-199" / "image_0"
# ground-truth "same place" per synthetic preset: (keyframe stride, radius m, max view angle deg)
REVISIT_SETUP = {"room-loop": (2, 0.5, 30.0), "street-loop": (2, 5.0, 30.0), "orbit": (2, 0.8, 30.0)}
REVISIT_EXTRA = 1.25          # sequences run this many loop periods


def _ms(seconds: float) -> float:
    return round(1e3 * seconds, 3)


def time_images(images, extractor, vocab) -> tuple[dict, list[BowVector]]:
    t_orb = t_bow = 0.0
    bows, n_feat = [], []
    for image in images:
        t0 = time.perf_counter()
        _, desc = extractor(image)
        t1 = time.perf_counter()
        bow, _ = vocab.transform(desc)
        t2 = time.perf_counter()
        t_orb, t_bow = t_orb + t1 - t0, t_bow + t2 - t1
        bows.append(bow)
        n_feat.append(len(desc))
    n = max(len(bows), 1)
    return {"images": len(bows), "resolution": list(images[0].shape[:2][::-1]) if len(images) else None,
            "features_mean": round(float(np.mean(n_feat)), 1) if n_feat else 0,
            "orb_ms_per_image": _ms(t_orb / n), "quantize_ms_per_image": _ms(t_bow / n)}, bows


def kitti_images(limit: int):
    import cv2

    files = sorted(KITTI_IMAGES.glob("*.png"))[:limit]
    return [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in files]


def synth_sequence(preset: str, frames_factor: float = 1.0):
    from fgslam.io.synth import SynthSequence, default_config

    cfg = default_config(preset)
    cfg.seed = 0
    cfg.frames = int(cfg.frames * frames_factor)
    return SynthSequence(cfg)


def relabel_words(b: BowVector, perm: np.ndarray) -> BowVector:
    """``b`` with its word ids mapped through the permutation ``perm`` (same weights): a new place
    with the word statistics of a real image."""
    words = perm[b.words]
    order = np.argsort(words)
    return BowVector(words[order].astype(np.int32), b.weights[order], b.n_features)


def permuted_bows(base: list[BowVector], n: int, n_words: int, rng) -> list[BowVector]:
    out = []
    for i in range(n):
        b = base[i % len(base)]
        out.append(relabel_words(b, rng.permutation(n_words)) if i >= len(base) else b)
    return out


def bench_database(vocab, base: list[BowVector], sizes: list[int], n_queries: int, rng) -> list[dict]:
    results = []
    for size in sizes:
        bows = permuted_bows(base, size + n_queries, vocab.n_words, rng)
        det = LoopDetector(vocab, LoopDetectionConfig())
        t0 = time.perf_counter()
        for i in range(size):
            det.process(i, bows[i])
        t_fill = time.perf_counter() - t0
        t_process = t_query = 0.0
        for i in range(size, size + n_queries):
            t0 = time.perf_counter()
            det.database.query(bows[i], det.cfg.max_results)
            t1 = time.perf_counter()
            det.process(i, bows[i])
            t_process += time.perf_counter() - t1
            t_query += t1 - t0
        results.append({"database_size": size, "postings": int(sum(len(b) for b in bows[:size])),
                        "fill_ms_per_keyframe": _ms(t_fill / size),
                        "query_ms": _ms(t_query / n_queries),
                        "process_ms_per_keyframe": _ms(t_process / n_queries)})
    return results


def revisits(vocab, extractor) -> dict:
    out = {}
    for preset, (stride, radius, angle) in REVISIT_SETUP.items():
        seq = synth_sequence(preset, REVISIT_EXTRA)
        times = seq.frame_times()[::stride]
        T_WC = seq.camera_poses(times)
        truth = same_place(T_WC, radius, angle)
        cfg = LoopDetectionConfig()
        det = LoopDetector(vocab, cfg)
        tp = fp = positives = raw_top1 = 0
        for i, (t, T) in enumerate(zip(times, T_WC)):
            bow, _ = vocab.transform(extractor(seq.render_view(T).image)[1])
            old = slice(0, max(i - cfg.min_gap_keyframes + 1, 0))
            has_revisit = bool(truth[i, old].any())
            positives += has_revisit
            if has_revisit:
                best = det.database.query(bow, 1, max_entry=i - cfg.min_gap_keyframes)
                raw_top1 += bool(best) and bool(truth[i, best[0].entry])
            r = det.process(i, bow, float(t))
            if r.status == "accepted":
                ok = bool(truth[i, r.candidates[0].kf_id])
                tp, fp = tp + ok, fp + (not ok)
        out[preset] = {"keyframes": len(times), "revisit_keyframes": positives, "accepted_true": tp,
                       "accepted_false": fp, "precision": round(tp / max(tp + fp, 1), 3),
                       "recall": round(tp / max(positives, 1), 3),
                       "raw_top1_recall": round(raw_top1 / max(positives, 1), 3),
                       "radius_m": radius, "max_angle_deg": angle, "keyframe_stride": stride}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="100,1000,5000")
    ap.add_argument("--queries", type=int, default=50, help="timed queries per database size")
    ap.add_argument("--images", type=int, default=50, help="images timed per source")
    ap.add_argument("--no-revisits", action="store_true")
    args = ap.parse_args()
    rng = np.random.default_rng(0)

    path = default_vocabulary_path()
    t0 = time.perf_counter()
    vocab = Vocabulary.load(path)
    t_load = time.perf_counter() - t0
    report = {"vocabulary": {"file": path.name, "bytes": path.stat().st_size, "words": vocab.n_words,
                             "branching": vocab.branching, "depth": vocab.depth,
                             "load_ms": _ms(t_load)}}
    extractor = OrbExtractor()
    base: list[BowVector] = []
    if KITTI_IMAGES.is_dir():
        report["kitti00"], base = time_images(kitti_images(args.images), extractor, vocab)
    seq = synth_sequence("street-loop")
    synth = [seq.render_view(T).image for T in seq.camera_poses(seq.frame_times()[::10][:args.images])]
    report["synthetic_street"], synth_bows = time_images(synth, extractor, vocab)
    base = base + synth_bows
    report["database"] = bench_database(vocab, base, [int(s) for s in args.sizes.split(",")],
                                        args.queries, rng)
    if not args.no_revisits:
        report["revisits"] = revisits(vocab, extractor)
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
