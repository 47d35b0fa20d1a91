"""Patch graph bookkeeping: edge creation within the lifetime, removal window, frame removal,
inactive store bounds, and configuration checks."""

from __future__ import annotations

import numpy as np
import pytest

from fgslam.core.errors import ConfigError, DataError
from fgslam.frontends.patch.config import PatchGraphConfig, PatchConfig
from fgslam.frontends.patch.graph import GraphFrame, InactiveEdges, PatchGraph
from fgslam.frontends.patch.source import make_source

K = 8


def _frame(fid: int) -> GraphFrame:
    rng = np.random.default_rng(fid)
    return GraphFrame(fid=fid, index=fid, timestamp=0.1 * fid, T_WC=np.eye(4), uv=rng.uniform(10, 100, (K, 2)),
                      inv_depth=np.full(K, 0.5), sensor_inv_depth=np.full(K, np.nan),
                      colour=np.zeros((K, 3), np.uint8))


def _graph(lifetime=3, removal=5, max_inactive=10_000) -> PatchGraph:
    cfg = PatchGraphConfig(patches_per_frame=K, patch_lifetime=lifetime, removal_window=removal, optimization_window=4)
    return PatchGraph(cfg, max_inactive)


def test_new_frame_edges_respect_lifetime():
    g = _graph(lifetime=3)
    for fid in range(6):
        g.add_frame(_frame(fid))
        idx = g.connect_new_frame(stereo=False, stereo_cross=False)
        older = list(range(max(0, fid - 3), fid))
        # forward: every patch of each older frame into the new one; backward: the reverse
        assert idx.size == 2 * K * len(older)
        fwd = g.tgt[idx] == fid
        assert sorted(set(g.src[idx][fwd].tolist())) == older
        assert sorted(set(g.tgt[idx][~fwd].tolist())) == older
        assert np.all(g.src[idx][~fwd] == fid)
        assert set(np.bincount(g.patch[idx], minlength=K).tolist()) == {2 * len(older)} if older else True
    # no edge spans more than the lifetime
    assert np.abs(g.src - g.tgt).max() <= 3


def test_stereo_edges_into_own_right_image():
    g = _graph()
    g.add_frame(_frame(0))
    g.add_frame(_frame(1))
    idx = g.connect_new_frame(stereo=True, stereo_cross=False)
    right = g.right[idx]
    assert right.sum() == K
    assert np.all(g.src[idx][right] == 1) and np.all(g.tgt[idx][right] == 1)
    idx2 = g.connect_all(stereo=True)
    assert g.right[idx2].sum() == 2 * K


def test_removal_window_moves_measured_edges_to_inactive_store():
    g = _graph(lifetime=2, removal=4)
    for fid in range(9):
        g.add_frame(_frame(fid))
        idx = g.connect_new_frame(stereo=False, stereo_cross=False)
        g.confidence[idx[::2]] = 1.0  # half of the edges measured
        g.uv[idx] = 1.0
        g.deactivate_old_edges()
    n = len(g) - 1
    oldest_active = g.frames[n - 4].fid
    assert g.src.min() >= oldest_active
    store = g.inactive.arrays()
    assert store["src"].max() < oldest_active
    assert np.all(store["confidence"] > 0)  # only measured edges are kept
    assert store["uv_src"].shape == (store["src"].size, 2)
    # frames before every active edge's reach can be popped; edges into them go too
    popped = g.pop_frames_before(2)
    assert [f.fid for f in popped] == [0, 1]
    assert not np.isin(g.tgt, [0, 1]).any()


def test_remove_frame_drops_its_edges():
    g = _graph(lifetime=3)
    for fid in range(4):
        g.add_frame(_frame(fid))
        g.connect_new_frame(stereo=False, stereo_cross=False)
    before = g.num_edges
    touching = int(((g.src == 2) | (g.tgt == 2)).sum())
    g.remove_frame(2)
    assert g.num_edges == before - touching
    assert 2 not in g.fids.tolist()
    assert np.array_equal(g.positions(np.array([0, 1, 3])), [0, 1, 2])


def test_inactive_store_is_bounded():
    store = InactiveEdges(max_edges=10)
    for i in range(5):
        store.add({"src": np.full(4, i)})
    assert store.count == 8 and store.dropped == 12  # whole chunks, oldest first
    assert store.arrays()["src"].tolist() == [3] * 4 + [4] * 4


def test_config_validation_and_learned_source_errors(tmp_path):
    with pytest.raises(ConfigError, match="removal_window"):
        PatchConfig(graph=PatchGraphConfig(patch_lifetime=10, removal_window=10)).validate()
    with pytest.raises(ConfigError, match="source=lk"):
        make_source(PatchConfig(source="learned"))
    missing = tmp_path / "dpvo.pth"
    with pytest.raises(DataError, match=r"dpvo\.pth.*source=lk"):
        make_source(PatchConfig(source="learned", checkpoint=str(missing)))


def test_patch_config_loads_from_yaml(tmp_path):
    from fgslam.core.config import load_config

    path = tmp_path / "patch.yaml"
    path.write_text("source: lk\ngraph:\n  patches_per_frame: 64\n  patch_lifetime: 4\nlk:\n  scale: 0.5\n")
    cfg = load_config(PatchConfig, path, ["tracking.motion_damping=0.7"])
    assert cfg.graph.patches_per_frame == 64 and cfg.graph.patch_lifetime == 4
    assert cfg.lk.scale == 0.5 and cfg.tracking.motion_damping == 0.7
    cfg.validate()
    path.write_text("graph:\n  patch_lifetiem: 4\n")
    with pytest.raises(ConfigError, match="patch_lifetiem"):
        load_config(PatchConfig, path)
