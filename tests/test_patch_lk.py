"""Built-in Lucas-Kanade source: recovers known shifts and warps from a reprojection start,
flags forward-backward failures, selection of patches."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fgslam.frontends.patch.config import LKConfig
from fgslam.frontends.patch.patches import select_patches
from fgslam.frontends.patch.lk import LKSource


def _texture(h=240, w=320, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0, 255, (h // 4, w // 4)).astype(np.float32)
    img = cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(cv2.GaussianBlur(img, (0, 0), 1.0), 0, 255)


def _warp(img: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Image whose pixel x shows img at A^-1 x (A: 2x3 affine mapping source to target pixels)."""
    return cv2.warpAffine(img, A, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_recovers_known_shift_from_offset_start(scale):
    img = _texture()
    A = np.array([[1.0, 0.0, 7.3], [0.0, 1.0, -4.6]])
    src, tgt = img.astype(np.uint8), _warp(img, A).astype(np.uint8)
    lk = LKSource(LKConfig(scale=scale), window=21)
    rng = np.random.default_rng(1)
    uv = np.stack([rng.uniform(60, 260, 50), rng.uniform(50, 190, 50)], 1)
    truth = uv + A[:, 2]
    pred = truth + rng.uniform(-3, 3, truth.shape)  # a reprojection a few pixels off
    m = lk.measure(lk.prepare(src), lk.prepare(tgt), uv, pred)
    ok = m.confidence > 0
    assert ok.mean() > 0.9
    err = np.linalg.norm(m.uv[ok] - truth[ok], axis=1)
    assert np.median(err) < (0.1 if scale == 1.0 else 0.2)
    # the residual update uv - pred is what DPVO's operator would predict
    assert np.allclose((m.uv - pred)[ok], (truth - pred)[ok], atol=0.5)


def test_recovers_small_rotation_and_zoom():
    img = _texture(seed=2)
    A = cv2.getRotationMatrix2D((160, 120), 3.0, 1.04)
    src, tgt = img.astype(np.uint8), _warp(img, A).astype(np.uint8)
    lk = LKSource(LKConfig(), window=21)
    rng = np.random.default_rng(3)
    uv = np.stack([rng.uniform(70, 250, 60), rng.uniform(60, 180, 60)], 1)
    truth = uv @ A[:, :2].T + A[:, 2]
    m = lk.measure(lk.prepare(src), lk.prepare(tgt), uv, uv)
    ok = m.confidence > 0
    assert ok.mean() > 0.8
    assert np.median(np.linalg.norm(m.uv[ok] - truth[ok], axis=1)) < 0.3


def test_forward_backward_failures_are_flagged():
    img = _texture(seed=4).astype(np.uint8)
    other = _texture(seed=5).astype(np.uint8)  # unrelated image: nothing can be tracked consistently
    blank = np.full_like(img, 128)
    lk = LKSource(LKConfig(), window=21)
    rng = np.random.default_rng(6)
    uv = np.stack([rng.uniform(40, 280, 80), rng.uniform(40, 200, 80)], 1)
    m_blank = lk.measure(lk.prepare(img), lk.prepare(blank), uv, uv)
    assert np.all(m_blank.confidence == 0)
    m_other = lk.measure(lk.prepare(img), lk.prepare(other), uv, uv + 5.0)
    assert (m_other.confidence > 0).mean() < 0.2
    # rejected tracks return the prediction, never NaN
    assert np.isfinite(m_other.uv).all()
    # batch API: one result per request, same as single calls
    ms = lk.measure_batch([(lk.prepare(img), lk.prepare(img), uv, uv + 1.0), (lk.prepare(img), lk.prepare(blank), uv, uv)])
    assert (ms[0].confidence > 0).mean() > 0.9 and np.all(ms[1].confidence == 0)
    assert np.median(np.linalg.norm(ms[0].uv - uv, axis=1)) < 0.05


def test_select_patches_spread_and_border():
    img = _texture(seed=7).astype(np.uint8)
    rng = np.random.default_rng(0)
    uv = select_patches(img, 96, 12, [8, 4], "corners", rng)
    assert uv.shape == (96, 2)
    assert uv[:, 0].min() >= 12 and uv[:, 0].max() <= 320 - 13
    assert uv[:, 1].min() >= 12 and uv[:, 1].max() <= 240 - 13
    cells = np.unique((uv[:, 0] * 8 // 320).astype(int) + 8 * (uv[:, 1] * 4 // 240).astype(int))
    assert cells.size >= 28  # spread over (almost) all 32 cells
    uv_r = select_patches(img, 96, 12, [8, 4], "random", rng)
    assert uv_r.shape == (96, 2) and uv_r.min() >= 12
    # a flat image still yields K centres (LK will reject them)
    assert select_patches(np.full_like(img, 50), 96, 12, [8, 4], "corners", rng).shape == (96, 2)


def _corners_by_sorting(score, count, border, grid, block, jitter):
    """The corner rule by numpy's sorts (the implementation before the compiled kernel): block maxima,
    ``lexsort`` by cell and ``-(score + jitter)``, the cells' quotas by a stable sort of ``-score``, the
    rest by another."""
    h, w = score.shape
    inner = score[border: h - border, border: w - border]
    hb, wb = inner.shape[0] // block, inner.shape[1] // block
    tiles = inner[: hb * block, : wb * block].reshape(hb, block, wb, block).transpose(0, 2, 1, 3).reshape(hb, wb, -1)
    arg = tiles.argmax(-1)
    best = np.take_along_axis(tiles, arg[..., None], -1)[..., 0].reshape(-1)
    by, bx = np.meshgrid(np.arange(hb), np.arange(wb), indexing="ij")
    v = (by * block + arg // block).reshape(-1) + border
    u = (bx * block + arg % block).reshape(-1) + border
    gx, gy = grid
    cell = (u * gx // w).clip(0, gx - 1) + gx * (v * gy // h).clip(0, gy - 1)
    order = np.lexsort((-(best + jitter), cell))
    cell_sorted = cell[order]
    rank = np.arange(order.size) - np.searchsorted(cell_sorted, cell_sorted, side="left")
    chosen = order[rank < max(1, count // (gx * gy))]
    chosen = chosen[np.argsort(-best[chosen], kind="stable")][:count]
    if chosen.size < count:
        left = np.ones(best.size, dtype=bool)
        left[chosen] = False
        rest = np.flatnonzero(left)
        chosen = np.concatenate([chosen, rest[np.argsort(-best[rest], kind="stable")][: count - chosen.size]])
    return np.stack([u[chosen], v[chosen]], 1).astype(np.float64)


@pytest.mark.parametrize("h, w, count, border, grid, block", [
    (240, 320, 48, 6, (8, 4), 4),     # the RGB-D preset's half-resolution response: one per cell, topped up
    (240, 320, 96, 12, (8, 4), 8),    # three per cell
    (96, 128, 200, 4, (4, 3), 8),     # more wanted than there are blocks
    (60, 50, 10, 4, (3, 5), 5),       # ragged blocks at the edges, fewer than one per cell
    (20, 20, 5, 6, (2, 2), 10),       # no whole block inside the border: random centres
    (96, 128, 0, 4, (4, 3), 8),       # none wanted
])
def test_compiled_corner_selection_equals_the_sorting_rule(monkeypatch, h, w, count, border, grid, block):
    """The compiled selection picks the pixels, in the order, that numpy's sorts pick, also among equal
    scores (a response quantised to a few levels, flat regions) and when the cells run short."""
    rng = np.random.default_rng(h * w + count)
    for levels in (3, 1000):  # many ties; almost none
        score = (rng.integers(0, levels, (h, w)) / levels).astype(np.float32)
        score[rng.random((h, w)) < 0.3] = 0.0  # flat regions
        monkeypatch.setattr(cv2, "cornerMinEigenVal", lambda image, size, s=score: s)
        blocks = max(0, (h - 2 * border) // block) * max(0, (w - 2 * border) // block)
        got = select_patches(np.zeros((h, w), np.uint8), count, border, list(grid), "corners", np.random.default_rng(5), block)
        assert got.shape == (count, 2)
        if blocks == 0:  # numpy's reshape of no blocks failed; the compiled rule pads with random centres
            assert ((got >= border) & (got <= np.array([w, h]) - 1 - border)).all()
            continue
        expected = _corners_by_sorting(score, count, border, grid, block, np.random.default_rng(5).uniform(0, 1e-9, blocks))
        np.testing.assert_array_equal(got[:min(count, blocks)], expected)


def test_row_nanmedian_equals_numpy_nanmedian():
    """The sensor-depth window's median (the patch family's depth look-up): the values of
    ``np.nanmedian(x, axis=1)``, bit for bit, on random rows with missing readings, all-NaN rows,
    one-column and empty arrays."""
    import warnings

    from fgslam.frontends.patch.patches import row_nanmedian

    rng = np.random.default_rng(0)
    cases = [np.zeros((3, 0)), np.full((2, 4), np.nan), np.array([[1.0], [np.nan]]), np.array([[-0.0], [0.0]]),
             np.array([[0.0, -0.0, 0.0, np.nan], [np.inf, -np.inf, 1.0, 2.0], [1e308, 1e308, np.nan, np.nan]])]
    for _ in range(300):
        m, k = rng.integers(1, 60), rng.integers(1, 50)
        x = rng.normal(size=(m, k)) * 10 ** rng.uniform(-3, 3)
        x[rng.random((m, k)) < rng.random()] = np.nan
        cases.append(x)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # numpy warns on all-NaN rows
        for x in cases:
            ours, theirs = row_nanmedian(x), np.nanmedian(x, axis=1)
            assert np.array_equal(ours, theirs, equal_nan=True) and ours.dtype == theirs.dtype
            number = ~np.isnan(theirs)  # the sign of a zero median too (a NaN's sign bit means nothing)
            assert np.array_equal(np.signbit(ours[number]), np.signbit(theirs[number]))
