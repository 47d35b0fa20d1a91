"""Equal scores are ordered by index, not by the CPU (issue 21's "same figures on another CPU").

numpy's default sort and partition dispatch to SIMD kernels (AVX-512 where the CPU has it, AVX2 or
scalar code elsewhere) that order equal keys differently. The patch selection and the keyframe
database's query rank scores that tie (flat image regions, equal BoW scores): each is run here with the
AVX-512 kernels disabled (``NPY_DISABLE_CPU_FEATURES``, as on a CPU without them) and must give the same
bytes. On a CPU without AVX-512 both runs take the same kernels and the test passes trivially."""

from __future__ import annotations

import os
import subprocess
import sys

_PROBE = r"""
import hashlib, sys
import numpy as np
from fgslam.frontends.patch.patches import select_patches

h = hashlib.sha256()
rng = np.random.default_rng(4)
image = np.full((120, 160), 90, np.uint8)
image[40:80, 60:100] = rng.integers(0, 255, (40, 40))  # a textured square in a flat image: many equal (zero) scores
for score_width in (0, 80):
    h.update(select_patches(image, 48, 4, [4, 3], "corners", np.random.default_rng(1), 8, score_width).tobytes())
argsort_ties = np.argsort(-np.repeat(np.arange(20, dtype=np.float32), 250))  # the kernels themselves: ties by SIMD order
print(h.hexdigest(), hashlib.sha256(argsort_ties.tobytes()).hexdigest())
"""


def _probe(extra_env: dict) -> list[str]:
    env = {**os.environ, **extra_env}
    out = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, env=env, check=True)
    return out.stdout.split()


def test_patch_selection_orders_ties_by_index_on_any_numpy_kernel():
    own = _probe({})
    other = _probe({"NPY_DISABLE_CPU_FEATURES": "AVX512_SPR,AVX512_ICL,X86_V4"})
    assert own[0] == other[0]


def test_patch_selection_ties_keep_their_cell_order():
    """On a flat image every score ties: the centres keep the order of the cells' first blocks."""
    import numpy as np

    from fgslam.frontends.patch.patches import select_patches

    image = np.full((64, 96), 50, np.uint8)
    a = select_patches(image, 12, 4, [4, 3], "corners", np.random.default_rng(0), 8)
    b = select_patches(image, 12, 4, [4, 3], "corners", np.random.default_rng(0), 8)
    assert a.tobytes() == b.tobytes() and len(np.unique(a, axis=0)) == 12


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
