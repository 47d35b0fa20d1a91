"""Equal scores are ordered by index, not by the CPU (issue 21's "same figures on another CPU").

numpy's default sort and partition dispatch to SIMD kernels (AVX-512 where the CPU has it, AVX2 or
scalar code elsewhere) that order equal keys differently (5,000 keys in 20 levels: two permutations
under numpy's AVX-512 and AVX2 kernels on one machine). The patch selection and the keyframe database's
query rank scores that tie (flat image regions, equal BoW scores): both follow one total order, checked
here against the rule written out (the former code fails both tests)."""

from __future__ import annotations


def test_patch_selection_ranks_equal_scores_by_their_quota_order(monkeypatch):
    """Corner responses in three levels (many blocks tie): the centres come out by score, and equal scores
    in the order the per-cell quota took them (cell by cell), as an explicit sort gives; a sort kernel's
    own order of equal keys would differ."""
    import cv2
    import numpy as np

    from fgslam.frontends.patch.patches import select_patches

    h, w, block, border, grid, count = 96, 128, 8, 4, (4, 3), 48
    levels = np.random.default_rng(2).integers(1, 4, ((h - 2 * border) // block, (w - 2 * border) // block))
    score = np.zeros((h, w), np.float32)
    score[border + 3:border + 3 + block * levels.shape[0]:block, border + 5:border + 5 + block * levels.shape[1]:block] = levels
    monkeypatch.setattr(cv2, "cornerMinEigenVal", lambda image, size: score)
    uv = select_patches(np.zeros((h, w), np.uint8), count, border, list(grid), "corners", np.random.default_rng(0), block)

    # the rule, written out: per cell the quota of best blocks (ties by the jitter drawn first), then by score
    best = levels.reshape(-1).astype(np.float32)
    jitter = np.random.default_rng(0).uniform(0, 1e-9, best.shape)
    by, bx = np.divmod(np.arange(best.size), levels.shape[1])
    u, v = bx * block + 5 + border, by * block + 3 + border
    cell = (u * grid[0] // w).clip(0, grid[0] - 1) + grid[0] * (v * grid[1] // h).clip(0, grid[1] - 1)
    quota = count // (grid[0] * grid[1])
    taken = []
    for c in range(grid[0] * grid[1]):
        members = sorted(np.flatnonzero(cell == c), key=lambda i: (-(best[i] + jitter[i]), i))
        taken += members[:quota]
    expected = sorted(taken, key=lambda i: (-best[i], taken.index(i)))
    assert uv.tolist() == [[float(u[i]), float(v[i])] for i in expected]


def test_database_query_ranks_equal_scores_by_entry():
    """Keyframes with the same BoW vector score the same: the query keeps the first entries, in order."""
    import numpy as np

    from fgslam.loop.bow import BowDatabase
    from fgslam.loop.vocabulary import BowVector

    db = BowDatabase(50)
    same = BowVector(np.array([3, 7, 11], np.int32), np.array([0.5, 0.25, 0.25]))
    other = BowVector(np.array([3, 8], np.int32), np.array([0.5, 0.5]))
    for kf in range(300):
        db.add(1000 + kf, same if kf % 3 else other)
    found = db.query(same, max_results=10)
    assert [r.entry for r in found] == [1, 2, 4, 5, 7, 8, 10, 11, 13, 14]
    assert len({r.score for r in found}) == 1
