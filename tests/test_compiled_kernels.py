"""The compiled kernels (fgslam/core/jit.py): the depth-alignment surface, association and residual
rows, the Lucas-Kanade track checks, and the pointmap family's patch descriptors and ray residual
rows. Their rules on constructed cases, the same bytes call to call, and the options that keep them
deterministic. (The point-to-plane Jacobians are checked against finite differences in
tests/test_depth_align.py, through the same kernel.)"""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.core.jit import KERNEL_OPTIONS
from fgslam.factors.depth_align_jit import associate_rows, point_to_plane_rows
from fgslam.frontends.patch.lk_jit import ERROR_CAP, finish_tracks


def test_kernel_options_are_the_deterministic_ones():
    assert KERNEL_OPTIONS["fastmath"] is False   # no reassociated or contracted (FMA) arithmetic
    assert "parallel" not in KERNEL_OPTIONS      # no reductions split over threads
    assert KERNEL_OPTIONS["cache"] is True       # compiled once per install, loaded afterwards


# ------------------------------------------------------------------ depth alignment

def _plane_reference(h=20, w=30, z=2.0, f=25.0):
    """A fronto-parallel wall at depth ``z`` seen by a ``w`` x ``h`` grid camera: vertices, normals
    (towards the camera), validity and intrinsics."""
    K = np.array([f, f, (w - 1) / 2, (h - 1) / 2])
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    V = np.stack(((u - K[2]) / K[0] * z, (v - K[3]) / K[1] * z, np.full_like(u, z)), -1).reshape(-1, 3)
    N = np.tile([0.0, 0.0, -1.0], (h * w, 1))
    return V, N, np.ones(h * w, dtype=bool), K, np.array([h, w], dtype=np.int64)


def _associate(A, b, X_f, n_f, ref, min_depth=0.1, max_distance=0.1, min_agree=0.8, jacobians=True):
    V, N, valid, K, shape = ref
    return associate_rows(A, b, X_f, n_f, V, N, valid, K, shape, min_depth, max_distance, min_agree, jacobians)


def _surface_reference(depth, off, stride, K, min_depth, max_depth, max_discontinuity):
    """One surface level by its definition, in numpy arrays (vertices, central-difference normals towards
    the camera, the depth and discontinuity gates), summed in numpy's order."""
    z = depth[off::stride, off::stride].astype(np.float64)
    h, w = z.shape
    ok = np.isfinite(z) & (z >= min_depth) & (z <= max_depth)
    z = np.where(ok, z, 0.0)
    V = np.stack(np.broadcast_arrays(((np.arange(w) - K[2]) / K[0])[None, :] * z,
                                     ((np.arange(h) - K[3]) / K[1])[:, None] * z, z), axis=-1)
    N, good = np.zeros_like(V), np.zeros_like(ok)
    c = z[1:-1, 1:-1]
    g = ok[1:-1, 1:-1] & ok[1:-1, 2:] & ok[1:-1, :-2] & ok[2:, 1:-1] & ok[:-2, 1:-1]
    for zn in (z[1:-1, 2:], z[1:-1, :-2], z[2:, 1:-1], z[:-2, 1:-1]):
        g &= np.abs(zn - c) <= max_discontinuity * c
    n = np.cross(V[1:-1, 2:] - V[1:-1, :-2], V[2:, 1:-1] - V[:-2, 1:-1])
    norm = np.linalg.norm(n, axis=-1)
    g &= norm > 0
    n = n / np.where(norm > 0, norm, 1.0)[..., None]
    n = np.where(((n * V[1:-1, 1:-1]).sum(-1) > 0)[..., None], -n, n)
    N[1:-1, 1:-1] = np.where(g[..., None], n, 0.0)
    good[1:-1, 1:-1] = g
    return V, N, good


def test_surface_rows_are_the_definition_bytewise():
    from fgslam.factors.depth_align_jit import surface_rows

    rng = np.random.default_rng(8)
    v, u = np.mgrid[0:90, 0:130]
    depth = (1.5 + 0.004 * u + 0.002 * v + 0.01 * rng.standard_normal((90, 130))).astype(np.float32)
    depth[30:50, 60:90] += 0.8            # a box: depth discontinuities
    depth[rng.random((90, 130)) < 0.05] = 0.0  # missing readings
    depth[5, 7] = np.nan
    for off, stride in ((0, 1), (1, 2), (4, 8)):
        K = np.array([100.0 / stride, 100.0 / stride, (64.5 - off) / stride, (44.5 - off) / stride])
        got = surface_rows(depth, off, stride, K, 0.3, 8.0, 0.05 * stride)
        ref = _surface_reference(depth, off, stride, K, 0.3, 8.0, 0.05 * stride)
        assert all(a.tobytes() == b.tobytes() for a, b in zip(got, ref)), stride
        assert got[2].any() and not got[2].all()


def test_surface_rows_of_a_wall_with_a_step_and_a_hole():
    """Vertices at the grid pixels' depth, unit normals towards the camera on a wall, none at the step
    (a neighbour's depth differs by more than the limit), around a missing reading or on the border."""
    from fgslam.factors.depth_align_jit import surface_rows

    depth = np.full((40, 60), 2.0, np.float32)
    depth[:, 40:] = 3.0         # a step between grid columns 9 and 10 (stride 4, offset 2)
    depth[22, 22] = np.nan      # grid pixel (5, 5): no reading
    K = np.array([25.0, 25.0, 7.5, 4.5])
    V, N, good = surface_rows(depth, 2, 4, K, 0.1, 10.0, 0.05)
    assert V.shape == (10, 15, 3) and good.shape == (10, 15)
    assert V[3, 4].tolist() == [(4 - 7.5) / 25.0 * 2.0, (3 - 4.5) / 25.0 * 2.0, 2.0]
    assert not V[5, 5].any()
    assert good[2, 2] and N[2, 2].tolist() == [0.0, 0.0, -1.0]
    assert not good[:, 9].any() and not good[:, 10].any() and good[2:8, 12].all()
    assert not good[5, 4:7].any() and not good[4:7, 5].any() and good[5, 3]
    assert not good[0].any() and not good[:, 0].any() and not good[-1].any() and not good[:, -1].any()
    assert not N[~good].any()
    np.testing.assert_allclose(np.linalg.norm(N[good], axis=-1), 1.0, atol=1e-12)
    again = surface_rows(depth, 2, 4, K, 0.1, 10.0, 0.05)
    assert all(a.tobytes() == b.tobytes() for a, b in zip(again, (V, N, good)))


def test_association_rules_on_a_wall():
    ref = _plane_reference()
    A, b = np.eye(3), np.zeros(3)
    X_f = np.array([
        [0.0, 0.0, 2.03],    # on the wall's ray, 3 cm behind it: paired, residual n . (Y - X_k) = -0.03
        [0.0, 0.0, 2.5],     # 0.5 m behind: seen, beyond max_distance
        [0.0, 0.0, -1.0],    # behind the camera: not seen
        [5.0, 0.0, 2.0],     # projects outside the grid: not seen
        [0.1, 0.1, 2.0],     # on the wall but its normal faces away: seen, not paired
    ])
    n_f = np.tile([0.0, 0.0, -1.0], (5, 1))
    n_f[4] = [0.0, 0.0, 1.0]
    seen, paired, r, J = _associate(A, b, X_f, n_f, ref)
    assert seen.tolist() == [True, True, False, False, True]
    assert paired.tolist() == [True, False, False, False, False]
    assert r[0] == pytest.approx(-0.03, abs=1e-12)
    assert np.all(r[1:] == 0) and np.all(J[1:] == 0)  # rows not paired stay zero


def test_association_follows_the_relative_pose():
    ref = _plane_reference()
    X_f = np.array([[0.0, 0.0, 1.9]])
    n_f = np.array([[0.0, 0.0, -1.0]])
    # the frame camera 0.1 m in front of the reference along z: its point lands on the wall
    seen, paired, r, _ = _associate(np.eye(3), np.array([0.0, 0.0, 0.1]), X_f, n_f, ref)
    assert paired[0] and r[0] == pytest.approx(0.0, abs=1e-12)
    # an invalid reference pixel there: not seen
    V, N, valid, K, shape = ref
    valid = valid.copy()
    valid[int(round(K[3])) * shape[1] + int(round(K[2]))] = False
    seen, paired, _, _ = associate_rows(np.eye(3), np.array([0.0, 0.0, 0.1]), X_f, n_f, V, N, valid, K, shape,
                                        0.1, 0.1, 0.8, True)
    assert not seen[0] and not paired[0]


def test_association_rows_equal_the_point_to_plane_rows_and_repeat_bytewise():
    rng = np.random.default_rng(3)
    ref = _plane_reference(h=40, w=60)
    V, N = ref[0], ref[1]
    X_f = V[rng.choice(len(V), 300, replace=False)] + rng.normal(0, 0.01, (300, 3))
    n_f = np.tile([0.0, 0.0, -1.0], (300, 1))
    c, s = np.cos(0.01), np.sin(0.01)
    A = 1.02 * np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    b = np.array([0.01, -0.02, 0.005])
    first = _associate(A, b, X_f, n_f, ref, max_distance=0.2)
    second = _associate(A, b, X_f, n_f, ref, max_distance=0.2)
    for x, y in zip(first, second):
        assert x.tobytes() == y.tobytes()
    seen, paired, r, J = first
    assert paired.sum() > 200
    # the paired rows are the point-to-plane rows of the matched reference vertices
    Y = X_f @ A.T + b
    u = np.rint(ref[3][0] * Y[:, 0] / Y[:, 2] + ref[3][2]).astype(int)
    v = np.rint(ref[3][1] * Y[:, 1] / Y[:, 2] + ref[3][3]).astype(int)
    idx = v * ref[4][1] + u
    r2, J2 = point_to_plane_rows(A, X_f[paired], Y[paired], V[idx[paired]], N[idx[paired]], True)
    np.testing.assert_allclose(r[paired], r2, rtol=0, atol=1e-15)
    np.testing.assert_allclose(J[paired], J2, rtol=0, atol=1e-15)


# ------------------------------------------------------------------ Lucas-Kanade track checks

def _finish(uv_fwd, err, uv_back, p_src, uv_pred, ok_fwd=None, ok_back=None, scale=1.0, half=5.0, size=(100, 80),
            fb_threshold=1.0, error_sigma=12.0, fb_sigma=0.5, min_confidence=0.05):
    n = len(uv_fwd)
    ok_fwd = np.ones(n, bool) if ok_fwd is None else np.asarray(ok_fwd)
    ok_back = np.ones(n, bool) if ok_back is None else np.asarray(ok_back)
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731 - OpenCV's dtypes
    return finish_tracks(f32(uv_fwd), ok_fwd, f32(err), f32(p_src), f32(uv_back), ok_back,
                         np.asarray(uv_pred, np.float64), scale, half, float(size[0]), float(size[1]),
                         fb_threshold, error_sigma, fb_sigma, min_confidence)


def test_track_checks():
    p_src = [[50, 40]] * 6
    uv_fwd = [[52, 41], [52, 41], [2, 41], [52, 41], [52, 41], [52, 41]]
    uv_back = [[50.375, 40.5], [51.5, 40], [50, 40], [50, 40], [50, 40], [50, 40]]
    err = [6.0, 0.0, 0.0, np.nan, 1e9, 0.0]
    ok_back = [True, True, True, True, True, False]
    uv_pred = np.full((6, 2), -7.0)
    uv, conf, fb = _finish(uv_fwd, err, uv_back, p_src, uv_pred, ok_back=ok_back)
    # a clean track: confidence from its photometric (6 grey levels) and forward-backward (0.625 px) errors
    assert conf[0] == pytest.approx(1 / (1 + (6 / 12) ** 2) / (1 + (0.625 / 0.5) ** 2), rel=1e-12)
    assert fb[0] == 0.625 and uv[0].tolist() == [52.0, 41.0]
    assert conf[1] == 0 and uv[1].tolist() == [-7.0, -7.0]       # forward-backward 1.5 px > 1 px
    assert conf[2] == 0 and uv[2].tolist() == [-7.0, -7.0]       # within 5 px of the border
    assert conf[3] == 0 and uv[3].tolist() == [-7.0, -7.0]       # a NaN error is no track
    assert conf[4] == 0 and uv[4].tolist() == [52.0, 41.0]       # a huge error: below min_confidence (kept in place)
    assert conf[5] == 0                                          # the backward track failed
    assert np.all(np.isfinite(fb)) and fb.max() <= ERROR_CAP


def test_track_checks_at_the_lk_resolution():
    # LK at half resolution: pixel centres at integers in both, errors reported in input pixels
    uv, conf, fb = _finish([[25.5, 20.5]], [0.0], [[25.25, 20.0]], [[25.0, 20.0]], [[0.0, 0.0]], scale=0.5,
                           half=5.0, fb_sigma=0.5)
    assert uv[0].tolist() == [51.5, 41.5]
    assert fb[0] == pytest.approx(0.5)
    assert conf[0] == pytest.approx(0.5)


# ------------------------------------------------------------------ pointmap descriptors and ray residual

def _patch_reference(smooth, offsets, texture_sq):
    """The patch descriptor by its definition, channel-first in numpy (float32, running sums from the
    first sample, as the kernel promises)."""
    H, W = smooth.shape
    v, u = np.mgrid[0:H, 0:W]
    samples = [smooth[np.clip(v + dy, 0, H - 1), np.clip(u + dx, 0, W - 1)] for dy in offsets for dx in offsets]
    D = np.stack(samples).astype(np.float32)
    D -= D.sum(0) / np.float32(16)
    sq = (D * D).sum(0)
    norm = np.sqrt(sq)
    D *= np.where(norm > np.float32(1e-6), np.float32(1) / np.maximum(norm, np.float32(1e-6)), np.float32(0))
    G = sq / np.float32(16)
    return np.ascontiguousarray(D.transpose(1, 2, 0)), G / (G + texture_sq)


def test_patch_descriptor_rows_are_the_definition_bytewise():
    from fgslam.frontends.pointmap.descriptors_jit import patch_rows

    rng = np.random.default_rng(3)
    smooth = (rng.uniform(0, 255, (23, 31)).astype(np.float32))
    smooth[:, :8] = 40.0  # a flat strip: zero descriptors, zero confidence
    offsets = np.array([-3, -1, 1, 3], np.int64)
    D, Q = patch_rows(smooth, offsets, np.float32(1e-6), np.float32(16.0))
    D_ref, Q_ref = _patch_reference(smooth, offsets, np.float32(16.0))
    assert D.dtype == np.float32 and D.shape == (23, 31, 16) and D.flags["C_CONTIGUOUS"]
    assert D.tobytes() == D_ref.tobytes() and Q.tobytes() == Q_ref.astype(np.float32).tobytes()
    assert not D[:, :4].any() and not Q[:, :4].any()
    norms = np.linalg.norm(D[:, 12:].astype(np.float64), axis=-1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-6)
    again = patch_rows(smooth, offsets, np.float32(1e-6), np.float32(16.0))
    assert again[0].tobytes() == D.tobytes() and again[1].tobytes() == Q.tobytes()


def test_ray_rows_broadcast_the_pose_batch_and_repeat_bytewise():
    """One pose per edge against its own matches, or one pose shared by a batch: the same rows as one call
    per pose, and the same bytes call to call."""
    import torch

    from fgslam.core.errors import DataError
    from fgslam.core.lie import Sim3
    from fgslam.factors.pointmap import prepare_matches, ray_dist_prepared

    g = torch.Generator().manual_seed(5)
    X_k = torch.rand(3, 40, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    X_f = X_k + 0.05 * torch.randn(3, 40, 3, generator=g, dtype=torch.float64)
    X_f[1, 7] = 0.0  # a zero-norm point: masked
    T = Sim3.exp(0.05 * torch.randn(3, 7, generator=g, dtype=torch.float64))
    prep = prepare_matches(X_f, X_k)
    batched = ray_dist_prepared(T, prep)
    for b in range(3):
        one = ray_dist_prepared(T[b], prepare_matches(X_f[b], X_k[b]))
        for name in ("r", "J", "sqrt_info", "valid"):
            assert torch.equal(getattr(batched, name)[b], getattr(one, name)), name
    assert not bool(batched.valid[1, 7]) and int(batched.valid.sum()) == 119
    shared = ray_dist_prepared(T[0], prep)  # one pose over the (3, 40) matches
    assert shared.r.shape == (3, 40, 4) and torch.equal(shared.r[0], batched.r[0])
    again = ray_dist_prepared(T, prep)
    assert all(torch.equal(getattr(again, n), getattr(batched, n)) for n in ("r", "J", "sqrt_info", "valid"))
    # rotations batched, one scale for all (Sim3 broadcasts its parts), against one set of matches
    mixed = Sim3(T.R, T.t, torch.tensor(1.0, dtype=torch.float64))
    one_set = prepare_matches(X_f[0], X_k[0])
    out = ray_dist_prepared(mixed, one_set)
    assert out.r.shape == (3, 40, 4)
    assert torch.equal(out.r[2], ray_dist_prepared(Sim3(T.R[2], T.t[2], torch.tensor(1.0, dtype=torch.float64)), one_set).r)
    # no matches: empty results of the right shapes
    empty = ray_dist_prepared(T, prepare_matches(X_f[:, :0], X_k[:, :0]))
    assert empty.r.shape == (3, 0, 4) and empty.J.shape == (3, 0, 4, 7) and empty.valid.shape == (3, 0)
    # the kernel takes CPU tensors without gradients
    with pytest.raises(DataError, match="CPU tensors without gradients"):
        ray_dist_prepared(Sim3(T.R, T.t.clone().requires_grad_(True), T.s), prep)


# ------------------------------------------------------------------ loaded before the first frame

_BUILD_AND_REPORT = """
import sys
import fgslam
camera = fgslam.Camera(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width=320, height=240)
slam = fgslam.Slam.from_preset(sys.argv[1], camera, overrides=sys.argv[2:])
print("numba" in sys.modules, slam.system.frontend.uses_compiled_kernels)
slam.abort()
"""


@pytest.mark.parametrize("preset, overrides", [
    ("patch_mono", []),                                     # reprojection, Lucas-Kanade track checks
    ("pointmap_rgbd", []),                                  # projective matching
    ("dense_rgbd", []),                                     # reprojection
])
def test_a_run_loads_the_kernels_before_its_first_frame(preset, overrides):
    """numba's import and machine-code target (about 2 s the first time a process calls a kernel) are
    paid when the run is built, not by a frame: every family calls kernels on its frames (the
    reprojection residual in the patch and dense families, projective matching in the pointmap family)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _BUILD_AND_REPORT, preset, *overrides], capture_output=True,
                         text=True, check=True).stdout.split()
    assert out == ["True", "True"]
