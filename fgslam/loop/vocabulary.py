"""Binary vocabulary for place recognition (after DBoW2, Galvez-Lopez & Tardos, T-RO 2012):
training, files, quantisation and BoW vectors (the database and loop detection: :mod:`fgslam.loop.bow`).

Vocabulary: a tree of branching ``k`` and depth ``L`` over 256-bit ORB descriptors, built by
hierarchical k-majority (k-medians in Hamming space: assign to the nearest centre, update each
centre bit to the majority bit of its members), seeded k-means++ style (next seed drawn with
probability proportional to the squared Hamming distance to the nearest seed). Leaves are the
words, numbered 0..W-1 in breadth-first order. Each word has the idf weight
``log(N / n_w)`` from the N training images (n_w images contain the word).

Quantisation descends the tree one level at a time for all descriptors at once (vectorised Hamming
distances: XOR of the descriptors viewed as 4 x uint64 and ``np.bitwise_count``); a descriptor
follows the nearest child (the lowest child index on ties), the same rule as in training, so every
training descriptor reaches the leaf it was clustered into.

BoW vector of an image: sparse ``(words ascending, weights)`` with tf-idf weights
``(n_wd / n_d) * idf_w`` normalised to unit L1 norm. Score (DBoW2 L1):
``s(v1, v2) = 1 - 0.5 * || v1/|v1| - v2/|v2| ||_1`` in [0, 1]; for non-negative unit-L1 vectors it
equals ``sum_w min(v1_w, v2_w)`` over the shared words, which the inverted index accumulates.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.config import MAX_COUNT, MAX_ITERATIONS, MAX_LEVELS, MAX_SEED, check_ranges, ranged
from ..core.errors import DataError, FormatError
from .features import DESCRIPTOR_BYTES

logger = logging.getLogger(__name__)

VOCABULARY_FORMAT_VERSION = 1
DEFAULT_VOCABULARY_FILE = "orb_vocab_synth_k10_d5.npz"  # in fgslam/loop/data/
_WORDS_PER_DESCRIPTOR = DESCRIPTOR_BYTES // 8  # descriptor viewed as uint64 words
_MAX_HAMMING = 8 * DESCRIPTOR_BYTES + 1        # larger than any Hamming distance (masks)
_CHUNK_ROWS = 1 << 15                          # descriptors per block in distance/bit-count work


# ----------------------------------------------------------------------------------- configs

@dataclass
class VocabularyTrainingConfig:
    """Hierarchical k-majority training tunables."""

    branching: int = ranged(10, ge=2, le=MAX_COUNT)  # children per node (k)
    depth: int = ranged(5, ge=1, le=MAX_LEVELS)  # levels below the root (L); at most k^L words
    max_iterations: int = ranged(10, ge=1, le=MAX_ITERATIONS)  # assign/update rounds of k-majority per node
    seed: int = ranged(0, ge=0, le=MAX_SEED)  # seeding of k-means++ draws

    def validate(self) -> None:
        check_ranges(self, "vocabulary.")


# ----------------------------------------------------------------------------------- Hamming

def _as_descriptors(desc: np.ndarray, what: str = "descriptors") -> np.ndarray:
    d = np.asarray(desc)
    if d.dtype != np.uint8 or d.ndim != 2 or d.shape[1] != DESCRIPTOR_BYTES:
        raise DataError(f"{what}: expected (N, {DESCRIPTOR_BYTES}) uint8 ORB descriptors, "
                        f"got {d.shape} {d.dtype}")
    return np.ascontiguousarray(d)


def _words64(desc: np.ndarray) -> np.ndarray:
    """(N, 32) uint8 -> (N, 4) uint64 view (same bits)."""
    return np.ascontiguousarray(desc).view(np.uint64).reshape(len(desc), _WORDS_PER_DESCRIPTOR)


def hamming_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) int32 Hamming distances between (N, 32) and (M, 32) uint8 descriptors."""
    a64, b64 = _words64(_as_descriptors(a)), _words64(_as_descriptors(b))
    out = np.empty((len(a64), len(b64)), np.int32)
    rows = max(1, _CHUNK_ROWS // max(1, len(b64)) * 8)
    for s in range(0, len(a64), rows):
        x = a64[s:s + rows, None, :] ^ b64[None, :, :]
        out[s:s + rows] = np.bitwise_count(x).sum(axis=-1, dtype=np.int32)
    return out


def _bit_sums(desc: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """(k, 256) float64: per cluster, the number of members with each bit set (MSB-first order of
    ``np.unpackbits``)."""
    sums = np.zeros((k, 8 * DESCRIPTOR_BYTES), np.float64)
    for s in range(0, len(desc), _CHUNK_ROWS):
        bits = np.unpackbits(desc[s:s + _CHUNK_ROWS], axis=1).astype(np.float32)
        onehot = np.zeros((k, len(bits)), np.float32)
        onehot[labels[s:s + _CHUNK_ROWS], np.arange(len(bits))] = 1.0
        sums += onehot @ bits
    return sums


# ----------------------------------------------------------------------------------- k-majority

def _seed_kmeanspp(desc: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of up to k distinct seeds (fewer if the descriptors have fewer distinct values):
    greedy k-means++ (each step draws ``2 + ln k`` candidates with probability proportional to the
    squared distance to the nearest seed and keeps the one that lowers the total potential most)."""
    n = len(desc)
    n_trials = 2 + int(np.log(k))
    seeds = [int(rng.integers(n))]
    d_min = hamming_matrix(desc, desc[seeds[0]:seeds[0] + 1])[:, 0].astype(np.float64)
    for _ in range(1, k):
        p = d_min * d_min
        total = p.sum()
        if total <= 0.0:                      # every descriptor equals a seed
            break
        cand = rng.choice(n, size=n_trials, p=p / total)
        d_cand = np.minimum(d_min[:, None], hamming_matrix(desc, desc[cand]))
        best = int(np.argmin(np.sum(d_cand * d_cand, axis=0)))
        seeds.append(int(cand[best]))
        d_min = d_cand[:, best]
    return np.array(seeds)


def kmajority(desc: np.ndarray, k: int, max_iterations: int, rng: np.random.Generator
              ) -> tuple[np.ndarray, np.ndarray]:
    """Cluster (N, 32) descriptors into at most k groups in Hamming space.

    Returns ``(centres (k', 32) uint8, labels (N,) int64)`` with k' <= k non-empty clusters and
    labels equal to the nearest centre (lowest index on ties) of the returned centres."""
    desc = _as_descriptors(desc)
    centres = desc[_seed_kmeanspp(desc, k, rng)]
    labels = np.argmin(hamming_matrix(desc, centres), axis=1)
    for _ in range(max_iterations):
        counts = np.bincount(labels, minlength=len(centres))
        keep = counts > 0
        sums = _bit_sums(desc, labels, len(centres))
        majority = (2.0 * sums[keep] > counts[keep, None]).astype(np.uint8)
        centres = np.packbits(majority, axis=1)
        new_labels = np.argmin(hamming_matrix(desc, centres), axis=1)
        if keep.all() and np.array_equal(new_labels, labels):
            break
        labels = new_labels
    used = np.unique(labels)                  # drop centres that lost all members
    remap = np.full(len(centres), -1, np.int64)
    remap[used] = np.arange(len(used))
    return centres[used], remap[labels]


# ----------------------------------------------------------------------------------- BoW vector

@dataclass(frozen=True, eq=False)
class BowVector:
    """Sparse BoW vector: ``words`` (M,) int32 ascending unique word ids, ``weights`` (M,) float64
    non-negative with sum 1 (empty when the image had no usable features); ``n_features`` = number of
    descriptors it was computed from."""

    words: np.ndarray
    weights: np.ndarray
    n_features: int = 0

    @staticmethod
    def empty() -> "BowVector":
        return BowVector(np.zeros(0, np.int32), np.zeros(0, np.float64), 0)

    def __len__(self) -> int:
        return len(self.words)


def l1_score(v1: BowVector, v2: BowVector) -> float:
    """DBoW2 L1 score ``1 - 0.5 * |v1/|v1|_1 - v2/|v2|_1|_1`` in [0, 1]; 0 if either is empty."""
    n1, n2 = float(np.abs(v1.weights).sum()), float(np.abs(v2.weights).sum())
    if n1 <= 0.0 or n2 <= 0.0:
        return 0.0
    _, i1, i2 = np.intersect1d(v1.words, v2.words, assume_unique=True, return_indices=True)
    a, b = v1.weights[i1] / n1, v2.weights[i2] / n2
    # over the shared words |a| + |b| - |a - b|; the words of one vector only cancel out
    return float(0.5 * np.sum(np.abs(a) + np.abs(b) - np.abs(a - b)))


# ----------------------------------------------------------------------------------- vocabulary

class Vocabulary:
    """Hierarchical binary vocabulary (tree arrays in breadth-first order).

    ``node_descriptors`` (M, 32) uint8 (row 0 = root, unused), ``child_start`` (M,) int32 index of the
    first child (children are contiguous), ``child_count`` (M,) int32 (0 for leaves), ``node_word``
    (M,) int32 word id of leaves (-1 for inner nodes), ``idf`` (W,) float64."""

    def __init__(self, node_descriptors: np.ndarray, child_start: np.ndarray, child_count: np.ndarray,
                 node_word: np.ndarray, idf: np.ndarray, branching: int, depth: int,
                 n_training_images: int = 0, source: str = "<memory>"):
        self.node_descriptors = _as_descriptors(node_descriptors, f"{source}: node_descriptors")
        self.child_start = np.asarray(child_start, np.int64)
        self.child_count = np.asarray(child_count, np.int64)
        self.node_word = np.asarray(node_word, np.int64)
        self.idf = np.asarray(idf, np.float64)
        self.branching, self.depth = int(branching), int(depth)
        self.n_training_images = int(n_training_images)
        self.source = source
        self._check()
        self._node64 = _words64(self.node_descriptors)

    def _check(self) -> None:
        m = len(self.node_descriptors)
        if not (len(self.child_start) == len(self.child_count) == len(self.node_word) == m) or m < 2:
            raise FormatError(f"{self.source}: tree arrays of different lengths or no nodes")
        leaves = self.child_count == 0
        words = self.node_word[leaves]
        if (np.any(self.child_count < 0) or np.any(self.child_count > self.branching)
                or np.any(self.node_word[~leaves] != -1)
                or not np.array_equal(np.sort(words), np.arange(len(self.idf)))):
            raise FormatError(f"{self.source}: inconsistent tree (child counts, word ids vs "
                              f"{len(self.idf)} idf weights)")
        inner = ~leaves
        last = self.child_start[inner] + self.child_count[inner]
        if np.any(self.child_start[inner] <= np.flatnonzero(inner)) or np.any(last > m):
            raise FormatError(f"{self.source}: child indices out of range")
        if not np.all(np.isfinite(self.idf)) or np.any(self.idf < 0):
            raise FormatError(f"{self.source}: idf weights must be finite and >= 0")

    @property
    def n_words(self) -> int:
        return len(self.idf)

    @property
    def n_nodes(self) -> int:
        return len(self.node_descriptors)

    def __repr__(self) -> str:
        return (f"Vocabulary(k={self.branching}, L={self.depth}, words={self.n_words}, "
                f"source={self.source!r})")

    # ------------------------------------------------------------------ quantisation
    def quantize(self, descriptors: np.ndarray, level: int | None = None) -> np.ndarray:
        """Leaf word id (N,) int64 of each (N, 32) descriptor; with ``level`` (1..depth) the node id
        reached at that level instead (for restricting feature matching to a shared node, as in
        DBoW2's direct index; branches shorter than ``level`` stop at their leaf)."""
        desc = _as_descriptors(descriptors)
        steps = self.depth if level is None else int(level)
        node = np.zeros(len(desc), np.int64)
        for s in range(0, len(desc), _CHUNK_ROWS):
            node[s:s + _CHUNK_ROWS] = self._descend(_words64(desc[s:s + _CHUNK_ROWS]), steps)
        return node if level is not None else self.node_word[node]

    def _descend(self, d64: np.ndarray, steps: int) -> np.ndarray:
        """Node ids reached after ``steps`` levels by (n, 4) uint64 descriptors."""
        k = self.branching
        offsets = np.arange(k)
        node = np.zeros(len(d64), np.int64)
        for _ in range(steps):
            count = self.child_count[node]
            active = np.flatnonzero(count > 0)
            if len(active) == 0:
                break
            first = self.child_start[node[active]]
            valid = offsets[None, :] < count[active, None]
            cand = np.where(valid, first[:, None] + offsets[None, :], first[:, None])
            dist = np.bitwise_count(d64[active, None, :] ^ self._node64[cand]).sum(-1, dtype=np.int32)
            dist[~valid] = _MAX_HAMMING
            node[active] = cand[np.arange(len(active)), np.argmin(dist, axis=1)]
        return node

    def bow_from_words(self, words: np.ndarray) -> BowVector:
        """tf-idf BoW vector (unit L1) from the (N,) leaf words of one image's descriptors."""
        n = len(words)
        if n == 0:
            return BowVector.empty()
        uniq, counts = np.unique(words, return_counts=True)
        w = counts / n * self.idf[uniq]
        total = w.sum()
        keep = w > 0.0
        if total <= 0.0:                         # only words present in every training image
            return BowVector(np.zeros(0, np.int32), np.zeros(0, np.float64), n)
        return BowVector(uniq[keep].astype(np.int32), w[keep] / total, n)

    def transform(self, descriptors: np.ndarray) -> tuple[BowVector, np.ndarray]:
        """``(BoW vector, leaf word id (N,) of each descriptor)`` of one image."""
        words = self.quantize(descriptors)
        return self.bow_from_words(words), words

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> None:
        """Compact binary file (``np.savez_compressed``)."""
        np.savez_compressed(
            path, format_version=np.int32(VOCABULARY_FORMAT_VERSION), descriptor=np.array("ORB"),
            branching=np.int32(self.branching), depth=np.int32(self.depth),
            n_training_images=np.int64(self.n_training_images),
            node_descriptors=self.node_descriptors, child_start=self.child_start.astype(np.int32),
            child_count=self.child_count.astype(np.uint8 if self.branching < 256 else np.int32),
            node_word=self.node_word.astype(np.int32), idf=self.idf.astype(np.float32))

    @staticmethod
    def load(path: str | Path) -> "Vocabulary":
        required = ("branching", "depth", "node_descriptors", "child_start", "child_count", "node_word", "idf")
        data = read_versioned_npz(path, "vocabulary", required, VOCABULARY_FORMAT_VERSION)
        return Vocabulary(data["node_descriptors"], data["child_start"], data["child_count"],
                          data["node_word"], data["idf"], int(data["branching"]), int(data["depth"]),
                          int(data.get("n_training_images", 0)), source=str(path))


def read_versioned_npz(path: str | Path, what: str, required: tuple[str, ...], version: int) -> dict[str, np.ndarray]:
    """The arrays of a versioned ``.npz`` data file (``what``: a vocabulary, VLAD centres), read without
    pickle: DataError when it is missing, FormatError when it is unreadable, lacks ``format_version`` or
    one of ``required``, or has another format version (each naming the file)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: {what} file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {key: z[key] for key in z.files}
    except (OSError, ValueError) as exc:
        raise FormatError(f"{path}: not a readable .npz {what} ({exc})") from exc
    missing = [key for key in ("format_version", *required) if key not in data]
    if missing:
        raise FormatError(f"{path}: missing arrays {missing}")
    if int(data["format_version"]) != version:
        raise FormatError(f"{path}: format_version {int(data['format_version'])} (this fgslam reads {version})")
    return data


def default_vocabulary_path() -> Path:
    """Path of the vocabulary shipped in ``fgslam/loop/data/``."""
    return Path(str(resources.files(__package__).joinpath("data", DEFAULT_VOCABULARY_FILE)))


@lru_cache(maxsize=1)
def load_default_vocabulary() -> Vocabulary:
    """The vocabulary shipped with fgslam (loaded once per process; treat it as read-only)."""
    return Vocabulary.load(default_vocabulary_path())


def load_vocabulary(name_or_path: str) -> Vocabulary:
    """``'default'`` -> :func:`load_default_vocabulary`, otherwise the .npz file at that path."""
    return load_default_vocabulary() if name_or_path == "default" else Vocabulary.load(name_or_path)


# ----------------------------------------------------------------------------------- training

def build_tree(descriptors: np.ndarray, cfg: VocabularyTrainingConfig
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Hierarchical k-majority over (N, 32) descriptors.

    Returns ``(node_descriptors, child_start, child_count, node_word, leaf_word)`` where the first
    four are the tree arrays of :class:`Vocabulary` and ``leaf_word`` (N,) is the word each training
    descriptor was clustered into (equal to its quantisation). A node becomes a leaf at depth L, or
    when its descriptors are all equal; a node with at most k distinct descriptors gets one child
    per distinct descriptor."""
    cfg.validate()
    desc = _as_descriptors(descriptors, "training descriptors")
    if len(desc) == 0:
        raise DataError("vocabulary training: no descriptors")
    rng = np.random.default_rng(cfg.seed)
    k = cfg.branching
    node_desc = [np.zeros(DESCRIPTOR_BYTES, np.uint8)]
    child_start, child_count = [0], [0]
    leaf_node = np.zeros(len(desc), np.int64)
    queue = deque([(0, np.arange(len(desc)), 0)])
    while queue:
        node, idx, level = queue.popleft()
        if level == cfg.depth:
            leaf_node[idx] = node
            continue
        sub = desc[idx]
        uniq, inverse = np.unique(sub, axis=0, return_inverse=True)
        if len(uniq) <= 1:
            leaf_node[idx] = node
            continue
        if len(uniq) <= k:
            centres, labels = uniq, inverse.reshape(-1)
        else:
            centres, labels = kmajority(sub, k, cfg.max_iterations, rng)
        # the descent rule (nearest centre, lowest index on ties) must reproduce the labels
        labels = np.argmin(hamming_matrix(sub, centres), axis=1)
        first = len(node_desc)
        child_start[node], child_count[node] = first, len(centres)
        order = np.argsort(labels, kind="stable")
        bounds = np.searchsorted(labels[order], np.arange(len(centres) + 1))
        for j in range(len(centres)):
            node_desc.append(centres[j])
            child_start.append(0)
            child_count.append(0)
            members = idx[order[bounds[j]:bounds[j + 1]]]
            if len(members) == 0:               # a centre nobody is nearest to: empty leaf
                continue
            queue.append((first + j, members, level + 1))
    child_count_arr = np.array(child_count, np.int64)
    leaves = np.flatnonzero(child_count_arr == 0)
    node_word = np.full(len(child_count_arr), -1, np.int64)
    node_word[leaves] = np.arange(len(leaves))
    return (np.stack(node_desc), np.array(child_start, np.int64), child_count_arr, node_word,
            node_word[leaf_node])


def train_vocabulary(image_descriptors: Sequence[np.ndarray], cfg: VocabularyTrainingConfig | None = None
                     ) -> Vocabulary:
    """Vocabulary from the ORB descriptors of a set of training images (one (N_i, 32) array each);
    idf_w = log(N_images / images containing w) (words no training image contains get log(N))."""
    cfg = cfg or VocabularyTrainingConfig()
    arrays = [_as_descriptors(d, f"training image {i}") for i, d in enumerate(image_descriptors)]
    n_images = len(arrays)
    if n_images == 0:
        raise DataError("vocabulary training: no images")
    image_of = np.repeat(np.arange(n_images), [len(d) for d in arrays])
    node_desc, child_start, child_count, node_word, leaf_word = build_tree(np.concatenate(arrays), cfg)
    n_words = int(node_word.max()) + 1
    pairs = np.unique(image_of * n_words + leaf_word)      # (image, word) present
    images_with = np.bincount(pairs % n_words, minlength=n_words)
    idf = np.log(n_images / np.maximum(images_with, 1))
    logger.info("vocabulary: %d descriptors from %d images -> %d words (%d nodes)",
                len(leaf_word), n_images, n_words, len(node_desc))
    return Vocabulary(node_desc, child_start, child_count, node_word, idf, cfg.branching, cfg.depth,
                      n_images)

