"""Patch BA block: vectorised Schur reduction vs the generic one, fixed frames, stereo/prior rows,
and local bundle adjustment through the backend's window optimisation converging to ground truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fgslam.factors.schur import schur_reduce
from fgslam.factors.visual_block import InverseDepthBlock
from fgslam.frontends.patch.ba import PatchBlock
from fgslam.core.lie import Sim3
from fgslam.backend import Backend, BackendConfig, GaugeConfig, pose_key

K = torch.tensor([200.0, 200.0, 160.0, 120.0], dtype=torch.float64)


def _scene(rng, n_frames=5, n_patches=40):
    """Frames on a short arc looking at points 3-6 m ahead; returns poses (Sim3 (F,)), patch
    source frames, pixels, true inverse depths."""
    R = []
    t = []
    for f in range(n_frames):
        w = torch.tensor([0.0, 0.03 * f, 0.01 * f], dtype=torch.float64)
        from fgslam.core.so3 import so3_exp

        R.append(so3_exp(w))
        t.append(torch.tensor([0.15 * f, 0.02 * f, 0.05 * f], dtype=torch.float64))
    poses = Sim3(torch.stack(R), torch.stack(t), torch.ones(n_frames, dtype=torch.float64))
    src = rng.integers(0, n_frames, n_patches)
    uv = np.stack([rng.uniform(40, 280, n_patches), rng.uniform(30, 210, n_patches)], 1)
    inv_depth = 1.0 / rng.uniform(3.0, 6.0, n_patches)
    return poses, src, uv, inv_depth


def _edges(poses, src, uv, inv_depth, n_frames, noise, rng, right=False, T_CRCL=None):
    from fgslam.factors.reprojection import reproject

    e_src, e_tgt, e_patch, e_uv = [], [], [], []
    for p in range(len(src)):
        for f in range(n_frames):
            if f == src[p] and not right:
                continue
            u, ok = reproject(torch.as_tensor(uv[p]), torch.tensor(inv_depth[p]), poses[int(src[p])], poses[f], K,
                              T_CtCj=T_CRCL if right else None)
            if bool(ok):
                e_src.append(int(src[p]))
                e_tgt.append(f)
                e_patch.append(p)
                e_uv.append(u.numpy() + noise * rng.standard_normal(2))
    return np.array(e_src), np.array(e_tgt), np.array(e_patch), np.array(e_uv)


def _values(poses):
    import gtsam

    values = gtsam.Values()
    for i in range(poses.shape[0]):
        values.insert(pose_key(i), poses[i].to_gtsam())
    return values


def test_linearize_matches_generic_schur():
    rng = np.random.default_rng(0)
    poses, src, uv, d = _scene(rng)
    e_src, e_tgt, e_patch, e_uv = _edges(poses, src, uv, d, 5, 0.5, rng)
    d0 = d * rng.uniform(0.8, 1.2, len(d))
    w = rng.uniform(0.2, 1.0, len(e_src))
    keys = [pose_key(i) for i in range(5)]
    empty = torch.zeros(0, 3, 3, dtype=torch.float64)
    block = PatchBlock(keys, empty, torch.zeros(0, 3), torch.zeros(0), e_src, e_tgt, np.zeros(len(e_src), bool),
                       uv[e_patch], e_uv, w, e_patch, K, d0)
    ref = InverseDepthBlock(keys, torch.as_tensor(e_src), torch.as_tensor(e_tgt), torch.as_tensor(uv[e_patch]),
                            torch.as_tensor(e_uv), torch.as_tensor(e_patch), torch.as_tensor(w), K, torch.as_tensor(d0))
    values = _values(poses)
    _, H, g, c = block.linearize(values)[0]
    _, H_ref, g_ref, c_ref = ref.linearize(values)[0]
    np.testing.assert_allclose(H, H_ref, rtol=1e-9, atol=1e-6 * np.abs(H_ref).max())
    np.testing.assert_allclose(g, g_ref, rtol=1e-9, atol=1e-6 * np.abs(g_ref).max())
    assert c == pytest.approx(c_ref, rel=1e-9)
    assert block.cost(values) == pytest.approx(ref.cost(values), rel=1e-12)


def test_fixed_frames_equal_dropped_columns():
    """Fixed frames: the reduced system equals the all-variable one restricted to the variable
    slots when the fixed slots' columns are removed before elimination."""
    rng = np.random.default_rng(1)
    poses, src, uv, d = _scene(rng, n_frames=5, n_patches=30)
    e_src, e_tgt, e_patch, e_uv = _edges(poses, src, uv, d, 5, 0.3, rng)
    w = rng.uniform(0.2, 1.0, len(e_src))
    # frames 0, 1 fixed: local order [2, 3, 4, 0, 1]
    local = {2: 0, 3: 1, 4: 2, 0: 3, 1: 4}
    ls = np.array([local[int(f)] for f in e_src])
    lt = np.array([local[int(f)] for f in e_tgt])
    keys = [pose_key(i) for i in (2, 3, 4)]
    fixed = poses[torch.tensor([0, 1])]
    block = PatchBlock(keys, fixed.R, fixed.t, fixed.s, ls, lt, np.zeros(len(ls), bool), uv[e_patch], e_uv, w,
                       e_patch, K, d)
    values = _values(poses)
    _, H, g, c = block.linearize(values)[0]
    # reference: generic schur_reduce with 5 slots, then drop fixed columns before elimination
    from fgslam.factors.reprojection import reproject_inv_depth

    res = reproject_inv_depth(torch.as_tensor(uv[e_patch]), torch.as_tensor(d[e_patch]), poses[torch.as_tensor(e_src)],
                              poses[torch.as_tensor(e_tgt)], K, torch.as_tensor(e_uv))
    J = torch.stack([res.J_Ti, res.J_Tj], 2)
    var = torch.tensor([s < 3 for s in ls])[:, None, None], torch.tensor([t < 3 for t in lt])[:, None, None]
    J[:, :, 0] *= var[0].to(J.dtype)
    J[:, :, 1] *= var[1].to(J.dtype)
    slots = torch.stack([torch.as_tensor(np.minimum(ls, 3)), torch.as_tensor(np.minimum(lt, 3))], 1)
    sys_ = schur_reduce(res.residual, J, slots, res.J_d, torch.as_tensor(e_patch), torch.as_tensor(w)[:, None].expand(-1, 2),
                        4, len(d), min_information=1e-12)
    np.testing.assert_allclose(H, sys_.H[:21, :21].numpy(), rtol=1e-9, atol=1e-7 * np.abs(H).max())
    np.testing.assert_allclose(g, sys_.g[:21].numpy(), rtol=1e-9, atol=1e-7 * np.abs(g).max())
    assert c == pytest.approx(sys_.c, rel=1e-9)


@pytest.mark.parametrize("mode", ["mono", "stereo", "rgbd"])
def test_local_ba_converges_to_ground_truth(mode):
    rng = np.random.default_rng(2)
    n_frames = 6
    poses, src, uv, d = _scene(rng, n_frames=n_frames, n_patches=60)
    e_src, e_tgt, e_patch, e_uv = _edges(poses, src, uv, d, n_frames, 0.0, rng)
    right = np.zeros(len(e_src), bool)
    T_CRCL = None
    extra = {}
    if mode == "stereo":
        T_CLCR = np.eye(4)
        T_CLCR[0, 3] = 0.1
        T_CRCL = np.linalg.inv(T_CLCR)
        r_src, r_tgt, r_patch, r_uv = _edges(poses, src, uv, d, n_frames, 0.0, rng, right=True,
                                             T_CRCL=torch.as_tensor(T_CRCL))
        keep = r_src == r_tgt
        e_src, e_tgt, e_patch = (np.concatenate([a, b[keep]]) for a, b in ((e_src, r_src), (e_tgt, r_tgt), (e_patch, r_patch)))
        e_uv = np.concatenate([e_uv, r_uv[keep]])
        right = np.concatenate([right, np.ones(int(keep.sum()), bool)])
        extra = dict(K_right=K, T_CRCL=T_CRCL)
    if mode == "rgbd":
        extra = dict(prior_idx=np.arange(len(d)), prior_value=d, prior_weight=np.full(len(d), 1e4))
    # frames 0 and 1 fixed at the truth; the others perturbed, depths perturbed
    var = list(range(2, n_frames))
    local = {f: i for i, f in enumerate(var + [0, 1])}
    ls = np.array([local[int(f)] for f in e_src])
    lt = np.array([local[int(f)] for f in e_tgt])
    fixed = poses[torch.tensor([0, 1])]
    d0 = d * rng.uniform(0.7, 1.3, len(d))
    block = PatchBlock([pose_key(f) for f in var], fixed.R, fixed.t, fixed.s, ls, lt, right, uv[e_patch], e_uv,
                       np.ones(len(ls)), e_patch, K, d0, **extra)
    gauge = GaugeConfig(fix_anchor=False, hold_scale=True, world_scale_range=False)
    backend = Backend(BackendConfig(gauge=gauge))
    for f in var:
        xi = torch.as_tensor(np.concatenate([rng.normal(0, 0.01, 3), rng.normal(0, 0.03, 3), [0.0]]))
        backend.add_keyframe(f, poses[f].retract(xi).to_gtsam(), 0.1 * f)
    backend.set_blocks("patch", [block])
    report = backend.optimize_window(var, 30)
    assert report.final_cost < 1e-8 * max(report.initial_cost, 1.0)
    est = backend.poses(var)
    err_t = (est.t - poses[torch.tensor(var)].t).norm(dim=-1).max().item()
    assert err_t < 1e-6
    np.testing.assert_allclose(block.structure.numpy(), d, rtol=1e-6)
