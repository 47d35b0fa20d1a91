"""tools/train.py on a tiny pool: clips obey the flow range, one optimisation step moves every part of
the network (gradients reach the encoders through the dense BA layer), and the checkpoint it writes
is what the dense source loads."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fgslam.frontends.dense.source import DenseSourceConfig, LearnedDroidSource, make_dense_source
from tool_support import load_tool

train = load_tool("train")


@pytest.fixture(scope="module")
def tiny():
    torch.set_num_threads(1)
    cfg = train.TrainConfig(width=64, height=64, pool_frames=24, iterations=2, ba_steps=1, edge_radius=1,
                            eval_clips=1, clip_frames=3, threads=1, flow_min=8.0, flow_max=96.0)
    return cfg, train.ClipPool(cfg)


def test_clips_follow_the_flow_range(tiny):
    cfg, pool = tiny
    rng = np.random.default_rng(0)
    for _ in range(5):
        clip = pool.sample(rng)
        assert len(clip) == cfg.clip_frames and all(b > a for a, b in zip(clip, clip[1:]))
        for a, b in zip(clip, clip[1:]):
            assert cfg.flow_min <= pool.flow[a, b - a] <= cfg.flow_max
    narrow = train.ClipPool.__new__(train.ClipPool)
    narrow.cfg, narrow.frames, narrow.flow = cfg, pool.frames, np.full_like(pool.flow, np.nan)
    with pytest.raises(train.FGSlamError, match="no clip"):
        narrow.sample(rng)


def test_a_step_trains_every_part_and_writes_a_loadable_checkpoint(tiny, tmp_path):
    cfg, pool = tiny
    torch.manual_seed(0)
    net = train.DroidNet()
    before = {k: v.clone() for k, v in net.state_dict().items()}
    losses = train.unroll(net, pool, pool.sample(np.random.default_rng(1)), cfg, torch.device("cpu"))
    assert len(losses) == cfg.iterations and all(torch.isfinite(p) and torch.isfinite(f) for p, f in losses)
    train.total_loss(losses, cfg).backward()
    for name in ("fnet.conv1.weight", "cnet.conv2.weight", "update.gru.convq.weight", "update.delta.2.weight",
                 "update.weight.2.weight", "update.agg.eta.0.weight"):
        grad = dict(net.named_parameters())[name].grad
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().max() > 0, name
    out = tmp_path / "droid.pth"
    summary = train.train(train.TrainConfig(**{**cfg.__dict__, "steps": 1, "eval_every": 1, "out": str(out)}),
                          log=lambda line: None, pool=pool)
    assert [e["step"] for e in summary["eval"]] == [0, 1]
    assert all(np.isfinite(e["pose_loss"]) and np.isfinite(e["flow_loss"]) for e in summary["eval"])
    source = make_dense_source(DenseSourceConfig(kind="droid", checkpoint=str(out)))
    assert isinstance(source, LearnedDroidSource)
    assert before.keys() == source._runner.net.state_dict().keys()


def test_a_batch_of_clips_is_the_mean_of_its_clips_and_float32_follows_float64(tiny):
    cfg, pool = tiny
    rng = np.random.default_rng(2)
    clips = [pool.sample(rng) for _ in range(3)]
    torch.manual_seed(0)
    net = train.DroidNet()
    cpu = torch.device("cpu")
    with torch.no_grad():
        alone = np.mean([[(float(p), float(f)) for p, f in train.unroll(net, pool, c, cfg, cpu)] for c in clips], axis=0)
        batch = np.array([(float(p), float(f)) for p, f in train.unroll(net, pool, clips, cfg, cpu)])
        single = np.array([(float(p), float(f)) for p, f in train.unroll(net, pool, clips, cfg, cpu, torch.float32)])
    assert train.ba_dtype(cfg, cpu) == torch.float64 and train.ba_dtype(cfg, torch.device("cuda")) == torch.float32
    np.testing.assert_allclose(batch, alone, rtol=1e-9)
    np.testing.assert_allclose(single, batch, rtol=1e-4)
    assert train.initial_losses(pool, clips, cfg) == pytest.approx(np.mean([train.initial_losses(pool, c, cfg)
                                                                            for c in clips], axis=0), rel=1e-12)


def test_a_pool_of_several_scenes_keeps_clips_inside_one_scene():
    cfg = train.TrainConfig(width=64, height=64, pool_frames=10, pool_seeds=2, clip_frames=3, max_gap=6, flow_min=4.0)
    pool = train.ClipPool(cfg)
    assert len(pool.frames) == 20 and list(pool.scene) == [0] * 10 + [1] * 10
    assert np.isfinite(pool.flow[3, 3:7]).all() and np.isfinite(pool.flow[13, 3:7]).all()  # inside a scene
    assert not np.isfinite(pool.flow[7, 3:7]).any()  # 7 -> 10..13 would cross into the second scene
    assert not np.array_equal(pool.frames[0].image, pool.frames[10].image)  # another scene, the same first pose
    np.testing.assert_array_equal(pool.frames[0].T_WC, pool.frames[10].T_WC)
    rng = np.random.default_rng(0)
    for _ in range(20):
        clip = pool.sample(rng)
        assert len(set(pool.scene[clip])) == 1
    with pytest.raises(train.FGSlamError, match="ba-dtype"):
        train.ba_dtype(train.TrainConfig(ba_dtype="float16"), torch.device("cpu"))
