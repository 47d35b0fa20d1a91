"""Tests of fgslam.frontends.pointmap.matching (MASt3R-SLAM section 3.2) on synthetic renders: matches
of every pixel against the generator's true correspondences, invalidation of occluded pixels, warm
start, descriptor refinement of a wrong geometry, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fgslam.core.errors import DataError
from fgslam.frontends.pointmap.matching import MatchingConfig, RayImage, match_pointmaps, pixel_grid_uv
from fgslam.frontends.pointmap.source import PointmapSourceConfig, make_pointmap_source
from pointmap_support import render, room_sequence, true_correspondences

I, J = 40, 52  # 0.21 m apart, with some occlusions behind the furniture


@pytest.fixture(scope="module")
def scene():
    seq = room_sequence()
    vi, vj = render(seq, I), render(seq, J)
    src = make_pointmap_source(PointmapSourceConfig(kind="rgbd"), seq.K)
    src.add_frame(I, vi.image, depth=vi.depth)
    src.add_frame(J, vj.image, depth=vj.depth)
    T_true = np.linalg.inv(vi.T_WC) @ vj.T_WC
    pair = src.predict(I, J, T_CiCj=T_true)  # exact geometry: X_j^i from the true pose
    uv_true, visible, occluded = true_correspondences(seq.K, vi, vj)
    return seq, src, pair, T_true, uv_true, visible, occluded


def _match(pair, **kw):
    ref = RayImage(pair.X_i_in_i, pair.C_i)
    return match_pointmaps(ref, pair.X_j_in_i, D_i=pair.D_i, D_j=pair.D_j.reshape(-1, pair.D_j.shape[-1]),
                           query_valid=(pair.C_j > 0).reshape(-1), **kw)


def test_matches_all_pixels_against_true_correspondences(scene):
    *_, pair, _, uv_true, visible, occluded = scene
    assert occluded.sum() > 300  # the pair has occlusions to invalidate
    m = _match(pair, config=MatchingConfig(refine_radius=0))
    valid = m.valid.numpy()
    assert valid[visible].mean() > 0.95
    err_lm = np.linalg.norm(m.uv_lm.numpy() - uv_true, axis=-1)[valid & visible]
    assert np.median(err_lm) < 0.05  # px: the ray error's minimum is the true correspondence
    err = np.linalg.norm(m.uv.numpy() - uv_true, axis=-1)[valid & visible]
    assert np.median(err) < 0.45 and np.percentile(err, 99) < 0.75  # integer matches: rounding only
    assert valid[occluded].mean() < 0.05  # occluded pixels find the occluder: far apart in 3-D
    assert m.index.numpy()[valid].max() < 320 * 240
    np.testing.assert_array_equal(m.uv.numpy()[:, 1] * 320 + m.uv.numpy()[:, 0], m.index.numpy())


def test_warm_start_converges_to_the_same_matches_in_fewer_iterations(scene):
    *_, pair, _, uv_true, visible, _ = scene
    cold = _match(pair, config=MatchingConfig(refine_radius=0))
    warm = _match(pair, init_uv=cold.uv_lm, config=MatchingConfig(refine_radius=0, max_iterations=1))
    one_cold = _match(pair, config=MatchingConfig(refine_radius=0, max_iterations=1))
    ok = (cold.valid & warm.valid).numpy() & visible
    np.testing.assert_allclose(warm.uv_lm.numpy()[ok], cold.uv_lm.numpy()[ok], atol=0.02)
    err_one_cold = np.linalg.norm(one_cold.uv_lm.numpy() - uv_true, axis=-1)[visible]
    assert np.median(err_one_cold) > 0.5  # one iteration from the identity is not enough on this pair
    assert warm.valid.numpy()[visible].mean() > 0.95


def test_descriptor_refinement_corrects_a_wrong_geometry(scene):
    seq, src, _, T_true, uv_true, visible, _ = scene
    T_wrong = T_true.copy()
    c, s = np.cos(np.radians(1.0)), np.sin(np.radians(1.0))
    T_wrong[:3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ T_true[:3, :3]  # ~3 px off
    pair = src.predict(I, J, T_CiCj=T_wrong)
    coarse = _match(pair, config=MatchingConfig(refine_radius=0))
    refined = _match(pair, config=MatchingConfig(refine_radius=3, refine_dilations=[2, 1]))
    ok = (coarse.valid & refined.valid).numpy() & visible
    err_coarse = np.linalg.norm(coarse.uv.numpy() - uv_true, axis=-1)[ok]
    err_refined = np.linalg.norm(refined.uv.numpy() - uv_true, axis=-1)[ok]
    assert np.median(err_coarse) > 2.0
    assert np.median(err_refined) < 1.0


def test_invalid_queries_and_references_are_never_matched():
    H, W = 12, 16
    uv = pixel_grid_uv(H, W)
    z = torch.full((H * W,), 2.0)
    X = torch.stack(((uv[:, 0] - 8) / 10 * z, (uv[:, 1] - 6) / 10 * z, z), -1).reshape(H, W, 3)
    C = torch.ones(H, W)
    C[5, 7] = 0.0  # no reference point there
    ref = RayImage(X, C)
    Xq = X.clone().reshape(-1, 3)
    Xq[3] = float("nan")  # a broken query
    Xq[4] = 0.0  # a missing query
    m = match_pointmaps(ref, Xq)
    assert not m.valid[3] and not m.valid[4]
    assert not m.valid[5 * W + 7]  # its own pixel has no point: the neighbour's point is 10 % away
    assert bool(m.valid[torch.arange(H * W) != 5 * W + 7][5:].all())
    with pytest.raises(DataError, match="init_uv"):
        match_pointmaps(ref, Xq[:10])
    with pytest.raises(DataError, match="3 coordinates"):
        match_pointmaps(ref, torch.zeros(H * W, 2))


@pytest.mark.parametrize("kind", ["stereo", "mono"])
def test_matches_of_the_sources_own_pointmaps(scene, kind):
    """Each built-in source's pair (its own estimated pose and depths, every query with a point, low
    confidences included) matched against the true correspondences. Regression: the mono pair's
    degenerate ray-image regions once produced a NaN step (an out-of-bounds gather)."""
    seq = scene[0]
    vi, vj = render(seq, 40, stereo=True), render(seq, 46, stereo=True)
    uv_true, visible, _ = true_correspondences(seq.K, vi, vj)
    src = make_pointmap_source(PointmapSourceConfig(kind=kind), seq.K, baseline=seq.cfg.camera.baseline)
    src.add_frame(0, vi.image, right=vi.right)
    src.add_frame(1, vj.image, right=vj.right)
    pair = src.predict(0, 1)
    m = _match(pair)
    assert torch.isfinite(m.uv_lm).all()
    valid = m.valid.numpy()
    assert valid.mean() > 0.5
    err = np.linalg.norm(m.uv.numpy() - uv_true, axis=-1)[valid & visible]
    assert np.median(err) < 0.6 and np.percentile(err, 90) < 1.5


def test_matching_repeats_bytewise(scene):
    """The compiled LM and refinement (fgslam/core/jit.py: no fast-math, no threads) give the same bytes
    call to call."""
    *_, pair, _, _, _, _ = scene
    a, b = _match(pair), _match(pair)
    for x, y in ((a.uv_lm, b.uv_lm), (a.index, b.index), (a.valid, b.valid), (a.ray_error, b.ray_error),
                 (a.score, b.score)):
        assert x.numpy().tobytes() == y.numpy().tobytes()

def test_queries_without_a_ray_are_skipped_and_do_not_change_the_others(scene):
    """Non-finite / zero query points get no LM (their start kept, infinite ray error, invalid); the other
    queries' matches are those of a run without them."""
    *_, pair, _, _, _, _ = scene
    ref = RayImage(pair.X_i_in_i, pair.C_i)
    X = torch.as_tensor(pair.X_j_in_i, dtype=torch.float32).reshape(-1, 3)[::7].clone()
    D = torch.as_tensor(pair.D_j).reshape(-1, pair.D_j.shape[-1])[::7]
    init = (pixel_grid_uv(240, 320)[::7] + 0.3).clamp(max=torch.tensor([319.0, 239.0]))  # inside: kept as given
    holes = torch.zeros(X.shape[0], dtype=torch.bool)
    holes[::5] = True
    X_holes = X.clone()
    X_holes[holes] = torch.where(torch.arange(int(holes.sum()))[:, None] % 2 == 0, float("nan"), 0.0)
    m = match_pointmaps(ref, X_holes, init_uv=init, D_i=pair.D_i, D_j=D)
    alone = match_pointmaps(ref, X[~holes], init_uv=init[~holes], D_i=pair.D_i, D_j=D[~holes])
    assert not m.valid[holes].any() and torch.isinf(m.ray_error[holes]).all()
    torch.testing.assert_close(m.uv_lm[holes], init[holes], rtol=0, atol=0)
    assert int(alone.valid.sum()) > 0.5 * int((~holes).sum())
    for name in ("uv", "uv_lm", "index", "valid", "ray_error"):
        torch.testing.assert_close(getattr(m, name)[~holes], getattr(alone, name), rtol=0, atol=0)
