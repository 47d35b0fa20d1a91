"""Bag-of-words place recognition: ORB wrapper, k-majority vocabulary, tf-idf, L1 score, inverted
index, DBoW2 loop detection (gap, normalisation, islands, temporal consistency)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from fgslam.core.config import load_config
from fgslam.core.errors import ConfigError, DataError, FormatError
from fgslam.loop.bow import BowConfig, BowDatabase, LoopDetectionConfig, LoopDetector, PlaceRecognizer, same_place
from fgslam.loop.vocabulary import (BowVector, Vocabulary, VocabularyTrainingConfig, build_tree, hamming_matrix,
                                    kmajority, l1_score, load_default_vocabulary, train_vocabulary)
from fgslam.loop.features import OrbConfig, OrbExtractor, spread_keypoints


# ----------------------------------------------------------------------------------- helpers

def _random_descriptors(rng, n):
    return rng.integers(0, 256, size=(n, 32), dtype=np.uint8)


def _flip_bits(rng, desc, n_bits):
    """Copy of ``desc`` with ``n_bits`` random distinct bits flipped in every row."""
    bits = np.unpackbits(desc, axis=1)
    cols = np.argsort(rng.random(bits.shape), axis=1)[:, :n_bits]
    np.put_along_axis(bits, cols, 1 - np.take_along_axis(bits, cols, axis=1), axis=1)
    return np.packbits(bits, axis=1)


def _bow(words, weights=None):
    words = np.asarray(words, np.int32)
    w = np.ones(len(words)) if weights is None else np.asarray(weights, np.float64)
    order = np.argsort(words)
    return BowVector(words[order], w[order] / w.sum(), n_features=1000)


@pytest.fixture(scope="module")
def synth_room():
    """room-loop (seed 0, never used to train the shipped vocabulary), small images."""
    from fgslam.io.synth import SynthSequence, default_config

    cfg = default_config("room-loop")
    cfg.seed = 0
    cfg.frames = int(cfg.frames * 1.25)          # run 25 % past the start: a real revisit stretch
    return SynthSequence(cfg)


@pytest.fixture(scope="module")
def small_training_set(synth_room):
    extractor = OrbExtractor(OrbConfig(n_features=300))
    times = synth_room.frame_times()[:400:40]
    return [extractor(synth_room.render_view(T).image)[1] for T in synth_room.camera_poses(times)]


# ----------------------------------------------------------------------------------- features

def test_hamming_matrix_matches_bit_count():
    rng = np.random.default_rng(1)
    a, b = _random_descriptors(rng, 37), _random_descriptors(rng, 11)
    ref = (np.unpackbits(a, axis=1)[:, None, :] != np.unpackbits(b, axis=1)[None, :, :]).sum(-1)
    np.testing.assert_array_equal(hamming_matrix(a, b), ref)
    with pytest.raises(DataError):
        hamming_matrix(a.astype(np.int16), b)


def test_spread_keypoints_fills_every_cell():
    rng = np.random.default_rng(2)
    # 900 strong corners crowd the top-left cell, 10 weak ones sit in each of the other 3 cells
    crowd = rng.uniform(0, 50, size=(900, 2))
    others = np.concatenate([rng.uniform(0, 50, size=(10, 2)) + off
                             for off in ([50, 0], [0, 50], [50, 50])])
    uv = np.concatenate([crowd, others])
    response = np.concatenate([rng.uniform(10, 20, 900), rng.uniform(0, 1, 30)])
    keep = spread_keypoints(uv, response, 100, 100, n_keep=100, grid_rows=2, grid_cols=2)
    assert len(keep) == 100 and len(np.unique(keep)) == 100
    assert np.all(np.isin(np.arange(900, 930), keep))      # the weak cells keep all of theirs
    assert np.sum(keep < 900) == 70                        # the crowd fills the remaining budget
    # a 1 x 1 grid is plain strongest-first
    top = spread_keypoints(uv, response, 100, 100, 100, 1, 1)
    np.testing.assert_array_equal(top, np.sort(np.argsort(-response)[:100]))


def test_orb_extractor_on_texture_and_blank():
    rng = np.random.default_rng(3)
    image = (rng.random((120, 160)) * 255).astype(np.float32)
    image = np.kron(image, np.ones((3, 3), np.float32))    # blobs of 3 pixels: corners for FAST
    uv, desc = OrbExtractor(OrbConfig(n_features=200))(image)
    assert 50 < len(uv) <= 200 and desc.shape == (len(uv), 32) and desc.dtype == np.uint8
    assert np.all((uv >= 0) & (uv < [480, 360]))
    uv_rgb, _ = OrbExtractor(OrbConfig(n_features=200))(np.repeat(image[..., None], 3, axis=2))
    assert abs(len(uv_rgb) - len(uv)) <= 0.1 * len(uv)     # colour input is converted to grey
    uv0, desc0 = OrbExtractor()(np.full((240, 320), 128.0, np.float32))
    assert uv0.shape == (0, 2) and desc0.shape == (0, 32)
    with pytest.raises(ConfigError):
        OrbExtractor(OrbConfig(scale_factor=1.0))


# ----------------------------------------------------------------------------------- vocabulary

def test_kmajority_recovers_planted_clusters():
    rng = np.random.default_rng(4)
    centres = _random_descriptors(rng, 5)
    truth = np.repeat(np.arange(5), 60)
    desc = _flip_bits(rng, centres[truth], 12)              # 12 of 256 bits flipped per member
    found, labels = kmajority(desc, 5, 20, np.random.default_rng(0))
    assert len(found) == 5
    # same partition as the truth and the majority centres equal the planted ones
    match = np.argmin(hamming_matrix(centres, found), axis=1)
    assert len(np.unique(match)) == 5
    np.testing.assert_array_equal(match[truth], labels)
    np.testing.assert_array_equal(found[match], centres)


def test_training_is_deterministic_and_descriptors_reach_their_leaf(small_training_set):
    cfg = VocabularyTrainingConfig(branching=6, depth=3, seed=7)
    desc = np.concatenate(small_training_set)
    node_desc, child_start, child_count, node_word, leaf_word = build_tree(desc, cfg)
    v1 = train_vocabulary(small_training_set, cfg)
    v2 = train_vocabulary(small_training_set, cfg)
    np.testing.assert_array_equal(v1.node_descriptors, v2.node_descriptors)
    np.testing.assert_array_equal(v1.idf, v2.idf)
    np.testing.assert_array_equal(v1.node_descriptors, node_desc)
    assert v1.n_words <= 6 ** 3 and v1.n_words > 6 ** 2
    # every training descriptor quantises to the leaf it was clustered into
    np.testing.assert_array_equal(v1.quantize(desc), leaf_word)
    # level quantisation gives the ancestor at that level
    lvl1 = v1.quantize(desc, level=1)
    assert np.all((lvl1 >= 1) & (lvl1 <= 6))
    other = train_vocabulary(small_training_set, VocabularyTrainingConfig(branching=6, depth=3, seed=8))
    assert not np.array_equal(other.node_descriptors[1:7], v1.node_descriptors[1:7])


def test_tfidf_weights(small_training_set):
    vocab = train_vocabulary(small_training_set, VocabularyTrainingConfig(branching=6, depth=3))
    n_images = len(small_training_set)
    words_per_image = [np.unique(vocab.quantize(d)) for d in small_training_set]
    images_with = np.bincount(np.concatenate(words_per_image), minlength=vocab.n_words)
    np.testing.assert_allclose(vocab.idf, np.log(n_images / np.maximum(images_with, 1)))
    bow, words = vocab.transform(small_training_set[0])
    counts = np.bincount(words, minlength=vocab.n_words)
    expected = counts / len(words) * vocab.idf
    expected /= expected.sum()
    dense = np.zeros(vocab.n_words)
    dense[bow.words] = bow.weights
    np.testing.assert_allclose(dense, expected, atol=1e-12)
    assert abs(bow.weights.sum() - 1.0) < 1e-12 and np.all(np.diff(bow.words) > 0)
    # a word seen in every training image carries no information: weight 0, left out
    common = np.flatnonzero(images_with == n_images)
    assert not np.any(np.isin(bow.words, common))
    # rarer words weigh more for the same count
    assert np.all(np.diff(vocab.idf[np.argsort(images_with)]) <= 1e-12)


def test_vocabulary_file_roundtrip_and_errors(small_training_set, tmp_path):
    vocab = train_vocabulary(small_training_set, VocabularyTrainingConfig(branching=5, depth=2))
    path = tmp_path / "v.npz"
    vocab.save(path)
    loaded = Vocabulary.load(path)
    np.testing.assert_array_equal(loaded.node_descriptors, vocab.node_descriptors)
    np.testing.assert_allclose(loaded.idf, vocab.idf, rtol=1e-6)
    np.testing.assert_array_equal(loaded.quantize(small_training_set[1]),
                                  vocab.quantize(small_training_set[1]))
    bad = tmp_path / "bad.npz"
    np.savez(bad, format_version=np.int32(1), branching=np.int32(5))
    with pytest.raises(FormatError, match="missing"):
        Vocabulary.load(bad)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError):
        Vocabulary.load(tmp_path / "junk.npz")
    with pytest.raises(DataError):
        Vocabulary.load(tmp_path / "absent.npz")


# ----------------------------------------------------------------------------------- scoring

def test_l1_score():
    a = _bow([1, 5, 9], [0.2, 0.3, 0.5])
    assert l1_score(a, a) == pytest.approx(1.0)
    assert l1_score(a, _bow([2, 3])) == 0.0
    assert l1_score(a, BowVector.empty()) == 0.0
    b = _bow([5, 9, 11], [0.5, 0.25, 0.25])
    dense = np.zeros((2, 12))
    dense[0, a.words], dense[1, b.words] = a.weights, b.weights
    expected = 1.0 - 0.5 * np.abs(dense[0] - dense[1]).sum()
    assert l1_score(a, b) == pytest.approx(expected) == pytest.approx(l1_score(b, a))
    # scale invariant (vectors are normalised inside)
    scaled = BowVector(b.words, 3.0 * b.weights, 10)
    assert l1_score(a, scaled) == pytest.approx(expected)


def test_database_scores_equal_pairwise_l1_and_query_filters():
    rng = np.random.default_rng(5)
    n_words = 2000
    entries = []
    db = BowDatabase(n_words)
    for i in range(400):                         # 400 x ~200 postings: several index merges
        words = rng.choice(n_words, size=rng.integers(1, 400), replace=False)
        entries.append(_bow(words, rng.random(len(words)) + 0.01))
        assert db.add(100 + i, entries[-1], timestamp=0.5 * i) == i
    db.add(999, BowVector.empty(), timestamp=300.0)
    query = _bow(entries[123].words[:40], entries[123].weights[:40])
    expected = np.array([l1_score(query, e) for e in entries] + [0.0])
    np.testing.assert_allclose(db.scores(query), expected, atol=1e-12)
    res = db.query(query, max_results=5)
    assert [r.entry for r in res] == list(np.argsort(-expected, kind="stable")[:5])
    assert res[0].kf_id == 223 and res[0].score == pytest.approx(expected.max())
    assert all(r.entry <= 100 for r in db.query(query, 50, max_entry=100))
    assert all(db.timestamp(r.entry) <= 20.0 for r in db.query(query, 50, max_timestamp=20.0))
    assert all(r.score >= 0.2 for r in db.query(query, 50, min_score=0.2))
    with pytest.raises(DataError):
        db.add(1, _bow([n_words]))


# ----------------------------------------------------------------------------------- detection

def _stream_bow(i):
    """Keyframe i of a drive through new places: 10 words, 5 shared with keyframe i - 1."""
    return _bow(np.arange(5 * i, 5 * i + 10))


class _FakeVocab:
    n_words = 100_000


def test_temporal_consistency_rejects_single_spurious_match():
    cfg = LoopDetectionConfig(min_gap_keyframes=10, min_consistent=3, min_features=1)
    det = LoopDetector(_FakeVocab(), cfg)
    statuses = [det.process(i, _stream_bow(i)).status for i in range(40)]
    assert statuses[0] == "no_prior" and set(statuses[1:]) == {"no_candidates"}
    # one keyframe shares half its words with the previous keyframe and half with keyframe 5
    spurious = _bow(np.concatenate([np.arange(200, 205), np.arange(25, 30)]))
    r = det.process(40, spurious)
    assert r.status == "not_consistent" and r.n_matches >= 1
    r = det.process(41, _bow(np.arange(200, 210)))   # the drive goes on: no match, chain broken
    assert r.status == "no_candidates"
    # a real revisit: keyframes 42.. look like keyframes 12.. again, consecutively (keyframe 42
    # shares no word with keyframe 41, so it has no prior score and is skipped)
    results = []
    for j in range(6):
        words = np.arange(5 * (12 + j), 5 * (12 + j) + 10)
        results.append(det.process(42 + j, _bow(words)))
    assert [r.status for r in results] == ["low_prior", "not_consistent", "not_consistent",
                                           "accepted", "accepted", "accepted"]
    for j, r in enumerate(results[3:], start=3):
        assert abs(r.candidates[0].kf_id - (12 + j)) <= 1 and r.candidates[0].consistent >= 3
        assert r.candidates[0].normalized_score >= cfg.min_normalized_score


def test_min_gap_excludes_recent_keyframes():
    det = LoopDetector(_FakeVocab(), LoopDetectionConfig(min_gap_keyframes=10, min_gap_seconds=8.0,
                                                         min_features=1, min_consistent=1))
    for i in range(30):
        r = det.process(i, _stream_bow(i % 12), timestamp=float(i))   # repeats every 12 keyframes
        if r.status == "accepted":
            assert all(i - c.kf_id >= 10 and i - c.kf_id >= 8 for c in r.candidates)
    assert r.status == "accepted"


def test_blank_frames_give_no_features_and_no_detection(caplog):
    vocab = load_default_vocabulary()
    extractor = OrbExtractor()
    det = LoopDetector(vocab)
    blank = np.full((200, 320), 90.0, np.float32)
    with caplog.at_level(logging.INFO, logger="fgslam.loop.bow"):
        for i in range(3):
            bow, _ = vocab.transform(extractor(blank)[1])
            assert len(bow) == 0 and bow.n_features == 0
            r = det.process(i, bow)
            assert r.status == "too_few_features" and r.candidates == ()
    assert caplog.text.count("not queried") == 3
    assert len(det.database) == 3
    with pytest.raises(ConfigError):
        LoopDetector(vocab, LoopDetectionConfig(min_consistent=0))


def test_revisit_precision_recall_on_synthetic_room(synth_room):
    """Held-out room-loop (seed 0) that runs 25 % past its start; true revisits from GT poses."""
    stride, gap = 4, 15
    times = synth_room.frame_times()[::stride]
    T_WC = synth_room.camera_poses(times)
    truth = same_place(T_WC, radius=0.5, max_angle_deg=30.0)
    recognizer = PlaceRecognizer(BowConfig(detection=LoopDetectionConfig(min_gap_keyframes=gap)))
    tp = fp = positives = 0
    for i, (t, T) in enumerate(zip(times, T_WC)):
        r, feats = recognizer.process(i, synth_room.render_view(T).image, float(t))
        assert len(feats.uv) == len(feats.descriptors) == len(feats.words) > 500
        positives += bool(truth[i, :max(i - gap + 1, 0)].any())
        if r.status == "accepted":
            tp += bool(truth[i, r.candidates[0].kf_id])
            fp += not truth[i, r.candidates[0].kf_id]
    precision, recall = tp / max(tp + fp, 1), tp / max(positives, 1)
    assert positives >= 20
    assert precision >= 0.95 and recall >= 0.75, (precision, recall, tp, fp, positives)


# ----------------------------------------------------------------------------------- shipped vocabulary

def test_shipped_vocabulary_on_kitti(shared_data):
    import cv2

    vocab = load_default_vocabulary()
    assert vocab.branching == 10 and vocab.depth == 5 and vocab.n_words > 50_000
    assert load_default_vocabulary() is vocab
    folder = shared_data / "kitti00_0-199" / "image_0"
    extractor = OrbExtractor()
    bows = {}
    for i in (0, 1, 150):
        image = cv2.imread(str(folder / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        assert image is not None, folder
        _, desc = extractor(image)
        assert len(desc) > 500
        bows[i], words = vocab.transform(desc)
        assert words.min() >= 0 and words.max() < vocab.n_words
        assert len(bows[i]) > 200 and bows[i].weights.sum() == pytest.approx(1.0)
    # consecutive frames share far more words than frames 15 s apart
    assert l1_score(bows[0], bows[1]) > 2.0 * l1_score(bows[0], bows[150])


def test_bow_config_from_yaml(tmp_path):
    path = tmp_path / "bow.yaml"
    path.write_text("orb:\n  n_features: 500\ndetection:\n  min_consistent: 4\n")
    cfg = load_config(BowConfig, path, ["detection.min_gap_seconds=12.5", "vocabulary=my.npz"])
    assert cfg.orb.n_features == 500 and cfg.orb.scale_factor == 1.2
    assert cfg.detection.min_consistent == 4 and cfg.detection.min_gap_seconds == 12.5
    assert cfg.vocabulary == "my.npz"
    with pytest.raises(ConfigError):
        load_config(BowConfig, None, ["detection.no_such_key=1"])
