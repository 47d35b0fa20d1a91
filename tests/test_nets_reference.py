"""fgslam's DROID-SLAM and DPVO networks against the official modules' outputs (``../shared/reference``,
its README): seeded weights built by the README's recipe and loaded through fgslam's strict loader,
the encoders and update operators compared to float32 precision; and the correlation lookups against
a brute-force lookup written here from the official CUDA kernels' semantics:

- DROID (``droid_slam/modules/corr.py`` + ``corr_index_forward_kernel``): volume ``<f_i/4, f_j/4>``,
  level ``l`` = ``2^l x 2^l`` average pooling of the target dimensions (floor of odd sizes), the
  point ``coords / 2^l``; output ``[dx][dy]`` (x offset major) is the bilinear value at
  ``(x - r + dx, y - r + dy)`` from the four integer neighbours, zero outside the map; channel
  ``level * 49 + dx * 7 + dy``.
- DPVO (``dpvo/altcorr/correlation_kernel.cu``): for patch pixel ``(row, col)`` of an edge, the
  gmap feature at that pixel dotted with the target map at the integer samples around the pixel's
  own coordinate, bilinear as above; levels: the map and its ``4 x 4`` average pooling with
  coordinates / 4; output ``[dx][dy][row][col][level]``.
"""

from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np
import pytest
import torch

from fgslam.nets.checkpoint import load_dpvo, load_droid
from fgslam.nets.droid import CORR_LEVELS, AltCorr, CorrVolume
from fgslam.nets.dpvo import patch_correlation, pyramid
from nets_support import dpvo_table, droid_table
from nets_support import one_thread  # noqa: F401 (autouse fixture)

# float32 tolerance from the reduction length (Higham's probabilistic rounding-error bound): an output
# that passes through dot products of lengths n_1 .. n_L, summed in any order (another CPU's kernels,
# another blocking), differs from the exact value by about u * sqrt(n_1 + ... + n_L) relative to its
# scale, with unit roundoff u = 2^-24; the bound holds with probability >= 1 - 2 exp(-LAMBDA^2 / 2) per
# element, so LAMBDA = 6 leaves ~3e-3 chance over the ~1e5 elements compared. Measured here (AVX2 and
# ATEN_CPU_CAPABILITY=default): at most 0.8 of u * sqrt(n) (DROID update, out_net), so the margin to
# the bound is >= 7x; a real error (a wrong channel, padding, bias or order) is >= 1e-3 of the scale.
FLOAT32_UNIT_ROUNDOFF = 2.0 ** -24
LAMBDA = 6.0
DPVO_POOLS = (1, 4)  # the official lookup's levels: the map and its 4 x 4 average pooling


def reduction_length(module: torch.nn.Module) -> int:
    """Summed fan-in of every convolution and linear layer of ``module``: an upper bound of the dot-product
    lengths along any path from its input to an output (branches counted once each)."""
    n = 0
    for m in module.modules():
        if isinstance(m, torch.nn.Conv2d):
            n += m.in_channels // m.groups * m.kernel_size[0] * m.kernel_size[1]
        elif isinstance(m, torch.nn.Linear):
            n += m.in_features
    return n


def lookup_reduction(channels: int, largest_pool: int) -> int:
    """Reduction length of a correlation lookup: the feature dot product, the average pooling of the
    coarsest level (``largest_pool`` x ``largest_pool`` values) and the four bilinear neighbours."""
    return channels + largest_pool ** 2 + 4


def float32_tolerance(reduction: int) -> float:
    """Relative tolerance (to the output's largest magnitude) of a float32 result over ``reduction``."""
    return LAMBDA * math.sqrt(reduction) * FLOAT32_UNIT_ROUNDOFF


def seeded_state(keys, table, seed: int) -> "OrderedDict[str, torch.Tensor]":
    """The reference README's recipe: keys in the file's order, one generator, one ``randn`` per
    floating-point tensor; a normalisation layer's 1-D weight ``1 + 0.05 r``, the rest ``0.05 r``.
    Shapes come from the official parameter table (tests/nets_support.py), not from fgslam."""
    shapes = dict(table)
    assert sorted(shapes) == sorted(str(k) for k in keys), "the reference keys are the official parameter names"
    g = torch.Generator().manual_seed(int(seed))
    out = OrderedDict()
    for key in (str(k) for k in keys):
        r = torch.randn(shapes[key], generator=g, dtype=torch.float32)
        norm_weight = "norm" in key and key.endswith("weight") and r.dim() == 1
        out[key] = 1.0 + 0.05 * r if norm_weight else 0.05 * r
    return out


def _reference(folder, tmp_path_factory, name: str, table, load):
    """The official outputs ``<name>_official.npz`` and the network with their seeded weights, loaded
    through fgslam's strict loader from a checkpoint file."""
    ref = dict(np.load(folder / f"{name}_official.npz"))
    path = tmp_path_factory.mktemp("ref") / f"{name}.pth"
    torch.save(seeded_state(ref["keys"], table, ref["seed"]), path)
    return ref, load(path)


@pytest.fixture(scope="module")
def droid_ref(shared_reference, tmp_path_factory):
    return _reference(shared_reference, tmp_path_factory, "droid", droid_table(), load_droid)


@pytest.fixture(scope="module")
def dpvo_ref(shared_reference, tmp_path_factory):
    return _reference(shared_reference, tmp_path_factory, "dpvo", dpvo_table(), load_dpvo)


def close(actual: torch.Tensor, expected: np.ndarray, name: str, reduction: int) -> None:
    """``actual`` equals ``expected`` to the float32 tolerance of a computation over ``reduction``."""
    exp = torch.from_numpy(np.asarray(expected))
    assert tuple(actual.shape) == tuple(exp.shape), f"{name}: shape {tuple(actual.shape)} vs {tuple(exp.shape)}"
    tol = float32_tolerance(reduction)
    torch.testing.assert_close(actual.float(), exp.float(), rtol=tol, atol=tol * float(exp.abs().max()),
                               msg=lambda m: f"{name}: {m}")


def test_droid_encoders_match_the_official_extract_features(droid_ref):
    ref, net = droid_ref
    rgb = torch.from_numpy(ref["images_bgr"][:, ::-1].copy())  # extract_features flips BGR -> RGB
    with torch.inference_mode():
        fmap, hidden, inp = net.extract(rgb)
    close(fmap, ref["fmap"], "fmap", reduction_length(net.fnet))
    close(hidden, ref["net"], "net", reduction_length(net.cnet))
    close(inp, ref["inp"], "inp", reduction_length(net.cnet))
    with torch.inference_mode():  # the channel order matters: BGR fed as if RGB is another input
        fmap_bgr = net.extract(torch.from_numpy(ref["images_bgr"]))[0]
    differs = (fmap_bgr - torch.from_numpy(ref["fmap"])).abs().max() / float(np.abs(ref["fmap"]).max())
    assert differs > 100 * float32_tolerance(reduction_length(net.fnet)), differs


def test_droid_update_operator_matches_the_official_outputs(droid_ref):
    ref, net = droid_ref
    t = {k: torch.from_numpy(ref[k]) for k in ("upd_net", "upd_inp", "upd_corr", "upd_flow", "ii")}
    with torch.inference_mode():
        out_net, delta, weight, (eta, upmask, frames) = net.update(t["upd_net"], t["upd_inp"], t["upd_corr"],
                                                                   t["upd_flow"], t["ii"])
    assert frames.tolist() == sorted(set(ref["ii"].tolist()))
    close(out_net, ref["out_net"], "out_net", reduction_length(net.update))
    close(delta, ref["out_delta"], "out_delta", reduction_length(net.update))
    close(weight, ref["out_weight"], "out_weight", reduction_length(net.update))
    close(eta, ref["out_eta"], "out_eta", reduction_length(net.update))
    close(upmask, ref["out_upmask"], "out_upmask", reduction_length(net.update))


def test_dpvo_encoders_match_the_official_patchify_maps(dpvo_ref):
    ref, net = dpvo_ref
    with torch.inference_mode():  # DPVO feeds BGR as cv2 reads it, no flip
        fmap, imap = net.extract(torch.from_numpy(ref["images_bgr"]))
    close(fmap, ref["fmap"], "fmap", reduction_length(net.patchify.fnet))
    close(imap, ref["imap"], "imap", reduction_length(net.patchify.inet))


def test_dpvo_update_operator_matches_the_official_outputs(dpvo_ref):
    ref, net = dpvo_ref
    t = {k: torch.from_numpy(ref[k]) for k in ("upd_net", "upd_inp", "upd_corr", "ii", "jj", "kk")}
    with torch.inference_mode():
        out_net, delta, weight = net.update(t["upd_net"], t["upd_inp"], t["upd_corr"], t["ii"], t["jj"], t["kk"])
    close(out_net, ref["out_net"], "out_net", reduction_length(net.update))
    close(delta, ref["out_delta"], "out_delta", reduction_length(net.update))
    close(weight, ref["out_weight"], "out_weight", reduction_length(net.update))


# ---------------------------------------------------------------- brute-force correlation lookups
def _bilinear_at(score, x: float, y: float) -> float:
    """``score(yi, xi)`` (zero outside) bilinear at ``(x, y)`` from its four integer neighbours."""
    x0, y0 = math.floor(x), math.floor(y)
    ax, ay = x - x0, y - y0
    return ((1 - ax) * (1 - ay) * score(y0, x0) + ax * (1 - ay) * score(y0, x0 + 1)
            + (1 - ax) * ay * score(y0 + 1, x0) + ax * ay * score(y0 + 1, x0 + 1))


def _dot_score(f_src: np.ndarray, target: np.ndarray):
    """Scalar map ``<f_src, target[:, yi, xi]>``, zero outside ``target``."""
    _, H, W = target.shape

    def score(yi: int, xi: int) -> float:
        return float(f_src @ target[:, yi, xi]) if 0 <= yi < H and 0 <= xi < W else 0.0
    return score


def _avg_pool(maps: np.ndarray, k: int) -> np.ndarray:
    C, H, W = maps.shape
    h, w = H // k, W // k
    return maps[:, :h * k, :w * k].reshape(C, h, k, w, k).mean(axis=(2, 4))


def brute_droid_corr(fmaps, ii, jj, coords, levels=CORR_LEVELS, radius=3) -> np.ndarray:
    fmaps = np.asarray(fmaps, np.float64) / 4.0
    E, h, w, _ = coords.shape
    D = 2 * radius + 1
    out = np.zeros((E, levels * D * D, h, w))
    for e in range(E):
        for lvl in range(levels):
            target = _avg_pool(fmaps[jj[e]], 2 ** lvl)
            for y in range(h):
                for x in range(w):
                    score = _dot_score(fmaps[ii[e]][:, y, x], target)
                    cx, cy = coords[e, y, x] / 2 ** lvl
                    for dx in range(D):
                        for dy in range(D):
                            out[e, lvl * D * D + dx * D + dy, y, x] = _bilinear_at(score, cx - radius + dx,
                                                                                   cy - radius + dy)
    return out


def brute_dpvo_corr(gmap, fmaps, kk, jj, coords, radius=3, pools=DPVO_POOLS) -> np.ndarray:
    gmap, fmaps = np.asarray(gmap, np.float64), np.asarray(fmaps, np.float64)
    E, p = coords.shape[:2]
    D = 2 * radius + 1
    out = np.zeros((E, D, D, p, p, len(pools)))
    for e in range(E):
        for lvl, k in enumerate(pools):
            target = _avg_pool(fmaps[jj[e]], k)
            for row in range(p):
                for col in range(p):
                    score = _dot_score(gmap[kk[e], :, row, col], target)
                    cx, cy = coords[e, row, col] / k
                    for dx in range(D):
                        for dy in range(D):
                            out[e, dx, dy, row, col, lvl] = _bilinear_at(score, cx - radius + dx, cy - radius + dy)
    return out.reshape(E, -1)


def test_droid_correlation_lookups_match_a_brute_force_lookup():
    g = torch.Generator().manual_seed(7)
    fmaps = torch.randn(3, 16, 9, 11, generator=g)  # odd sizes: the pooled levels floor them
    ii, jj = torch.tensor([0, 1, 2, 0]), torch.tensor([1, 2, 0, 2])
    # points inside, near and beyond the border (zeros outside) and at exact integers
    coords = torch.rand(4, 9, 11, 2, generator=g) * torch.tensor([15.0, 13.0]) - 2.0
    coords[0, 0, 0] = torch.tensor([3.0, 4.0])
    expect = brute_droid_corr(fmaps.numpy(), ii.tolist(), jj.tolist(), coords.double().numpy())
    volume = CorrVolume(fmaps[ii], fmaps[jj])(coords)
    reduction = lookup_reduction(fmaps.shape[1], 2 ** (CORR_LEVELS - 1))
    close(volume, expect.astype(np.float32), "CorrVolume", reduction)
    for mode in ("volume", "features"):
        close(AltCorr(fmaps, chunk=3, mode=mode)(coords, ii, jj), expect.astype(np.float32), f"AltCorr {mode}",
              reduction)


def test_dpvo_patch_correlation_matches_a_brute_force_lookup():
    g = torch.Generator().manual_seed(8)
    fmaps = torch.randn(3, 16, 18, 22, generator=g)
    gmap = torch.randn(4, 16, 3, 3, generator=g)
    kk, jj = torch.tensor([0, 1, 2, 3, 1]), torch.tensor([1, 2, 0, 1, 0])
    coords = torch.rand(5, 3, 3, 2, generator=g) * torch.tensor([26.0, 22.0]) - 2.0
    coords[0, 1, 1] = torch.tensor([5.0, 6.0])
    expect = brute_dpvo_corr(gmap.numpy(), fmaps.numpy(), kk.tolist(), jj.tolist(), coords.double().numpy())
    close(patch_correlation(gmap, pyramid(fmaps), coords, kk, jj), expect.astype(np.float32), "patch_correlation",
          lookup_reduction(fmaps.shape[1], max(DPVO_POOLS)))
