"""Stored map load time (issue 25: a map of 5,000 keyframes loads in under 5 s); prints one JSON object.

Writes a synthetic map of ``--keyframes`` keyframes with ``--features`` features each (the size of the
7-Scenes RGB-D maps: about 630 features and 300 BoW words per keyframe), then times, in CPU and wall
seconds, :func:`fgslam.export.mapfile.save_stored_map`, :func:`~fgslam.export.mapfile.load_stored_map`
and the localiser's set-up on it (retrieval database and per-keyframe world points:
:class:`fgslam.localize.localizer.MapLocalizer`), and checks that a second save gives the same bytes.

Usage:
  nice -n 5 .venv/bin/python tools/bench_mapfile.py --work /tmp/bench_mapfile [--keyframes 5000] [--features 650]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np


def synthetic_map(n_kf: int, n_feat: int, n_words: int, vocabulary_words: int, seed: int = 0):
    from fgslam.export.mapfile import StoredMap

    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n_kf, 1, 1))
    T[:, :3, 3] = np.cumsum(rng.normal(scale=0.02, size=(n_kf, 3)), axis=0)
    n = n_kf * n_feat
    X = rng.uniform(-1, 1, size=(n, 3)).astype(np.float32)
    X[:, 2] += 2.0
    X[rng.random(n) < 0.25] = np.nan
    words_list = [np.unique(rng.integers(0, vocabulary_words, size=n_words)).astype(np.int32) for _ in range(n_kf)]
    ptr = np.concatenate([[0], np.cumsum([len(w) for w in words_list])])
    weights = np.concatenate([np.full(len(w), 1.0 / len(w)) for w in words_list])
    meta = {"family": "patch", "sensor": "rgbd", "metric": True,
            "camera": {"K": [585.0, 585.0, 320.0, 240.0], "width": 640, "height": 480},
            "features": {"image_scale": 0.5, "K": [292.5, 292.5, 159.75, 119.75], "width": 320, "height": 240,
                         "vocabulary": "default", "orb": {}},
            "config": {}, "dataset": {"name": "synthetic"}, "groundtruth_alignment": None}
    return StoredMap(meta, np.arange(n_kf), np.arange(n_kf) / 30.0, np.arange(n_kf), T,
                     np.arange(n_kf + 1) * n_feat, rng.uniform(0, 320, size=(n, 2)),
                     rng.integers(0, 256, size=(n, 32), dtype=np.uint8), X, ptr, np.concatenate(words_list),
                     weights, np.zeros((0, 3)), np.zeros((0, 3)), [], [], np.zeros((0, 2)))


def timed(fn):
    c, w = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.process_time() - c, time.perf_counter() - w


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True, type=Path)
    ap.add_argument("--keyframes", type=int, default=5000)
    ap.add_argument("--features", type=int, default=650)
    ap.add_argument("--words", type=int, default=300)
    args = ap.parse_args()
    from fgslam.export.mapfile import load_stored_map, save_stored_map
    from fgslam.localize.localizer import MapLocalizer
    from fgslam.loop.vocabulary import load_vocabulary

    args.work.mkdir(parents=True, exist_ok=True)
    n_vocab = load_vocabulary("default").n_words
    stored = synthetic_map(args.keyframes, args.features, args.words, n_vocab)
    path, again = args.work / "map.fgmap", args.work / "again.fgmap"
    _, save_cpu, save_wall = timed(lambda: save_stored_map(path, stored))
    del stored
    loaded, load_cpu, load_wall = timed(lambda: load_stored_map(path))
    _, setup_cpu, setup_wall = timed(lambda: MapLocalizer(loaded))
    save_stored_map(again, loaded)
    print(json.dumps({
        "keyframes": args.keyframes, "features_per_keyframe": args.features, "words_per_keyframe": args.words,
        "file_mib": path.stat().st_size / 2**20,
        "save_cpu_s": save_cpu, "save_wall_s": save_wall,
        "load_cpu_s": load_cpu, "load_wall_s": load_wall,
        "localizer_setup_cpu_s": setup_cpu, "localizer_setup_wall_s": setup_wall,
        "load_and_setup_wall_s": load_wall + setup_wall,
        "resave_identical": path.read_bytes() == again.read_bytes(),
        "load_average": list(os.getloadavg()),
    }))


if __name__ == "__main__":
    main()
