"""The DROID-SLAM and DPVO networks: official parameter names and shapes, strict loading of files in
the official form, clear errors for wrong files, and the pieces' arithmetic (correlation, lookup,
aggregation, upsampling) against brute force."""

from __future__ import annotations

import pytest
import torch

from fgslam.core.errors import DataError
from fgslam.nets.checkpoint import CheckpointError, load_dpvo, load_droid, save_checkpoint
from fgslam.nets.common import scatter_softmax, window_lookup
from fgslam.nets.dpvo import SoftAgg, VONet, neighbors, patch_correlation, pyramid
from fgslam.nets.droid import AltCorr, CorrVolume, DroidNet, GraphAgg, convex_upsample

from nets_support import droid_table, dpvo_table, official_dpvo_file, official_droid_file
from nets_support import one_thread  # noqa: F401 (autouse fixture)




# ------------------------------------------------------------------------------ names and shapes
@pytest.mark.parametrize("cls, table", [(DroidNet, droid_table), (VONet, dpvo_table)])
def test_state_dict_has_exactly_the_official_names_and_shapes(cls, table):
    ours = {k: tuple(v.shape) for k, v in cls().state_dict().items()}
    assert ours == dict(table())


def test_official_droid_file_loads_strictly_with_its_extra_channels(tmp_path):
    state = official_droid_file(seed=1)
    path = tmp_path / "droid.pth"
    torch.save(state, path)
    net = load_droid(path)
    loaded = net.state_dict()
    assert torch.equal(loaded["fnet.conv1.weight"], state["module.fnet.conv1.weight"])
    assert torch.equal(loaded["update.delta.2.weight"], state["module.update.delta.2.weight"][:2])
    assert torch.equal(loaded["update.weight.2.bias"], state["module.update.weight.2.bias"][:2])
    assert not net.training


def test_official_dpvo_file_loads_strictly_without_lmbda(tmp_path):
    state = official_dpvo_file(seed=2)
    path = tmp_path / "dpvo.pth"
    torch.save(state, path)
    loaded = load_dpvo(path).state_dict()
    assert "update.lmbda" not in loaded
    assert torch.equal(loaded["update.agg_ij.g.weight"], state["module.update.agg_ij.g.weight"])
    # DPV-SLAM's newer wrapper
    torch.save({"model_state_dict": state}, path)
    assert torch.equal(load_dpvo(path).state_dict()["update.corr.5.bias"], state["module.update.corr.5.bias"])


def test_saved_checkpoint_round_trips(tmp_path):
    net = DroidNet()
    path = save_checkpoint(net, tmp_path / "out" / "droid.pth")
    again = load_droid(path)
    for k, v in net.state_dict().items():
        assert torch.equal(v, again.state_dict()[k])


def test_wrong_or_missing_files_are_clear_errors(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        load_droid(tmp_path / "nope.pth")
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"this is not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable torch state dict"):
        load_dpvo(junk)
    swapped = tmp_path / "dpvo_as_droid.pth"
    torch.save(official_dpvo_file(), swapped)
    with pytest.raises(CheckpointError, match=r"not a DROID-SLAM \(droid.pth\) state dict: \d+ missing keys \(fnet"):
        load_droid(swapped)
    bad = official_droid_file()
    bad["module.update.gru.convz.weight"] = torch.zeros(128, 400, 3, 3)
    torch.save(bad, tmp_path / "bad.pth")
    with pytest.raises(CheckpointError, match=r"1 shape mismatches \(update.gru.convz.weight \(128, 400, 3, 3\)"):
        load_droid(tmp_path / "bad.pth")
    torch.save([1, 2, 3], tmp_path / "list.pth")
    with pytest.raises(CheckpointError, match="does not hold a state dict"):
        load_droid(tmp_path / "list.pth")
    assert issubclass(CheckpointError, DataError)


# ------------------------------------------------------------------------------ arithmetic
def _brute_bilinear(img, x, y):
    H, W = img.shape[-2:]

    def at(i, j):
        return img[..., i, j] if 0 <= i < H and 0 <= j < W else torch.zeros(img.shape[:-2], dtype=img.dtype)

    x0, y0 = int(torch.floor(torch.tensor(x))), int(torch.floor(torch.tensor(y)))
    ax, ay = x - x0, y - y0
    return ((1 - ax) * (1 - ay) * at(y0, x0) + ax * (1 - ay) * at(y0, x0 + 1) + (1 - ax) * ay * at(y0 + 1, x0)
            + ax * ay * at(y0 + 1, x0 + 1))


def test_window_lookup_is_bilinear_with_zero_border_in_x_major_order():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64)
    pts = torch.tensor([[[2.3, 1.7], [0.2, 4.6]]], dtype=torch.float64)
    win = window_lookup(src, torch.tensor([1]), pts, radius=1)  # (1, 2, 3, 3, 3)
    for q, (x, y) in enumerate(pts[0].tolist()):
        for a, ox in enumerate((-1, 0, 1)):
            for b, oy in enumerate((-1, 0, 1)):
                torch.testing.assert_close(win[0, q, a, b], _brute_bilinear(src[1], x + ox, y + oy))


def test_memory_efficient_correlation_equals_the_all_pairs_pyramid():
    g = torch.Generator().manual_seed(1)
    fmaps = torch.randn(3, 8, 16, 12, generator=g, dtype=torch.float64)
    ii, jj = torch.tensor([0, 1, 2, 0]), torch.tensor([1, 2, 0, 2])
    coords = torch.rand(4, 16, 12, 2, generator=g, dtype=torch.float64) * torch.tensor([14.0, 18.0]) - 1.0
    volume = CorrVolume(fmaps[ii], fmaps[jj])(coords)
    assert volume.shape == (4, 196, 16, 12)
    for mode in ("volume", "features"):
        torch.testing.assert_close(AltCorr(fmaps, chunk=3, mode=mode)(coords, ii, jj), volume)
    # channel = level * 49 + x_offset * 7 + y_offset: level 0 at offset (+1, -2) of edge 2, pixel (3, 5)
    e, y, x = 2, 3, 5
    cx, cy = coords[e, y, x].tolist()
    f_i = fmaps[ii[e], :, y, x] / 4
    expect = (_brute_bilinear(fmaps[jj[e]] / 4, cx + 1, cy - 2) * f_i).sum()
    torch.testing.assert_close(volume[e, (1 + 3) * 7 + (-2 + 3), y, x], expect)


def test_graph_aggregation_pools_the_edges_of_each_source_frame():
    torch.manual_seed(0)
    agg = GraphAgg().double()
    net = torch.randn(4, 128, 3, 4, dtype=torch.float64)
    ii = torch.tensor([5, 2, 5, 2])
    eta, mask, frames = agg(net, ii)
    assert frames.tolist() == [2, 5] and eta.shape == (2, 3, 4) and mask.shape == (2, 576, 3, 4)
    assert bool((eta > 0).all())
    eta2, _, _ = agg(net[[2, 3, 0, 1]], ii[[2, 3, 0, 1]])  # order of edges does not matter
    torch.testing.assert_close(eta, eta2)
    eta_one, _, _ = agg(net[[0]], ii[[0]])  # frame 5 alone differs from frame 5 pooled with edge 2
    assert not torch.allclose(eta_one[0], eta[1])


def test_convex_upsampling_of_a_constant_field_is_constant():
    data = torch.full((1, 3, 4, 2), 2.5)
    up = convex_upsample(data, torch.randn(1, 576, 3, 4))
    assert up.shape == (1, 24, 32, 2)
    torch.testing.assert_close(up[:, 8:16, 8:24], torch.full((1, 8, 16, 2), 2.5))


def test_soft_aggregation_and_neighbours_match_brute_force():
    torch.manual_seed(0)
    agg = SoftAgg(6).double()
    x = torch.randn(7, 6, dtype=torch.float64)
    keys = torch.tensor([3, 9, 3, 3, 1, 9, 4])
    out = agg(x, keys)
    for k in keys.unique():
        m = keys == k
        w = torch.softmax(agg.g(x[m]), dim=0)
        expect = agg.h((agg.f(x[m]) * w).sum(0))
        torch.testing.assert_close(out[m], expect.expand(int(m.sum()), -1))
    kk = torch.tensor([0, 0, 1, 0, 1, 2])
    jj = torch.tensor([3, 1, 2, 2, 5, 0])
    prev, nxt = neighbors(kk, jj)
    for e in range(6):
        same = [f for f in range(6) if kk[f] == kk[e] and f != e]
        lower = [f for f in same if jj[f] < jj[e]]
        upper = [f for f in same if jj[f] > jj[e]]
        assert prev[e] == (max(lower, key=lambda f: jj[f]) if lower else -1)
        assert nxt[e] == (min(upper, key=lambda f: jj[f]) if upper else -1)
    s = scatter_softmax(torch.tensor([[1.0], [2.0], [0.5]]), torch.tensor([0, 0, 1]), 2)
    torch.testing.assert_close(s[:, 0], torch.tensor([1 / (1 + torch.e), torch.e / (1 + torch.e), 1.0]))


def test_patch_correlation_layout_is_x_y_row_col_level():
    g = torch.Generator().manual_seed(3)
    fmap = torch.randn(2, 4, 12, 16, generator=g, dtype=torch.float64)
    gmap = torch.randn(3, 4, 3, 3, generator=g, dtype=torch.float64)
    coords = torch.rand(2, 3, 3, 2, generator=g, dtype=torch.float64) * 10 + 2
    kk, jj = torch.tensor([2, 0]), torch.tensor([1, 0])
    levels = pyramid(fmap)
    corr = patch_correlation(gmap, levels, coords, kk, jj).reshape(2, 7, 7, 3, 3, 2)
    e, ox, oy, py, px = 0, 5, 1, 2, 0
    for lvl, (scale, fl) in enumerate(zip((1, 4), levels)):
        x, y = (coords[e, py, px] / scale).tolist()
        expect = (_brute_bilinear(fl[jj[e]], x + ox - 3, y + oy - 3) * gmap[kk[e], :, py, px]).sum()
        torch.testing.assert_close(corr[e, ox, oy, py, px, lvl], expect)


def test_forward_passes_have_the_documented_shapes():
    torch.manual_seed(0)
    droid = DroidNet().eval()
    images = torch.randint(0, 255, (2, 3, 64, 80)).float()
    with torch.inference_mode():
        fmaps, net, inp = droid.extract(images)
        assert fmaps.shape == (2, 128, 8, 10) and net.shape == inp.shape == (2, 128, 8, 10)
        assert float(net.abs().max()) <= 1.0 and float(inp.min()) >= 0.0
        ii, jj = torch.tensor([0, 1]), torch.tensor([1, 0])
        grid = torch.stack(torch.meshgrid(torch.arange(10.0), torch.arange(8.0), indexing="xy"), -1)[None].repeat(2, 1, 1, 1)
        out_net, target, weight, (eta, mask, frames) = droid.step(net[ii], inp[ii], AltCorr(fmaps), grid, grid, grid, ii, jj)
        assert target.shape == weight.shape == (2, 8, 10, 2) and eta.shape == (2, 8, 10)
        assert bool(((weight > 0) & (weight < 1)).all())
        vo = VONet().eval()
        fmap, imap = vo.extract(images)
        assert fmap.shape == (2, 128, 16, 20) and imap.shape == (2, 384, 16, 20)
        gmap, ctx = vo.patchify.patches(fmap, imap, torch.tensor([0, 0, 1]), torch.tensor([[4.0, 5.0], [7.5, 3.2], [10.0, 9.0]]))
        assert gmap.shape == (3, 128, 3, 3) and ctx.shape == (3, 384)
        torch.testing.assert_close(ctx[0], imap[0, :, 5, 4])
        torch.testing.assert_close(gmap[0, :, 0, 2], fmap[0, :, 4, 5])  # row -1, column +1
