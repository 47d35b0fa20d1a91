"""Place recognition with float descriptors (XFeat, :class:`fgslam.loop.features.XFeatExtractor`) for the
classical loop closer: a VLAD global descriptor per keyframe, a cosine-similarity database, and the
same DBoW2-style detection logic as the binary bag of words (:class:`fgslam.loop.bow.LoopDetector`).

VLAD (Jegou et al., CVPR 2010): each local descriptor (unit norm) is assigned to its nearest centre
(largest dot product) of a small float "vocabulary" of ``k`` centres; the residuals ``d - c_j`` are
summed per centre, each centre's sum is L2-normalised (intra-normalisation) and the concatenation
(``k * 64`` values) is L2-normalised. The score of two keyframes is the cosine similarity of their
VLAD vectors, clipped at 0 (so it stays in [0, 1] like the DBoW2 L1 score the detector expects).
Chosen by measurement on the 7-Scenes kitchen revisit and the synthetic room loop
(docs/benchmarks/loops.md): VLAD with 64 centres separates revisits from pairs without
common view better than the mean descriptor and than ORB's bag of words.

Centres: spherical k-means (dot-product assignment, mean then renormalise), seeded, on XFeat
descriptors of fgslam's own synthetic renders (``tools/train_vocabulary.py --xfeat-centres 64``),
shipped as ``fgslam/loop/data/xfeat_vlad_synth_k64.npz``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Literal

import numpy as np

from ..core.config import MAX_COUNT, MAX_ITERATIONS, MAX_SEED, check_ranges, ranged
from ..core.errors import ConfigError, DataError, FormatError
from .bow import KeyframeDatabase, KeyframeFeatures, LoopDetectionConfig, LoopDetector, LoopQuery
from .features import XFEAT_DESCRIPTOR_DIM, XFeatConfig, XFeatExtractor
from .vocabulary import read_versioned_npz

logger = logging.getLogger(__name__)

CENTRES_FORMAT_VERSION = 1
DEFAULT_CENTRES_FILE = "xfeat_vlad_synth_k64.npz"     # in fgslam/loop/data/
FEATURE_KINDS = ("orb", "xfeat")
_GROW = 1024                                          # database rows allocated at a time


# ----------------------------------------------------------------------------------- configs

def _xfeat_detection() -> LoopDetectionConfig:
    # VLAD cosine scores: a keyframe's score against the previous keyframe is 0.6-0.95 and a
    # revisit's 0.4-0.7 of it (7-Scenes kitchen, synthetic room), unrelated views up to 0.75 of it
    # in the kitchen: verification decides there (docs/benchmarks/loops.md)
    return LoopDetectionConfig(min_prior_score=0.05, min_normalized_score=0.5)


@dataclass
class VladRetrievalConfig:
    """Retrieval of keyframes by their VLAD vectors (``loop_closure.features.kind: xfeat``)."""

    centres: str = "default"           # 'default' (shipped, trained on synthetic renders) or a path to a .npz
    detection: LoopDetectionConfig = field(default_factory=_xfeat_detection)
    relocalization_min_score: float = ranged(0.3, ge=0, le=1)  # cosine score a relocalisation candidate needs


@dataclass
class LoopFeaturesConfig:
    """Which local features the classical loop closer and relocalisation use: ``orb`` (binary bag
    of words, ``loop_closure.bow``; the default) or ``xfeat`` (learned, optional extra
    ``fgslam[xfeat]``; VLAD retrieval and cosine matching, about 25x ORB's CPU per keyframe: docs/benchmarks/loops.md)."""

    kind: Literal["orb", "xfeat"] = "orb"  # orb: binary bag of words; xfeat: learned features (extra fgslam[xfeat])
    xfeat: XFeatConfig = field(default_factory=XFeatConfig)
    retrieval: VladRetrievalConfig = field(default_factory=VladRetrievalConfig)

    def validate(self) -> None:
        if self.kind not in FEATURE_KINDS:
            raise ConfigError(f"loop_closure.features.kind={self.kind!r}: expected one of {', '.join(FEATURE_KINDS)}")
        check_ranges(self, "loop_closure.features.")


# ----------------------------------------------------------------------------------- centres

class VladCentres:
    """``k`` unit-norm float centres (k, D) and the VLAD vectors they give."""

    def __init__(self, centres: np.ndarray, source: str = ""):
        c = np.asarray(centres, np.float64)
        if c.ndim != 2 or len(c) == 0 or not np.isfinite(c).all():
            raise DataError(f"VLAD centres{' ' + source if source else ''}: expected a finite (k, D) array, got {c.shape}")
        self.centres = c / np.maximum(np.linalg.norm(c, axis=1, keepdims=True), np.finfo(np.float64).tiny)
        self.source = source

    @property
    def k(self) -> int:
        return len(self.centres)

    @property
    def dim(self) -> int:
        return self.centres.shape[1]

    def vlad(self, descriptors: np.ndarray) -> np.ndarray:
        """(k * D,) unit VLAD vector of (N, D) descriptors; zeros for N = 0."""
        d = np.asarray(descriptors, np.float64)
        out = np.zeros((self.k, self.dim))
        if len(d) == 0:
            return out.ravel()
        if d.ndim != 2 or d.shape[1] != self.dim:
            raise DataError(f"VLAD: descriptors of shape {d.shape} (expected (N, {self.dim}))")
        assign = np.argmax(d @ self.centres.T, axis=1)
        np.add.at(out, assign, d - self.centres[assign])
        norms = np.linalg.norm(out, axis=1, keepdims=True)
        out = np.divide(out, norms, out=np.zeros_like(out), where=norms > 0)     # intra-normalisation
        v = out.ravel()
        n = np.linalg.norm(v)
        return v / n if n > 0 else v

    def save(self, path: str | Path, n_training_images: int = 0) -> None:
        np.savez_compressed(path, format_version=np.int32(CENTRES_FORMAT_VERSION), descriptor=np.array("XFeat"),
                            centres=self.centres.astype(np.float32), n_training_images=np.int64(n_training_images))

    @staticmethod
    def load(path: str | Path) -> "VladCentres":
        data = read_versioned_npz(path, "VLAD centres", ("centres",), CENTRES_FORMAT_VERSION)
        if data["centres"].ndim != 2 or data["centres"].shape[1] != XFEAT_DESCRIPTOR_DIM:
            raise FormatError(f"{path}: centres of shape {data['centres'].shape} "
                              f"(expected (k, {XFEAT_DESCRIPTOR_DIM}) XFeat centres)")
        return VladCentres(data["centres"], source=str(path))


@lru_cache(maxsize=1)
def load_default_centres() -> VladCentres:
    return VladCentres.load(Path(str(resources.files(__package__).joinpath("data", DEFAULT_CENTRES_FILE))))


def load_centres(name_or_path: str) -> VladCentres:
    """``'default'`` -> the shipped centres, otherwise the .npz file at that path."""
    return load_default_centres() if name_or_path == "default" else VladCentres.load(name_or_path)


@dataclass
class CentreTrainingConfig:
    """Spherical k-means of the VLAD centres."""

    k: int = ranged(64, ge=1, le=MAX_COUNT)  # centres
    max_iterations: int = ranged(20, ge=1, le=MAX_ITERATIONS)  # assign/update rounds
    seed: int = ranged(0, ge=0, le=MAX_SEED)  # initial centres drawn from the descriptors


def train_centres(descriptors: np.ndarray, cfg: CentreTrainingConfig | None = None) -> VladCentres:
    """Spherical k-means of (N, D) unit descriptors: the initial centres are ``k`` distinct
    descriptors drawn with ``seed``; an empty cluster keeps its centre."""
    cfg = cfg or CentreTrainingConfig()
    check_ranges(cfg, "centres.")
    X = np.asarray(descriptors, np.float64)
    if X.ndim != 2 or len(X) < cfg.k:
        raise DataError(f"train_centres: {X.shape} descriptors for {cfg.k} centres")
    rng = np.random.default_rng(cfg.seed)
    C = X[rng.choice(len(X), cfg.k, replace=False)].copy()
    for _ in range(cfg.max_iterations):
        assign = np.argmax(X @ C.T, axis=1)
        sums = np.zeros_like(C)
        np.add.at(sums, assign, X)
        norms = np.linalg.norm(sums, axis=1, keepdims=True)
        C = np.where(norms > 0, sums / np.maximum(norms, np.finfo(np.float64).tiny), C)
    return VladCentres(C)


# ----------------------------------------------------------------------------------- database

@dataclass(frozen=True, eq=False)
class GlobalDescriptor:
    """One keyframe's unit VLAD vector and its number of local features (``len`` 0: no features)."""

    vector: np.ndarray
    n_features: int

    def __len__(self) -> int:
        return 1 if self.n_features > 0 else 0


def cosine_score(a: GlobalDescriptor, b: GlobalDescriptor) -> float:
    """Cosine similarity of two VLAD vectors clipped at 0 (in [0, 1]); 0 when either is empty."""
    if not len(a) or not len(b):
        return 0.0
    return max(0.0, float(a.vector @ b.vector))


class VladDatabase(KeyframeDatabase):
    """Keyframes' VLAD vectors in one growing matrix; a query scores every entry by cosine."""

    def __init__(self, dim: int):
        super().__init__()
        self.dim = int(dim)
        self._rows = np.zeros((0, self.dim), np.float64)

    def add(self, kf_id: int, g: GlobalDescriptor, timestamp: float = math.nan) -> int:
        entry = self._append(kf_id, timestamp)
        if g.vector.shape != (self.dim,):
            raise DataError(f"VladDatabase.add: vector of shape {g.vector.shape} (expected ({self.dim},))")
        if entry >= len(self._rows):
            self._rows = np.concatenate([self._rows, np.zeros((_GROW, self.dim))])
        self._rows[entry] = g.vector if len(g) else 0.0
        return entry

    def scores(self, g: GlobalDescriptor) -> np.ndarray:
        if not len(g) or len(self) == 0:
            return np.zeros(len(self))
        return np.maximum(self._rows[:len(self)] @ g.vector, 0.0)


# ----------------------------------------------------------------------------------- recognizer

class XFeatPlaceRecognizer:
    """XFeat extraction + VLAD + :class:`~fgslam.loop.bow.LoopDetector` over a :class:`VladDatabase`
    (the interface of :class:`fgslam.loop.bow.PlaceRecognizer`)."""

    def __init__(self, cfg: LoopFeaturesConfig, centres: VladCentres | None = None, extractor=None):
        self.cfg = cfg
        self.extractor = extractor or XFeatExtractor(cfg.xfeat)     # first: the error without the extra
        self.vocabulary = centres or load_centres(cfg.retrieval.centres)
        if self.vocabulary.dim != XFEAT_DESCRIPTOR_DIM:
            raise ConfigError(f"loop_closure.features.retrieval.centres: {self.vocabulary.dim}-D centres "
                              f"(XFeat descriptors are {XFEAT_DESCRIPTOR_DIM}-D)")
        self.detector = LoopDetector(None, cfg.retrieval.detection,
                                     database=VladDatabase(self.vocabulary.k * self.vocabulary.dim),
                                     pair_score=cosine_score)

    def describe(self, image: np.ndarray) -> KeyframeFeatures:
        uv, desc = self.extractor(image)
        g = GlobalDescriptor(self.vocabulary.vlad(desc), len(uv))
        return KeyframeFeatures(uv, desc, np.zeros(0, np.int64), g)

    def process(self, kf_id: int, image: np.ndarray, timestamp: float = math.nan) -> tuple[LoopQuery, KeyframeFeatures]:
        feats = self.describe(image)
        return self.detector.process(kf_id, feats.bow, timestamp), feats

    def for_caller_thread(self) -> "XFeatPlaceRecognizer":
        """A recogniser for relocalisation in the caller's thread: the model is read-only, so shared."""
        return self
