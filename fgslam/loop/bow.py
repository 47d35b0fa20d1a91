"""Bag of binary words for place recognition (after DBoW2, Galvez-Lopez & Tardos, T-RO 2012).

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

Database: an inverted index (word -> entries with their weights) that grows one keyframe at a time;
:class:`LoopDetector` adds the DBoW2 loop logic: a minimum gap to recent keyframes, scores
normalised by the score against the previous keyframe, grouping of neighbouring candidates into
islands, and temporal consistency (a loop needs several consecutive consistent detections).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Sequence

import numpy as np

from ..config import MAX_COUNT, MAX_ITERATIONS, MAX_KEYFRAMES, MAX_LEVELS, MAX_SCALAR, MAX_SEED, check_ranges, ranged
from ..errors import DataError, FormatError
from .features import DESCRIPTOR_BYTES, OrbConfig

logger = logging.getLogger(__name__)

VOCABULARY_FORMAT_VERSION = 1
DEFAULT_VOCABULARY_FILE = "orb_vocab_synth_k10_d5.npz"  # in fgslam/loop/data/
_WORDS_PER_DESCRIPTOR = DESCRIPTOR_BYTES // 8  # descriptor viewed as uint64 words
_MAX_HAMMING = 8 * DESCRIPTOR_BYTES + 1        # larger than any Hamming distance (masks)
_CHUNK_ROWS = 1 << 15                          # descriptors per block in distance/bit-count work
_INDEX_BUFFER_POSTINGS = 1 << 15              # postings buffered before they join the sorted index


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


@dataclass
class LoopDetectionConfig:
    """DBoW2-style loop detection thresholds (keyframe counts are database entries)."""

    min_features: int = ranged(50, ge=0, le=MAX_COUNT)  # keyframes with fewer ORB features neither query nor count
    min_gap_keyframes: int = ranged(30, ge=0, le=MAX_KEYFRAMES)  # candidates must be at least this many keyframes older
    min_gap_seconds: float = ranged(0.0, ge=0, le=MAX_SCALAR)  # ... and at least this many seconds older (when timed)
    max_results: int = ranged(50, ge=1, le=MAX_KEYFRAMES)  # best raw-scored entries examined per query
    min_prior_score: float = ranged(0.005, ge=0, le=1)  # skip the query when s(current, previous kf) is below this
    min_normalized_score: float = ranged(0.6, ge=0, le=MAX_SCALAR)  # s(current, candidate) / s(current, previous kf) threshold
    # (DBoW2 uses 0.3; 0.6 gave precision 1.0 at recall 0.88-0.97 on held-out synthetic revisits)
    island_max_gap: int = ranged(3, ge=0, le=MAX_KEYFRAMES)  # candidates at most this many keyframes apart form one island
    min_consistent: int = ranged(3, ge=1, le=MAX_KEYFRAMES)  # consecutive queries with consistent islands to accept
    consistency_max_gap: int = ranged(5, ge=0, le=MAX_KEYFRAMES)  # keyframes between islands of consecutive queries

    def validate(self) -> None:
        check_ranges(self, "detection.")


@dataclass
class BowConfig:
    """Everything the BoW loop detector needs: features, vocabulary file, detection thresholds."""

    orb: OrbConfig = field(default_factory=OrbConfig)
    vocabulary: str = "default"        # 'default' (shipped with fgslam) or a path to a .npz file
    detection: LoopDetectionConfig = field(default_factory=LoopDetectionConfig)


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
        path = Path(path)
        if not path.is_file():
            raise DataError(f"{path}: vocabulary file not found")
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {key: z[key] for key in z.files}
        except (OSError, ValueError) as exc:
            raise FormatError(f"{path}: not a readable .npz vocabulary ({exc})") from exc
        required = ("format_version", "branching", "depth", "node_descriptors", "child_start",
                    "child_count", "node_word", "idf")
        missing = [key for key in required if key not in data]
        if missing:
            raise FormatError(f"{path}: missing arrays {missing}")
        if int(data["format_version"]) != VOCABULARY_FORMAT_VERSION:
            raise FormatError(f"{path}: format_version {int(data['format_version'])} "
                              f"(this fgslam reads {VOCABULARY_FORMAT_VERSION})")
        return Vocabulary(data["node_descriptors"], data["child_start"], data["child_count"],
                          data["node_word"], data["idf"], int(data["branching"]), int(data["depth"]),
                          int(data.get("n_training_images", 0)), source=str(path))


def default_vocabulary_path() -> Path:
    """Path of the vocabulary shipped in ``fgslam/loop/data/``."""
    from importlib import resources

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


# ----------------------------------------------------------------------------------- database

@dataclass(frozen=True)
class QueryResult:
    """One database match: ``entry`` = insertion index, ``kf_id`` = caller's keyframe id,
    ``score`` = DBoW2 L1 score in [0, 1]."""

    entry: int
    kf_id: int
    score: float


class BowDatabase:
    """Inverted index over L1-normalised BoW vectors, grown one keyframe at a time.

    Postings live in a word-sorted CSR block (``indptr`` over the vocabulary) plus a small append
    buffer of the latest keyframes, inserted into the block once it holds a few thousand postings
    (one O(postings) copy); a query gathers the postings of its words with vectorised range indexing
    and accumulates ``min(q_w, e_w)`` per entry."""

    def __init__(self, n_words: int):
        self.n_words = int(n_words)
        self._kf_ids: list[int] = []
        self._timestamps: list[float] = []
        self._indptr = np.zeros(self.n_words + 1, np.int64)
        self._entry = np.zeros(0, np.int64)
        self._weight = np.zeros(0, np.float64)
        self._buffer: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._buffered = 0

    def __len__(self) -> int:
        return len(self._kf_ids)

    def kf_id(self, entry: int) -> int:
        return self._kf_ids[entry]

    def timestamp(self, entry: int) -> float:
        return self._timestamps[entry]

    def add(self, kf_id: int, bow: BowVector, timestamp: float = math.nan) -> int:
        """Append one keyframe (an empty vector is stored too, so entries count keyframes);
        returns its entry index."""
        entry = len(self._kf_ids)
        if len(bow.words) and (bow.words.min() < 0 or bow.words.max() >= self.n_words):
            raise DataError(f"BowDatabase.add: word ids outside [0, {self.n_words})")
        self._kf_ids.append(int(kf_id))
        self._timestamps.append(float(timestamp))
        if len(bow.words):
            self._buffer.append((bow.words.astype(np.int64), np.full(len(bow.words), entry, np.int64),
                                 bow.weights.astype(np.float64)))
            self._buffered += len(bow.words)
            if self._buffered > _INDEX_BUFFER_POSTINGS:
                self._merge()
        return entry

    def _merge(self) -> None:
        """Insert the buffered postings at the end of their words' ranges (O(postings) copy)."""
        if not self._buffer:
            return
        words = np.concatenate([b[0] for b in self._buffer])
        order = np.argsort(words, kind="stable")          # keeps entry order within a word
        words = words[order]
        at = self._indptr[words + 1]
        self._entry = np.insert(self._entry, at, np.concatenate([b[1] for b in self._buffer])[order])
        self._weight = np.insert(self._weight, at, np.concatenate([b[2] for b in self._buffer])[order])
        self._indptr[1:] += np.cumsum(np.bincount(words, minlength=self.n_words))
        self._buffer, self._buffered = [], 0

    def scores(self, bow: BowVector) -> np.ndarray:
        """(len(self),) DBoW2 L1 scores of ``bow`` against every entry (0 for no shared word)."""
        out = np.zeros(len(self), np.float64)
        if len(bow.words) == 0 or len(self) == 0:
            return out
        q_words = bow.words.astype(np.int64)
        q_w = bow.weights / bow.weights.sum()
        # sorted block: gather the posting ranges of the query words
        start, stop = self._indptr[q_words], self._indptr[q_words + 1]
        lens = stop - start
        total = int(lens.sum())
        if total:
            base = np.repeat(start - (np.cumsum(lens) - lens), lens)
            pos = base + np.arange(total)
            out += np.bincount(self._entry[pos], np.minimum(np.repeat(q_w, lens), self._weight[pos]),
                               minlength=len(out))
        for words, entry, weight in self._buffer:   # one buffered keyframe per item
            _, iq, ib = np.intersect1d(q_words, words, assume_unique=True, return_indices=True)
            out[entry[0]] += np.minimum(q_w[iq], weight[ib]).sum()
        return out

    def query(self, bow: BowVector, max_results: int = 10, max_entry: int | None = None,
              max_timestamp: float | None = None, min_score: float = 0.0) -> list[QueryResult]:
        """Best ``max_results`` entries by score (descending), among entries with index <=
        ``max_entry`` and timestamp <= ``max_timestamp`` (when given; untimed entries pass) and score
        >= ``min_score`` (> 0 always)."""
        s = self.scores(bow)
        eligible = (s > 0.0) & (s >= min_score)
        if max_entry is not None:
            eligible[max(max_entry + 1, 0):] = False
        if max_timestamp is not None:
            t = np.asarray(self._timestamps)
            eligible &= ~(t > max_timestamp)
        idx = np.flatnonzero(eligible)
        if len(idx) > max_results:
            idx = idx[np.argpartition(-s[idx], max_results - 1)[:max_results]]
        idx = idx[np.lexsort((idx, -s[idx]))]
        return [QueryResult(int(i), self._kf_ids[i], float(s[i])) for i in idx]


# ----------------------------------------------------------------------------------- detection

@dataclass(frozen=True)
class LoopCandidate:
    """An accepted loop: the best keyframe of a temporally consistent island of matches."""

    kf_id: int
    entry: int
    score: float                 # raw L1 score
    normalized_score: float      # score / s(current, previous keyframe)
    island_score: float          # sum of normalised scores of the island
    island_kf_ids: tuple[int, int]  # first and last keyframe id of the island
    consistent: int              # consecutive queries with a consistent island (>= min_consistent)


@dataclass(frozen=True)
class LoopQuery:
    """Outcome of :meth:`LoopDetector.process` for one keyframe. ``status`` is one of
    ``too_few_features``, ``no_prior`` (first keyframe or previous keyframe unusable), ``low_prior``,
    ``no_candidates``, ``not_consistent``, ``accepted``; ``candidates`` (best island first) only when
    accepted."""

    kf_id: int
    entry: int
    status: str
    candidates: tuple[LoopCandidate, ...] = ()
    prior_score: float = 0.0
    n_matches: int = 0           # candidates above the normalised threshold


class LoopDetector:
    """DBoW2 loop detection over a growing :class:`BowDatabase`: one :meth:`process` call per
    keyframe, in keyframe order, from one thread (it keeps the previous keyframe's vector and the
    consistency groups). ``database`` is public for other queries (e.g. relocalisation with a
    stricter ``min_score``)."""

    def __init__(self, vocabulary: Vocabulary, cfg: LoopDetectionConfig | None = None):
        self.vocabulary = vocabulary
        self.cfg = cfg or LoopDetectionConfig()
        self.cfg.validate()
        self.database = BowDatabase(vocabulary.n_words)
        self._previous: BowVector | None = None
        self._groups: list[tuple[int, int, int]] = []   # (first entry, last entry, consecutive count)

    def process(self, kf_id: int, bow: BowVector, timestamp: float = math.nan) -> LoopQuery:
        """Add keyframe ``kf_id`` to the database and look for loops to older keyframes."""
        c = self.cfg
        entry = self.database.add(kf_id, bow, timestamp)
        previous, self._previous = self._previous, bow
        if bow.n_features < c.min_features or len(bow) == 0:
            logger.info("loop detection: keyframe %d has %d features (< %d), not queried", kf_id,
                        bow.n_features, c.min_features)
            self._previous = None
            return self._reject(kf_id, entry, "too_few_features")
        if previous is None:
            return self._reject(kf_id, entry, "no_prior")
        prior = l1_score(bow, previous)
        if prior < c.min_prior_score:
            return self._reject(kf_id, entry, "low_prior", prior)
        max_t = timestamp - c.min_gap_seconds if math.isfinite(timestamp) and c.min_gap_seconds > 0 \
            else None
        matches = self.database.query(bow, c.max_results, max_entry=entry - c.min_gap_keyframes,
                                      max_timestamp=max_t)
        matches = [m for m in matches if m.score / prior >= c.min_normalized_score]
        if not matches:
            return self._reject(kf_id, entry, "no_candidates", prior)
        islands = self._islands(matches, prior)
        groups, accepted = [], []
        for lo, hi, island_score, best in islands:
            count = 1 + max((n for g_lo, g_hi, n in self._groups
                             if lo - g_hi <= c.consistency_max_gap and g_lo - hi <= c.consistency_max_gap),
                            default=0)
            groups.append((lo, hi, count))
            if count >= c.min_consistent:
                accepted.append(LoopCandidate(best.kf_id, best.entry, best.score, best.score / prior,
                                              island_score, (self.database.kf_id(lo),
                                                             self.database.kf_id(hi)), count))
        self._groups = groups
        status = "accepted" if accepted else "not_consistent"
        if accepted:
            logger.info("loop detection: keyframe %d closes a loop with keyframe %d (score %.3f, "
                        "normalised %.2f, %d consistent)", kf_id, accepted[0].kf_id, accepted[0].score,
                        accepted[0].normalized_score, accepted[0].consistent)
        return LoopQuery(kf_id, entry, status, tuple(accepted), prior, len(matches))

    def _reject(self, kf_id: int, entry: int, status: str, prior: float = 0.0) -> LoopQuery:
        self._groups = []                       # consistency needs consecutive detections
        return LoopQuery(kf_id, entry, status, (), prior, 0)

    def _islands(self, matches: list[QueryResult], prior: float
                 ) -> list[tuple[int, int, float, QueryResult]]:
        """Group matches whose entries are at most ``island_max_gap`` apart; returns
        ``(first entry, last entry, sum of normalised scores, best match)`` by island score."""
        matches = sorted(matches, key=lambda m: m.entry)
        entries = np.array([m.entry for m in matches])
        norm = np.array([m.score for m in matches]) / prior
        cut = np.flatnonzero(np.diff(entries) > self.cfg.island_max_gap) + 1
        islands = []
        for a, b in zip(np.r_[0, cut], np.r_[cut, len(matches)]):
            best = a + int(np.argmax(norm[a:b]))
            islands.append((int(entries[a]), int(entries[b - 1]), float(norm[a:b].sum()), matches[best]))
        islands.sort(key=lambda isl: -isl[2])
        return islands


@dataclass(frozen=True, eq=False)
class KeyframeFeatures:
    """ORB features of one image with their words: ``uv`` (N, 2) float32 pixels, ``descriptors``
    (N, 32) uint8, ``words`` (N,) leaf word ids, ``bow`` the image's BoW vector."""

    uv: np.ndarray
    descriptors: np.ndarray
    words: np.ndarray
    bow: BowVector


class PlaceRecognizer:
    """ORB extraction + vocabulary + :class:`LoopDetector` built from one :class:`BowConfig`."""

    def __init__(self, cfg: BowConfig | None = None, vocabulary: Vocabulary | None = None):
        from .features import OrbExtractor

        self.cfg = cfg or BowConfig()
        self.vocabulary = vocabulary or load_vocabulary(self.cfg.vocabulary)
        self.extractor = OrbExtractor(self.cfg.orb)
        self.detector = LoopDetector(self.vocabulary, self.cfg.detection)

    def describe(self, image: np.ndarray) -> KeyframeFeatures:
        """Features, words and BoW vector of one (H, W) or (H, W, 3) image."""
        uv, desc = self.extractor(image)
        bow, words = self.vocabulary.transform(desc)
        return KeyframeFeatures(uv, desc, words, bow)

    def process(self, kf_id: int, image: np.ndarray, timestamp: float = math.nan
                ) -> tuple[LoopQuery, KeyframeFeatures]:
        """Describe a new keyframe image and run loop detection on it."""
        feats = self.describe(image)
        return self.detector.process(kf_id, feats.bow, timestamp), feats


# ----------------------------------------------------------------------------------- ground truth

def same_place(T_WC: np.ndarray, radius: float, max_angle_deg: float) -> np.ndarray:
    """(N, N) bool: camera pairs whose positions ``t_WC`` are within ``radius`` and whose viewing
    directions (camera z axes in the world) differ by at most ``max_angle_deg`` (for ground-truth
    revisits in evaluations). ``T_WC`` (N, 4, 4) camera-to-world."""
    T = np.asarray(T_WC, np.float64)
    pos, view = T[:, :3, 3], T[:, :3, 2]
    dist2 = np.sum((pos[:, None, :] - pos[None, :, :]) ** 2, axis=-1)
    cos = np.clip(view @ view.T, -1.0, 1.0)
    return (dist2 <= radius * radius) & (cos >= np.cos(np.deg2rad(max_angle_deg)))
