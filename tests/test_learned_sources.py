"""The learned sources plugged into the frontends' source interfaces (``dense.source.kind: droid``,
``patch.source: dpvo``) with randomly initialised checkpoints in the official file form: structure,
not accuracy (the official weights are not on this machine)."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import torch

from fgslam.core.config import load_config
from fgslam.core.errors import ConfigError, DataError
from fgslam.frontends.dense.source import DenseSourceConfig, LearnedDroidSource, make_dense_source
from fgslam.frontends.flow import DenseFlowSource, FlowRevision
from fgslam.frontends.patch import PatchConfig, make_source
from fgslam.frontends.patch.measurement import Measurement
from fgslam.frontends.patch.source import LearnedDPVOSource
from fgslam.nets.checkpoint import CheckpointError
from fgslam.nets.config import DpvoNetConfig, DroidNetConfig
from fgslam.backend import Backend, BackendConfig
from nets_support import official_dpvo_file, official_droid_file
from nets_support import one_thread  # noqa: F401 (autouse fixture)

H, W = 64, 80  # DROID: a multiple of 8 and at least 64 (4 pyramid levels)




@pytest.fixture(scope="module")
def ckpts(tmp_path_factory):
    root = tmp_path_factory.mktemp("ckpt")
    torch.save(official_droid_file(seed=4), root / "droid.pth")
    torch.save(official_dpvo_file(seed=5), root / "dpvo.pth")
    still = official_droid_file(seed=4)  # the update's delta head at zero: a source that revises nothing
    for name in ("module.update.delta.2.weight", "module.update.delta.2.bias"):
        still[name].zero_()
    torch.save(still, root / "droid_no_revision.pth")
    return root


def images(n=3, seed=0):
    rng = np.random.default_rng(seed)
    base = (rng.random((H + 16, W + 16)) * 255).astype(np.uint8)
    return [np.ascontiguousarray(base[2 * k:2 * k + H, 3 * k:3 * k + W]) for k in range(n)]


def induced(n_edges, h=H // 8, w=W // 8):
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    uv = np.stack((x + 0.3, y - 0.2), -1)[None].repeat(n_edges, 0)
    uv[:, 0, 0] = np.nan  # an invalid reprojection
    return uv


def droid(ckpts, **kw):
    return make_dense_source(DenseSourceConfig(kind="droid", checkpoint=str(ckpts / "droid.pth"),
                                               droid=DroidNetConfig(**kw)))


def test_droid_source_gives_what_the_flow_source_gives(ckpts):
    src = droid(ckpts, iterations=2)
    flow = DenseFlowSource(stride=8)
    assert isinstance(src, LearnedDroidSource) and src.grid_shape((H, W)) == (8, 10)
    for k, im in enumerate(images()):
        src.add_frame(k, im)
        flow.add_frame(k, im)
    edges = [(0, 1), (1, 0), (1, 2)]
    revs = src.revise(edges, induced(3))
    ref = flow.revise(edges, induced(3))
    assert len(revs) == 3 and all(isinstance(r, FlowRevision) for r in revs)
    for r, f in zip(revs, ref):
        for name in ("target", "weight", "fb_error"):
            a, b = getattr(r, name), getattr(f, name)
            assert a.shape == b.shape and a.dtype == b.dtype == np.float64, name
        assert np.isfinite(r.target).all() and ((r.weight >= 0) & (r.weight <= 1)).all()
        assert (r.weight[0, 0] == 0).all() and (r.weight[1:] > 0).all()
        assert r.damping.shape == (8, 10) and (r.damping > 0).all() and np.isnan(r.fb_error).all()
    # one damping per source frame: edges (1, 0) and (1, 2) share frame 1's
    np.testing.assert_array_equal(revs[1].damping, revs[2].damping)


def true_induced(edges, h=H // 8, w=W // 8):
    """The exact correspondence field of ``images()`` (frame k is the base shifted by (3k, 2k) px) in grid
    pixels of j, with one invalid reprojection at (0, 0)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    uv = np.stack([np.stack((x - 3.0 * (j - i) / 8, y - 2.0 * (j - i) / 8), -1) for i, j in edges])
    uv[:, 0, 0] = np.nan
    return uv


def test_droid_and_flow_sources_give_the_same_correspondences(ckpts):
    """The same values in the same convention (grid pixels of j): fed the exact correspondence field, a
    DROID source whose network revises nothing (delta head at zero) returns it unchanged, and the flow
    source measures it from the images. They agree to the flow source's own accuracy on these images
    (measured: max 0.057, median 0.0065 grid px = 0.45 / 0.05 image px); a half-cell or axis-swap
    convention error would be >= 0.25 grid px."""
    src = make_dense_source(DenseSourceConfig(kind="droid", checkpoint=str(ckpts / "droid_no_revision.pth"),
                                              droid=DroidNetConfig(iterations=2)))
    flow = DenseFlowSource(stride=8)
    for k, im in enumerate(images()):
        src.add_frame(k, im)
        flow.add_frame(k, im)
    edges = [(0, 1), (1, 0), (1, 2)]
    uv = true_induced(edges)
    ok = np.isfinite(uv).all(-1)
    for r, f, u, m in zip(src.revise(edges, uv), flow.revise(edges, uv), uv, ok):
        np.testing.assert_allclose(r.target[m], u[m], atol=1e-5)
        diff = np.abs(r.target - f.target)[m]
        assert diff.max() < 0.1 and np.median(diff) < 0.02, (diff.max(), np.median(diff))


def test_droid_recurrent_state_is_kept_per_edge_and_dropped_with_frames(ckpts):
    a, b = droid(ckpts), droid(ckpts)
    for k, im in enumerate(images(2)):
        a.add_frame(k, im)
        b.add_frame(k, im)
    first = a.revise([(0, 1)], induced(1))[0]
    np.testing.assert_allclose(b.revise([(0, 1)], induced(1))[0].target, first.target, atol=1e-5)  # deterministic
    second = a.revise([(0, 1)], induced(1))[0]  # same inputs, carried hidden state and target
    assert np.abs(second.target - first.target).max() > 1e-4
    a.remove_frame(1)
    with pytest.raises(DataError, match="frame 1 was not added"):
        a.revise([(0, 1)], induced(1))
    a.add_frame(1, images(2)[1])
    np.testing.assert_allclose(a.revise([(0, 1)], induced(1))[0].target, first.target, atol=1e-5)  # fresh edge


@pytest.mark.parametrize("mode", ["alt", "features"])
def test_droid_memory_efficient_and_volume_correlation_agree(ckpts, mode):
    alt, vol = droid(ckpts, correlation=mode, chunk_edges=1), droid(ckpts, correlation="volume")
    for k, im in enumerate(images()):
        alt.add_frame(k, im)
        vol.add_frame(k, im)
    edges = [(0, 2), (2, 1)]
    for r, s in zip(alt.revise(edges, induced(2)), vol.revise(edges, induced(2))):
        np.testing.assert_allclose(r.target, s.target, atol=1e-4)
        np.testing.assert_allclose(r.weight, s.weight, atol=1e-5)


def test_droid_source_errors(ckpts, tmp_path):
    with pytest.raises(ConfigError, match="dense.source.checkpoint.*dense.source.kind=flow"):
        make_dense_source(DenseSourceConfig(kind="droid"))
    with pytest.raises(DataError, match="not found.*dense.source.kind=flow"):
        LearnedDroidSource(str(tmp_path / "droid.pth"))
    (tmp_path / "droid.pth").write_bytes(b"weights")
    with pytest.raises(CheckpointError, match="not a readable torch state dict.*dense.source.checkpoint.*kind=flow"):
        LearnedDroidSource(str(tmp_path / "droid.pth"))
    with pytest.raises(CheckpointError, match="not a DROID-SLAM"):
        LearnedDroidSource(str(ckpts / "dpvo.pth"))
    with pytest.raises(ConfigError, match="stride must be 8"):
        LearnedDroidSource(str(ckpts / "droid.pth"), stride=4)
    src = droid(ckpts)
    with pytest.raises(DataError, match="at least 64x64"):
        src.add_frame(0, np.zeros((48, 80), np.uint8))
    with pytest.raises(DataError, match="uint8"):
        src.add_frame(0, np.zeros((64, 80), np.float32))


def test_learned_source_settings_load_from_yaml_with_ranges(tmp_path):
    path = tmp_path / "dense.yaml"
    path.write_text("kind: droid\ncheckpoint: /x/droid.pth\ndroid:\n  iterations: 3\n  threads: 2\n  device: cpu\n")
    cfg = load_config(DenseSourceConfig, path)
    assert cfg.kind == "droid" and cfg.droid.iterations == 3 and cfg.droid.threads == 2 and cfg.droid.device == "cpu"
    with pytest.raises(ConfigError, match="droid.iterations"):
        load_config(DenseSourceConfig, path, ["droid.iterations=0"])
    patch = tmp_path / "patch.yaml"
    patch.write_text("source: dpvo\ncheckpoint: /x/dpvo.pth\ndpvo:\n  iterations: 2\n")
    pc = load_config(PatchConfig, patch)
    pc.validate()
    assert pc.source == "dpvo" and pc.dpvo.iterations == 2
    with pytest.raises(ConfigError, match="dpvo.device"):
        load_config(PatchConfig, patch, ["dpvo.device=tpu"])


def patch_requests(src, feats, n=6, seed=0):
    rng = np.random.default_rng(seed)
    uv_src = np.stack((rng.uniform(12, W - 12, n), rng.uniform(12, H - 12, n)), -1)
    pred = uv_src + np.array([3.0, 2.0])
    return [(feats[0], feats[1], uv_src, pred), (feats[0], feats[2], uv_src, pred + 1.0), (feats[1], feats[0], pred, uv_src)]


def test_dpvo_source_measures_patches_through_the_patch_interface(ckpts):
    cfg = PatchConfig(source="dpvo", checkpoint=str(ckpts / "dpvo.pth"), dpvo=DpvoNetConfig(iterations=2))
    src = make_source(cfg)
    assert isinstance(src, LearnedDPVOSource)
    feats = [src.prepare(im) for im in images()]
    reqs = patch_requests(src, feats)
    out = src.measure_batch(reqs)
    assert len(out) == 3 and all(isinstance(m, Measurement) for m in out)
    for m, (_, _, uv_src, pred) in zip(out, reqs):
        assert m.uv.shape == (6, 2) and m.confidence.shape == (6,) and m.fb_error.shape == (6,)
        assert np.isfinite(m.uv).all() and ((m.confidence >= 0) & (m.confidence <= 1)).all()
        assert np.abs(m.uv - pred).max() < 64  # a revision around the prediction, in full-resolution pixels
    single = make_source(cfg).measure(*reqs[0])
    assert single.uv.shape == (6, 2)
    # the hidden state of each edge is carried to the next measurement of the same edge
    again = src.measure_batch(reqs)
    assert np.abs(again[0].uv - out[0].uv).max() > 1e-4
    # long-range edges keep only the image and recompute the maps
    packed = src.pack(feats[0])
    assert isinstance(packed, np.ndarray) and packed.dtype == np.uint8
    torch.testing.assert_close(src.unpack(packed).levels[0], feats[0].levels[0])
    # states of frames whose features are gone are dropped
    runner = src._runner
    assert runner._states
    del feats, reqs, out, again
    gc.collect()
    assert not runner._states


def test_dpvo_source_errors(ckpts, tmp_path):
    with pytest.raises(ConfigError, match="patch.checkpoint.*source=lk"):
        make_source(PatchConfig(source="dpvo"))
    with pytest.raises(DataError, match=r"dpvo\.pth.*source=lk"):
        make_source(PatchConfig(source="dpvo", checkpoint=str(tmp_path / "dpvo.pth")))
    with pytest.raises(CheckpointError, match="not a DPVO.*patch.source=lk"):
        make_source(PatchConfig(source="dpvo", checkpoint=str(ckpts / "droid.pth")))
    with pytest.raises(ConfigError, match="unknown source"):
        make_source(PatchConfig(source="sift"))  # type: ignore[arg-type]


def _dpvo_room_run(ckpts, frames, revise):
    """The patch frontend (RGB-D) on ``frames`` with the DPVO source, each measurement passed through
    ``revise(measurement, i, j, uv_src)`` (i, j: frame indices of the request); (frontend, statuses,
    the confidences the source returned)."""
    from fgslam.frontends.patch import PatchFrontend
    from patch_support import light_patch_config

    cfg = light_patch_config(4.0)
    cfg.source, cfg.checkpoint = "dpvo", str(ckpts / "dpvo.pth")
    cfg.graph.patches_per_frame = 32
    fe = PatchFrontend(cfg, sensor_mode="rgbd", backend=Backend(BackendConfig()))
    assert isinstance(fe.source, LearnedDPVOSource)
    frame_of_image = {id(f.colour_or_grey()): n for n, f in enumerate(frames)}  # what the source is fed
    frame_of_features, confidences = {}, []
    prepare, measure_batch = fe.source.prepare, fe.source.measure_batch

    def preparing(image):
        features = prepare(image)
        frame_of_features[id(features)] = frame_of_image[id(image)]
        return features

    def measuring(requests):
        out = measure_batch(requests)
        confidences.extend(m.confidence for m in out)
        return [revise(m, frame_of_features[id(a)], frame_of_features[id(b)], uv)
                for m, (a, b, uv, _) in zip(out, requests)]

    fe.source.prepare, fe.source.measure_batch = preparing, measuring
    statuses = [fe.process(f) for f in frames]
    fe.finish()
    return fe, statuses, np.concatenate(confidences)


@pytest.fixture(scope="module")
def dpvo_room(tmp_path_factory):
    from patch_support import open_frames, render_room

    root = render_room(tmp_path_factory, "room_dpvo", ["frames=10", "camera.width=160", "camera.height=128"])
    return open_frames(root, "rgbd")[1]


def test_patch_frontend_runs_end_to_end_on_the_dpvo_source(ckpts, dpvo_room):
    """Wiring (random weights): every frame gets a pose, the source's features flow through prepare /
    measure_batch of the real frontend, and its confidences are real ones (in (0, 1), not zero)."""
    frames = dpvo_room
    fe, statuses, confidence = _dpvo_room_run(ckpts, frames, lambda m, i, j, uv: m)
    assert len(fe.trajectory()[0]) == len(frames)
    assert all(s.pose_source in ("tracked", "motion_model") for s in statuses)
    # random weights: every confidence is near 0.5 (measured 0.5016 .. 0.5029 over 288 patches)
    assert confidence.size > 100 and ((confidence > 0.1) & (confidence < 0.9)).all()


def test_patch_frontend_poses_from_the_dpvo_source_s_confidences(ckpts, dpvo_room):
    """Random weights cannot measure motion (their trajectory is the stationary one), so the patch
    positions are replaced by the true ones while the confidences stay the network's: the trajectory
    must then beat doing nothing, and fail to when the confidences are zeroed (the frontend does use
    what the source returns). Measured on 10 frames: 0.00009 m with the network's confidences, 0.0479 m
    with zero confidences, 0.0479 m standing still (and 0.0479 m for the plain random-weight run)."""
    from fgslam.eval.trajectory import EvalConfig, evaluate
    from fgslam.io.trajectory import Trajectory
    from eval_support import BEAT_FACTOR, do_nothing_ate, frames_groundtruth

    frames = dpvo_room
    fx, fy, cx, cy = frames[0].calibration.K

    def truth(m, i, j, uv):
        z = frames[i].depth[np.clip(np.rint(uv[:, 1]).astype(int), 0, frames[i].depth.shape[0] - 1),
                            np.clip(np.rint(uv[:, 0]).astype(int), 0, frames[i].depth.shape[1] - 1)]
        X = np.stack(((uv[:, 0] - cx) / fx * z, (uv[:, 1] - cy) / fy * z, z), -1)
        T = np.linalg.inv(frames[j].T_WC_gt) @ frames[i].T_WC_gt
        Y = X @ T[:3, :3].T + T[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv_j = np.stack((fx * Y[:, 0] / Y[:, 2] + cx, fy * Y[:, 1] / Y[:, 2] + cy), -1)
        ok = np.isfinite(uv_j).all(1) & (z > 0)
        return Measurement(uv=np.where(ok[:, None], uv_j, m.uv), confidence=np.where(ok, m.confidence, 0.0),
                           fb_error=m.fb_error)

    gt = frames_groundtruth(frames)
    results = {}
    for name, revise in (("network", truth), ("zero", lambda m, i, j, uv: Measurement(
            uv=truth(m, i, j, uv).uv, confidence=np.zeros_like(m.confidence), fb_error=m.fb_error))):
        fe, _, _ = _dpvo_room_run(ckpts, frames, revise)
        t, T, _ = fe.trajectory()
        results[name] = evaluate(gt, Trajectory(t, T), EvalConfig(align="se3")).ate.rmse
    still = do_nothing_ate(gt, gt.timestamps, "se3")
    assert results["network"] < BEAT_FACTOR * still
    assert results["zero"] >= BEAT_FACTOR * still
