"""Tests of fgslam.factors.schur (exact structure elimination, square-root form, gtsam factors) and of
fgslam.factors.visual_block (blocks)."""

import gtsam
import numpy as np
import pytest
import torch

from fgslam.factors.schur import (
    POSE_DIM,
    SlotGroups,
    factorize_psd,
    jacobian_factor,
    schur_reduce,
    structure_gauss_newton_step,
    to_gaussian_factor,
)
from fgslam.factors.visual_block import BlockConfig, InverseDepthBlock
from fgslam.core.lie import Sim3

D = POSE_DIM


def random_problem(seed, n=60, m=2, k=4, num_structs=15, zero_info_struct=True):
    """Random linear least-squares problem in (poses, structure); returns tensors and dense matrices."""
    g = torch.Generator().manual_seed(seed)
    r = torch.randn(n, m, generator=g, dtype=torch.float64)
    J = torch.randn(n, m, 2, D, generator=g, dtype=torch.float64)
    slots = torch.randint(0, k, (n, 2), generator=g)
    E = torch.randn(n, m, generator=g, dtype=torch.float64)
    idx = torch.randint(0, num_structs, (n,), generator=g)
    w = torch.rand(n, m, generator=g, dtype=torch.float64) + 0.1
    if zero_info_struct:
        # structure 0 has only zero-weight rows and the last structure no rows at all: no information
        w[idx == 0] = 0.0
        idx[idx == num_structs - 1] = 1
    # dense joint Jacobian [A_x | A_d] over all rows
    rows = n * m
    A_x = np.zeros((rows, k * D))
    A_d = np.zeros((rows, num_structs))
    for i in range(n):
        for a in range(m):
            row = i * m + a
            for s in range(2):
                A_x[row, D * slots[i, s]:D * slots[i, s] + D] += J[i, a, s].numpy()
            A_d[row, idx[i]] = E[i, a]
    return dict(r=r, J=J, slots=slots, E=E, idx=idx, w=w, k=k, P=num_structs,
                A_x=A_x, A_d=A_d, rv=r.reshape(-1).numpy(), wv=w.reshape(-1).numpy())


@pytest.mark.parametrize("seed,damping", [(0, 0.0), (1, 0.0), (2, 0.3), (3, "per-structure")])
def test_reduced_quadratic_equals_joint_minimised_over_structure(seed, damping):
    p = random_problem(seed)
    if damping == "per-structure":
        damping = torch.rand(p["P"], generator=torch.Generator().manual_seed(seed), dtype=torch.float64) + 0.1
    sys_ = schur_reduce(p["r"], p["J"], p["slots"], p["E"], p["idx"], p["w"], p["k"], p["P"], damping,
                        min_information=1e-12)
    damping_vec = np.broadcast_to(np.asarray(damping, dtype=np.float64), (p["P"],))
    rng = np.random.default_rng(seed)
    W = np.diag(p["wv"])
    informative = (p["A_d"].T ** 2 @ p["wv"]) + damping_vec > 0
    for _ in range(5):
        dx = rng.standard_normal(p["k"] * D)
        rhs = p["rv"] + p["A_x"] @ dx
        # explicit joint minimisation over the informative structure variables
        Ad = p["A_d"][:, informative]
        lam = damping_vec[informative]
        N = Ad.T @ W @ Ad + np.diag(lam)
        dd = -np.linalg.solve(N, Ad.T @ W @ rhs)
        joint = (rhs + Ad @ dd) @ W @ (rhs + Ad @ dd) + dd @ (lam * dd)
        assert sys_.model(torch.as_tensor(dx)) == pytest.approx(joint, rel=1e-10, abs=1e-9)
        back = sys_.back_substitute(torch.as_tensor(dx)).numpy()
        np.testing.assert_allclose(back[informative], dd, rtol=1e-9, atol=1e-10)
        np.testing.assert_array_equal(back[~informative], 0.0)
    H = sys_.H.numpy()
    np.testing.assert_allclose(H, H.T, atol=1e-12)
    assert np.linalg.eigvalsh(H).min() > -1e-9 * np.abs(H).max()


@pytest.mark.parametrize("base_damping", [0.0, 0.3])
def test_damped_system_equals_the_elimination_with_the_damping_added(base_damping):
    """``SchurSystem.damped(lam)`` (the backend's LM damping of the structure) is the same linearisation
    eliminated with ``lam`` more on every structure's information: ``schur_reduce`` given that damping
    (its bytes when the block has no damping of its own), always relative to the undamped system (no accumulation), and its back-substituted
    structure step shrinks as ``lam`` grows."""
    p = random_problem(4)
    args = (p["r"], p["J"], p["slots"], p["E"], p["idx"], p["w"], p["k"], p["P"])
    sys_ = schur_reduce(*args, base_damping, min_information=1e-12)
    informative = sys_.inv_C > 0  # a structure without information stays left out when damped
    assert not informative.all() if base_damping == 0.0 else informative.all()
    dx = torch.as_tensor(np.random.default_rng(4).standard_normal(p["k"] * D))
    steps = []
    for lam in (1e-3, 1.0, 1e3):
        direct = schur_reduce(*args, base_damping + lam, min_information=1e-12)
        for damped in (sys_.damped(lam), sys_.damped(2.0 * lam).damped(lam)):
            for name in ("H", "g"):  # (C + base) + lam against C + (base + lam): rounding apart
                a, b = getattr(damped, name).numpy(), getattr(direct, name).numpy()
                assert a.tobytes() == b.tobytes() if base_damping == 0.0 else np.allclose(a, b, rtol=1e-12, atol=0), name
            a, b = damped.inv_C[informative].numpy(), direct.inv_C[informative].numpy()
            assert a.tobytes() == b.tobytes() if base_damping == 0.0 else np.allclose(a, b, rtol=1e-12, atol=0)
            assert (damped.inv_C[~informative] == 0).all()
            assert damped.c == pytest.approx(direct.c, rel=1e-12)
        steps.append(float(sys_.damped(lam).back_substitute(dx).abs().max()))
    assert steps[0] > steps[1] > steps[2] > 0.0


def test_precomputed_groups_match_internal_sort():
    p = random_problem(3, zero_info_struct=False)
    order, groups = SlotGroups.sort_rows(p["slots"])
    a = schur_reduce(p["r"], p["J"], p["slots"], p["E"], p["idx"], p["w"], p["k"], p["P"])
    b = schur_reduce(p["r"][order], p["J"][order], p["slots"][order], p["E"][order], p["idx"][order],
                     p["w"][order], p["k"], p["P"], groups=groups)
    np.testing.assert_allclose(a.H.numpy(), b.H.numpy(), rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(a.g.numpy(), b.g.numpy(), rtol=1e-12, atol=1e-10)
    assert a.c == pytest.approx(b.c, rel=1e-12)
    assert all(groups.slots[i] != groups.slots[i + 1] for i in range(len(groups.slots) - 1))


def test_structure_gauss_newton_step_is_exact_minimiser_for_linear_residuals():
    p = random_problem(4, zero_info_struct=False)
    step = structure_gauss_newton_step(p["r"], p["E"], p["idx"], p["w"], p["P"]).numpy()
    # with poses fixed the joint problem separates per structure
    W = np.diag(p["wv"])
    dd = -np.linalg.lstsq(np.sqrt(W) @ p["A_d"], np.sqrt(W) @ p["rv"], rcond=None)[0]
    has_rows = np.abs(p["A_d"]).sum(0) > 0
    np.testing.assert_allclose(step[has_rows], dd[has_rows], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_factorize_psd_reproduces_singular_quadratic(seed):
    p = random_problem(seed)
    sys_ = schur_reduce(p["r"], p["J"], p["slots"], p["E"], p["idx"], p["w"], p["k"], p["P"])
    H, g, c = sys_.H.numpy(), sys_.g.numpy(), sys_.c
    # make it rank deficient (a gauge): project out two directions
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((H.shape[0], 2)))
    Pm = np.eye(H.shape[0]) - Q @ Q.T
    H, g = Pm @ H @ Pm, Pm @ g
    A, b, e = factorize_psd(H, g, c)
    assert A.shape[0] == H.shape[0] - 2
    np.testing.assert_allclose(A.T @ A, H, atol=1e-9 * np.abs(H).max())
    np.testing.assert_allclose(A.T @ b, g, atol=1e-9 * np.abs(g).max())
    for _ in range(3):
        x = rng.standard_normal(H.shape[0])
        assert np.sum((A @ x + b) ** 2) + e**2 == pytest.approx(x @ H @ x + 2 * g @ x + c, rel=1e-9)


@pytest.mark.parametrize("kind,k", [("hessian", 4), ("hessian", 1), ("jacobian", 3), ("jacobian", 2), ("jacobian", 5)])
def test_gtsam_factor_error_equals_reduced_cost(kind, k):
    p = random_problem(5, k=k, n=40)
    sys_ = schur_reduce(p["r"], p["J"], p["slots"], p["E"], p["idx"], p["w"], p["k"], p["P"])
    keys = [gtsam.symbol("x", i) for i in range(k)]
    factor = to_gaussian_factor(keys, sys_.H.numpy(), sys_.g.numpy(), sys_.c, kind=kind)
    assert list(factor.keys()) == keys
    rng = np.random.default_rng(7)
    for _ in range(3):
        dx = rng.standard_normal(k * D)
        vv = gtsam.VectorValues()
        for i, key in enumerate(keys):
            vv.insert(key, dx[D * i:D * i + D])
        assert factor.error(vv) == pytest.approx(0.5 * sys_.model(torch.as_tensor(dx)), rel=1e-9)


@pytest.mark.parametrize("kind", ["hessian", "jacobian"])
def test_gtsam_factor_without_constant_differs_by_a_constant(kind):
    """``c=None`` (the global BA's per-source factors): the same quadratic without its constant."""
    k = 4
    p = random_problem(6, k=k, n=40)
    sys_ = schur_reduce(p["r"], p["J"], p["slots"], p["E"], p["idx"], p["w"], p["k"], p["P"])
    keys = list(range(k))
    factor = to_gaussian_factor(keys, sys_.H.numpy(), sys_.g.numpy(), None, kind=kind)
    rng = np.random.default_rng(8)
    offsets = []
    for _ in range(3):
        dx = rng.standard_normal(k * D)
        vv = gtsam.VectorValues()
        for i, key in enumerate(keys):
            vv.insert(key, dx[D * i:D * i + D])
        offsets.append(0.5 * sys_.model(torch.as_tensor(dx)) - factor.error(vv))
    np.testing.assert_allclose(offsets, offsets[0], rtol=1e-9)
    assert offsets[0] > 0  # the left-out part: 0.5 (c - b^T b) >= 0


def test_jacobian_factor_on_keys_of_mixed_dimensions():
    """One key dimension per key (a pose, a velocity, a bias...): the error is ``0.5 |A x - rhs|^2``."""
    dims = [D, 3, 6, D]
    keys = list(range(len(dims)))
    rng = np.random.default_rng(9)
    A = rng.standard_normal((20, sum(dims)))
    rhs = rng.standard_normal(20)
    factor = jacobian_factor(keys, A, rhs, dims)
    x = rng.standard_normal(sum(dims))
    vv = gtsam.VectorValues()
    for key, part in zip(keys, np.split(x, np.cumsum(dims)[:-1])):
        vv.insert(key, part)
    assert factor.error(vv) == pytest.approx(0.5 * float(np.sum((A @ x - rhs) ** 2)), rel=1e-12)
    with pytest.raises(ValueError, match="do not match"):
        jacobian_factor(keys, A, rhs, dims[:-1])


# ---------------------------------------------------------------------------------------------- blocks


def small_block(seed, noise=0.5, patch=False):
    """Source keyframe 0 observed in keyframes 1, 2; random Sim3 poses; returns (block, values)."""
    g = torch.Generator().manual_seed(seed)
    dtype = torch.float64
    K = torch.tensor([300.0, 300.0, 160.0, 120.0], dtype=dtype)
    xi = 0.2 * torch.rand(3, 7, generator=g, dtype=dtype) - 0.1  # rotations < 0.1 rad, |log s| < 0.1
    xi[:, 3:6] *= 3.0  # translations < 0.3 for points 2 to 5 units deep
    poses = Sim3.exp(xi)
    P = 30
    per = 4 if patch else 1
    uv = torch.rand(P, per, 2, generator=g, dtype=dtype) * torch.tensor([320.0, 240.0], dtype=dtype)
    d_true = 0.2 + 0.3 * torch.rand(P, generator=g, dtype=dtype)
    uv_src, d_rows = uv.reshape(-1, 2), d_true[:, None].expand(P, per).reshape(-1)
    idx = torch.arange(P)[:, None].expand(P, per).reshape(-1)
    from fgslam.factors.reprojection import reproject

    src, tgt, uvs, uvt, ids = [], [], [], [], []
    for j in (1, 2):
        uv_j, ok = reproject(uv_src, d_rows, poses[0], poses[j], K)
        assert bool(ok.all())
        uvt.append(uv_j + noise * torch.randn(uv_j.shape, generator=g, dtype=dtype))
        src.append(torch.zeros(len(uv_src), dtype=torch.long))
        tgt.append(torch.full((len(uv_src),), j))
        uvs.append(uv_src)
        ids.append(idx)
    w = torch.rand(2 * len(uv_src), 2, generator=g, dtype=dtype) + 0.5
    keys = [gtsam.symbol("x", i) for i in range(3)]
    block = InverseDepthBlock(keys, torch.cat(src), torch.cat(tgt), torch.cat(uvs), torch.cat(uvt), torch.cat(ids),
                              w, K, d_true * 1.1, BlockConfig(refine_steps=30))
    values = gtsam.Values()
    for key, T in zip(keys, poses.to_gtsam()):
        values.insert(key, T)
    return block, values


@pytest.mark.parametrize("patch", [False, True])
def test_block_gradient_matches_finite_differences_at_optimal_structure(patch):
    block, values = small_block(0, patch=patch)
    cost_refined = block.refine_structure(values)
    assert cost_refined == pytest.approx(block.cost(values), rel=1e-12)
    keys, H, g, c = block.linearize(values)[0]
    # at the optimal structure the reduced constant is the cost and the reduced gradient is the
    # partial gradient of the cost in the poses (envelope theorem): check against central differences
    assert 0.5 * c == pytest.approx(block.cost(values), rel=1e-8)
    d_opt = block.structure.clone()
    eps = 1e-6
    fd = np.zeros(len(keys) * D)
    for col in range(len(keys) * D):
        for sign in (1.0, -1.0):
            vv = gtsam.VectorValues()
            for a, key in enumerate(keys):
                step = np.zeros(D)
                if a == col // D:
                    step[col % D] = sign * eps
                vv.insert(key, step)
            fd[col] += sign * block.cost(values.retract(vv), d_opt) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * np.abs(g).max())
    # the target poses' scale columns are exact zeros (scale gauge of inverse depth)
    assert np.all(g[[D + 6, 2 * D + 6]] == 0.0) and np.all(H[:, [D + 6, 2 * D + 6]] == 0.0)


def test_block_back_substitution_predicts_joint_gauss_newton_structure():
    block, values = small_block(1, noise=0.0)
    block.refine_structure(values, steps=30)  # optimal structure at the linearisation point
    keys, H, g, c = block.linearize(values)[0]
    dx = 1e-4 * np.random.default_rng(0).standard_normal(len(keys) * D)
    vv = gtsam.VectorValues()
    for a, key in enumerate(keys):
        vv.insert(key, dx[D * a:D * a + D])
    moved = values.retract(vv)
    predicted = block.structure + block.back_substitute(vv)
    block.refine_structure(moved, steps=30)
    # first-order accurate: the error is quadratic in the (small) step
    np.testing.assert_allclose(predicted.numpy(), block.structure.numpy(), rtol=1e-5)


def test_block_zero_weights_and_invalid_rows_are_counted_not_nan():
    block, values = small_block(2)
    block.uv_source[:3] = torch.nan  # degenerate measurements
    keys, H, g, c = block.linearize(values)[0]
    assert np.isfinite(H).all() and np.isfinite(g).all() and np.isfinite(c)
    assert block.num_invalid == 3
    assert np.isfinite(block.cost(values))


def test_block_evaluation_matches_one_reprojection_per_edge():
    """The block evaluates all its edges in one call (each row pointed at its edge's pose pair): the bytes
    of one call per edge with that edge's pose pair."""
    from fgslam.factors.reprojection import reproject_inv_depth

    block, values = small_block(3, patch=True)
    poses = Sim3.from_gtsam([values.atSimilarity3(k) for k in block.keys])
    out = block.evaluate(poses, block.structure, jacobians=True)
    d_rows = block.structure[block.struct_idx]
    bounds = block.groups.bounds
    assert len(block.groups.slots) == 2
    for e, (si, sj) in enumerate(block.groups.slots):
        rows = slice(bounds[e], bounds[e + 1])
        ref = reproject_inv_depth(block.uv_source[rows], d_rows[rows], poses[si], poses[sj], block.K,
                                  block.uv_target[rows], config=block.reprojection)
        for got, want in ((out.r, ref.residual), (out.E, ref.J_d), (out.J[0], ref.J_Ti), (out.J[1], ref.J_Tj)):
            assert got[rows].numpy().tobytes() == want.numpy().tobytes()


def test_set_observations_takes_input_order():
    block, values = small_block(4)
    original = block.cost(values)
    inverse = torch.empty_like(block._order)
    inverse[block._order] = torch.arange(len(block._order))
    uv_input_order = block.uv_target[inverse].clone()
    w_input_order = block.weights[inverse].clone()
    block.set_observations(uv_input_order, w_input_order)  # same data, given in input order: no change
    assert block.cost(values) == pytest.approx(original, rel=1e-14)
    block.set_observations(weights=torch.zeros(len(uv_input_order)))
    assert block.cost(values) == 0.0
