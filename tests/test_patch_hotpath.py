"""Speed paths of the patch frontend: PatchBlock's evaluation memo answers exactly what a fresh
evaluation would, and the gtsam/numpy Sim(3) helpers of the frontend equal fgslam.core.lie's operations."""

from __future__ import annotations

import numpy as np
import torch

from fgslam.frontends.patch.ba import PatchBlock
from fgslam.frontends.records import sim3_interp as _interp, sim3_power as _sim3_power
from fgslam.core.lie import gtsam_matrix as _gtsam_matrix, gtsam_sim3 as _gtsam_sim3
from fgslam.core.lie import Sim3
from fgslam.backend.keys import pose_key

from test_patch_ba import K, _edges, _scene, _values


def _block(rng):
    poses, src, uv, d = _scene(rng)
    e_src, e_tgt, e_patch, e_uv = _edges(poses, src, uv, d, 5, 0.5, rng)
    d0 = d * rng.uniform(0.8, 1.2, len(d))
    w = rng.uniform(0.2, 1.0, len(e_src))
    empty = torch.zeros(0, 3, 3, dtype=torch.float64)

    def make():
        return PatchBlock([pose_key(i) for i in range(5)], empty, torch.zeros(0, 3), torch.zeros(0), e_src, e_tgt,
                          np.zeros(len(e_src), bool), uv[e_patch], e_uv, w, e_patch, K, d0)

    return make, poses


def test_memo_answers_like_a_fresh_block():
    rng = np.random.default_rng(3)
    make, poses = _block(rng)
    values = _values(poses)
    moved = _values(Sim3(poses.R, poses.t + 0.02 * torch.as_tensor(rng.normal(size=(5, 3))), poses.s))  # not a gauge motion
    block = make()
    c0 = block.cost(values)  # first evaluation of a fresh block (memo with Jacobians)
    keys, H, g, c = block.linearize(values)[0]  # answered from the memo
    _, H_ref, g_ref, c_ref = make().linearize(values)[0]
    np.testing.assert_array_equal(H, H_ref)
    np.testing.assert_array_equal(g, g_ref)
    assert c == c_ref and c0 == make().cost(values)
    # other poses, other structure: recomputed, not served stale
    assert block.cost(moved) == make().cost(moved)
    assert block.cost(moved) != block.cost(values)
    trial = block.structure * 1.05
    fresh = make()
    fresh.set_structure(trial)
    assert block.cost(values, trial) == fresh.cost(values)
    block.set_structure(trial)
    r, valid = block.residuals(values)
    r_ref, valid_ref = fresh.residuals(values)
    assert torch.equal(r, r_ref) and torch.equal(valid, valid_ref)


def test_structure_clamp_is_the_adopted_structure():
    rng = np.random.default_rng(4)
    make, _ = _block(rng)
    block = make()
    s = block.structure.clone()
    s[0] = -1.0
    clamped = block.clamp_structure(s)
    assert float(clamped[0]) == block.config.min_structure
    block.set_structure(s)
    assert torch.equal(block.structure, clamped)


def test_sim3_helpers_match_lie():
    rng = np.random.default_rng(5)
    for _ in range(5):
        A = Sim3.exp(torch.as_tensor(rng.normal(size=7) * 0.4))
        B = Sim3.exp(torch.as_tensor(rng.normal(size=7) * 0.4))
        Ma, Mb = A.matrix().numpy(), B.matrix().numpy()
        S = _gtsam_sim3(Ma)
        np.testing.assert_allclose(S.matrix(), A.to_gtsam().matrix(), atol=1e-12)
        np.testing.assert_allclose(_gtsam_matrix(S), Ma, atol=1e-12)
        alpha = float(rng.uniform(-1.0, 2.0))
        np.testing.assert_allclose(_sim3_power(Ma, alpha), Sim3.exp(alpha * A.log()).matrix().numpy(), atol=1e-10)
        ref = (A @ Sim3.exp(alpha * (A.inverse() @ B).log())).matrix().numpy()
        np.testing.assert_allclose(_interp(Ma, Mb, alpha), ref, atol=1e-10)
