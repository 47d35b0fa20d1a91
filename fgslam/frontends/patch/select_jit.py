"""Compiled corner selection of the patch frontend (:func:`fgslam.frontends.patch.patches.select_patches`,
method ``corners``): the strongest pixel of every block of the corner response, the best ``quota`` of
them in every grid cell, then the best of the rest up to ``count`` (:mod:`fgslam.core.jit`). It is the
implementation; its order of candidates and of equal scores is the one a stable sort gives (documented
on :func:`select_corners`).
"""

from __future__ import annotations

import numpy as np

from ...core.jit import kernel


@kernel
def _block_maxima(score, border, block, hb, wb, width, height, gx, gy):
    """Per block of ``block`` x ``block`` pixels (``hb`` x ``wb`` blocks, row-major, ``border`` pixels in):
    its highest score (the first in row-major order among equal ones), the pixel ``(u, v)`` and the grid
    cell (``gx`` x ``gy`` cells over the ``width`` x ``height`` image) of that pixel."""
    n = hb * wb
    best = np.empty(n, np.float32)
    u = np.empty(n, np.int64)
    v = np.empty(n, np.int64)
    cell = np.empty(n, np.int64)
    for by in range(hb):
        for bx in range(wb):
            k = by * wb + bx
            y0, x0 = border + by * block, border + bx * block
            top, ty, tx = score[y0, x0], 0, 0
            for dy in range(block):
                for dx in range(block):
                    s = score[y0 + dy, x0 + dx]
                    if s > top:
                        top, ty, tx = s, dy, dx
            best[k], u[k], v[k] = top, x0 + tx, y0 + ty
            cx = min(max(u[k] * gx // width, 0), gx - 1)
            cy = min(max(v[k] * gy // height, 0), gy - 1)
            cell[k] = cx + gx * cy
    return best, u, v, cell


@kernel
def _insert(idx, keys, size, capacity, i, key):
    """Insert candidate ``i`` with ``key`` into the ascending list ``idx[:size]`` / ``keys[:size]`` after the
    equal keys (a candidate with a larger index comes later, as in a stable sort), keeping at most
    ``capacity``; returns the new size."""
    p = size
    while p > 0 and keys[p - 1] > key:
        p -= 1
    if p >= capacity:
        return size
    last = min(size, capacity - 1)
    for q in range(last, p, -1):
        idx[q], keys[q] = idx[q - 1], keys[q - 1]
    idx[p], keys[p] = i, key
    return min(size + 1, capacity)


@kernel
def select_corners(score, border, block, width, height, gx, gy, jitter, count):
    """Indices of the chosen block maxima and the ``(u, v)`` pixels of every block maximum.

    With ``quota = max(1, count // (gx * gy))``: the ``quota`` best blocks of every cell by score plus
    ``jitter`` (cells in order; a tie by block index), ordered by score alone (stable: a tie keeps the
    cell order) and cut to ``count``; then, while fewer than ``count``, the best remaining blocks by score
    in block order (stable). The result equals numpy's ``lexsort`` by cell and ``-(score + jitter)``, a
    stable ``argsort`` of ``-score`` over the chosen, and a stable ``argsort`` of ``-score`` over the rest.
    ``jitter`` has one value per block (``hb * wb``)."""
    hb = max(0, (score.shape[0] - 2 * border) // block)
    wb = max(0, (score.shape[1] - 2 * border) // block)
    best, u, v, cell = _block_maxima(score, border, block, hb, wb, width, height, gx, gy)
    n = hb * wb
    cells = gx * gy
    quota = max(1, count // cells)
    top_idx = np.empty((cells, quota), np.int64)
    top_key = np.empty((cells, quota), np.float64)
    sizes = np.zeros(cells, np.int64)
    for i in range(n):
        c = cell[i]
        sizes[c] = _insert(top_idx[c], top_key[c], sizes[c], quota, i, -(np.float64(best[i]) + jitter[i]))
    total = 0
    for c in range(cells):
        total += sizes[c]
    picked = min(total, count)
    chosen = np.empty(count, np.int64)
    chosen_key = np.empty(count, np.float64)
    size = 0
    for c in range(cells):  # stable by -score over the per-cell picks in cell order
        for r in range(sizes[c]):
            i = top_idx[c, r]
            size = _insert(chosen, chosen_key, size, picked, i, -np.float64(best[i]))
    if size < count:
        taken = np.zeros(n, np.bool_)
        for r in range(size):
            taken[chosen[r]] = True
        need = count - size
        rest = np.empty(need, np.int64)
        rest_key = np.empty(need, np.float64)
        filled = 0
        for i in range(n):
            if not taken[i]:
                filled = _insert(rest, rest_key, filled, need, i, -np.float64(best[i]))
        for r in range(filled):
            chosen[size + r] = rest[r]
        size += filled
    return chosen[:size], u, v
