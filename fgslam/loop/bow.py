"""Bag of binary words place recognition (after DBoW2, Galvez-Lopez & Tardos, T-RO 2012): the
keyframe database and loop detection on the vocabulary's BoW vectors (:mod:`fgslam.loop.vocabulary`).

Database: an inverted index (word -> entries with their weights) that grows one keyframe at a time;
:class:`LoopDetector` adds the DBoW2 loop logic: a minimum gap to recent keyframes, scores
normalised by the score against the previous keyframe, grouping of neighbouring candidates into
islands, and temporal consistency (a loop needs several consecutive consistent detections).
Scores are DBoW2 L1 scores (:func:`fgslam.loop.vocabulary.l1_score`), accumulated over shared words.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from ..core.config import MAX_COUNT, MAX_KEYFRAMES, MAX_SCALAR, check_ranges, ranged
from ..core.errors import DataError
from .features import OrbConfig, OrbExtractor
from .vocabulary import BowVector, Vocabulary, l1_score, load_vocabulary

logger = logging.getLogger(__name__)

_INDEX_BUFFER_POSTINGS = 1 << 15              # postings buffered before they join the sorted index


# ----------------------------------------------------------------------------------- configs

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


# ----------------------------------------------------------------------------------- database

@dataclass(frozen=True)
class QueryResult:
    """One database match: ``entry`` = insertion index, ``kf_id`` = caller's keyframe id,
    ``score`` = DBoW2 L1 score in [0, 1]."""

    entry: int
    kf_id: int
    score: float


class KeyframeDatabase:
    """Keyframes in insertion order (entries) with their ids and times, and the ranked query over a
    subclass's ``scores`` (the BoW inverted index; :class:`fgslam.loop.vlad.VladDatabase`)."""

    def __init__(self) -> None:
        self._kf_ids: list[int] = []
        self._timestamps: list[float] = []

    def __len__(self) -> int:
        return len(self._kf_ids)

    def kf_id(self, entry: int) -> int:
        return self._kf_ids[entry]

    def timestamp(self, entry: int) -> float:
        return self._timestamps[entry]

    def _append(self, kf_id: int, timestamp: float) -> int:
        self._kf_ids.append(int(kf_id))
        self._timestamps.append(float(timestamp))
        return len(self._kf_ids) - 1

    def scores(self, query) -> np.ndarray:
        raise NotImplementedError

    def query(self, bow, max_results: int = 10, max_entry: int | None = None,
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
        # one total order (score, then index): a partial selection's ties at the cut depend on the CPU's SIMD kernel
        idx = idx[np.lexsort((idx, -s[idx]))][:max_results]
        return [QueryResult(int(i), self._kf_ids[i], float(s[i])) for i in idx]


class BowDatabase(KeyframeDatabase):
    """Inverted index over L1-normalised BoW vectors, grown one keyframe at a time.

    Postings live in a word-sorted CSR block (``indptr`` over the vocabulary) plus a small append
    buffer of the latest keyframes, inserted into the block once it holds a few thousand postings
    (one O(postings) copy); a query gathers the postings of its words with vectorised range indexing
    and accumulates ``min(q_w, e_w)`` per entry."""

    def __init__(self, n_words: int):
        super().__init__()
        self.n_words = int(n_words)
        self._indptr = np.zeros(self.n_words + 1, np.int64)
        self._entry = np.zeros(0, np.int64)
        self._weight = np.zeros(0, np.float64)
        self._buffer: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._buffered = 0

    def add(self, kf_id: int, bow: BowVector, timestamp: float = math.nan) -> int:
        """Append one keyframe (an empty vector is stored too, so entries count keyframes);
        returns its entry index."""
        if len(bow.words) and (bow.words.min() < 0 or bow.words.max() >= self.n_words):
            raise DataError(f"BowDatabase.add: word ids outside [0, {self.n_words})")
        entry = self._append(kf_id, timestamp)
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

    def __init__(self, vocabulary: Vocabulary | None, cfg: LoopDetectionConfig | None = None,
                 database: KeyframeDatabase | None = None, pair_score=l1_score):
        self.vocabulary = vocabulary
        self.cfg = cfg or LoopDetectionConfig()
        self.cfg.validate()
        # another database and its pairwise score: float-descriptor retrieval (fgslam.loop.vlad)
        self.database = database if database is not None else BowDatabase(vocabulary.n_words)
        self._pair_score = pair_score
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
        prior = self._pair_score(bow, previous)
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

    def for_caller_thread(self) -> "PlaceRecognizer":
        """A recogniser for relocalisation in the caller's thread: its own ORB extractor (OpenCV's is
        not thread-safe), the same vocabulary."""
        return PlaceRecognizer(self.cfg, self.vocabulary)


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
