"""Train an ORB bag-of-words vocabulary (fgslam.loop.vocabulary) and save it as a compact .npz.

Two image sources:
  * synthetic renders of fgslam's own generator (default; this is how the shipped vocabulary
    ``fgslam/loop/data/orb_vocab_synth_k10_d5.npz`` is made, so it may be redistributed):
        python tools/train_vocabulary.py --out fgslam/loop/data/orb_vocab_synth_k10_d5.npz
  * a user's own images (any folder tree of PNG/JPG files, e.g. frames of their own drives):
        python tools/train_vocabulary.py --images /path/to/frames --stride 5 --out my_vocab.npz
    then set ``vocabulary: my_vocab.npz`` in the BoW config.

The VLAD centres of the optional XFeat loop features (``loop_closure.features.kind: xfeat``,
:mod:`fgslam.loop.vlad`; needs the ``xfeat`` extra), from the same synthetic renders:
    python tools/train_vocabulary.py --xfeat-centres 64 --out fgslam/loop/data/xfeat_vlad_synth_k64.npz

Prints a JSON summary (images, descriptors, words, timings, file size) to stdout.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path


from fgslam.loop.vocabulary import VocabularyTrainingConfig, train_vocabulary
from fgslam.loop.features import OrbConfig, OrbExtractor

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm")


def synthetic_images(presets: list[str], seeds: list[int], stride: int):
    """Yield grey float images of fgslam's synthetic presets (every ``stride``-th frame)."""
    from fgslam.io.synth import SynthSequence, default_config

    for preset in presets:
        for seed in seeds:
            cfg = default_config(preset)
            cfg.seed = seed
            seq = SynthSequence(cfg)
            times = seq.frame_times()[::stride]
            for T_WC in seq.camera_poses(times):
                yield seq.render_view(T_WC).image


def folder_images(root: Path, stride: int):
    import cv2

    files = sorted(p for p in root.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise SystemExit(f"train_vocabulary: no images under {root}")
    for path in files[::stride]:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise SystemExit(f"train_vocabulary: cannot read {path}")
        yield image


def _images(args):
    if args.images is not None:
        return folder_images(args.images, args.stride), str(args.images)
    seeds = [int(s) for s in args.seeds.split(",")]
    return synthetic_images(args.presets.split(","), seeds, args.stride), f"synthetic presets {args.presets} seeds {seeds}"


def train_xfeat_centres(args) -> int:
    """Spherical k-means VLAD centres of XFeat descriptors (``--xfeat-centres K``)."""
    import numpy as np
    import torch

    from fgslam.loop.features import XFeatConfig, XFeatExtractor
    from fgslam.loop.vlad import CentreTrainingConfig, train_centres

    torch.set_num_threads(1)
    extractor = XFeatExtractor(XFeatConfig())
    images, source = _images(args)
    t0 = time.perf_counter()
    descriptors = [d for d in (extractor(img)[1] for img in images) if len(d)]
    t_features = time.perf_counter() - t0
    cfg = CentreTrainingConfig(k=args.xfeat_centres, seed=args.seed)
    t0 = time.perf_counter()
    centres = train_centres(np.concatenate(descriptors), cfg)
    t_train = time.perf_counter() - t0
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    centres.save(out, n_training_images=len(descriptors))
    print(json.dumps({
        "out": str(out), "bytes": out.stat().st_size, "source": source, "stride": args.stride,
        "images": len(descriptors), "descriptors": int(sum(len(d) for d in descriptors)), "centres": cfg.k,
        "iterations": cfg.max_iterations, "features_s": round(t_features, 2), "train_s": round(t_train, 2),
    }, indent=2))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="output .npz")
    ap.add_argument("--images", type=Path, help="folder of training images (default: synthetic renders)")
    ap.add_argument("--presets", default="room-loop,street-loop,orbit")
    ap.add_argument("--seeds", default="1,2,3", help="synthetic scene seeds (seed 0 is kept for tests)")
    ap.add_argument("--stride", type=int, default=5, help="use every n-th frame")
    ap.add_argument("--branching", type=int, default=VocabularyTrainingConfig.branching)
    ap.add_argument("--depth", type=int, default=VocabularyTrainingConfig.depth)
    ap.add_argument("--iterations", type=int, default=VocabularyTrainingConfig.max_iterations)
    ap.add_argument("--seed", type=int, default=0, help="k-means++ seeding")
    ap.add_argument("--n-features", type=int, default=OrbConfig.n_features)
    ap.add_argument("--xfeat-centres", type=int, default=0, metavar="K",
                    help="train K VLAD centres of XFeat descriptors (fgslam.loop.vlad) instead")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING)
    if args.xfeat_centres:
        return train_xfeat_centres(args)

    extractor = OrbExtractor(OrbConfig(n_features=args.n_features))
    images, source = _images(args)
    t0 = time.perf_counter()
    descriptors = [d for d in (extractor(img)[1] for img in images) if len(d)]
    t_features = time.perf_counter() - t0
    cfg = VocabularyTrainingConfig(branching=args.branching, depth=args.depth,
                                   max_iterations=args.iterations, seed=args.seed)
    t0 = time.perf_counter()
    vocab = train_vocabulary(descriptors, cfg)
    t_train = time.perf_counter() - t0
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    vocab.save(out)
    print(json.dumps({
        "out": str(out), "bytes": out.stat().st_size, "source": source, "stride": args.stride,
        "images": len(descriptors), "descriptors": int(sum(len(d) for d in descriptors)),
        "branching": cfg.branching, "depth": cfg.depth, "iterations": cfg.max_iterations,
        "words": vocab.n_words, "nodes": vocab.n_nodes,
        "features_s": round(t_features, 2), "train_s": round(t_train, 2),
    }, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
