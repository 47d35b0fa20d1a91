"""Loop closure inside the patch frontend: classical (fgslam.loop.closure through PatchFrontend and the
runner) and proximity (DPV-SLAM 3.2: loop edges + global BA, fgslam.frontends.patch.proximity and
global_ba), on a synthetic room-loop clip that goes once round the room and on past its start, run
with loop closure classical / proximity (synchronous, deterministic) and off.

The clip is rendered at 4 Hz so that one loop (20 s) is 81 frames and the file stays fast; the
default 20 Hz would give the same revisit after 401 frames.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest

from fgslam.core.errors import ConfigError
from fgslam.run.system import SlamSystem
from fgslam.frontends.patch import PatchFrontend
from fgslam.loop.records import LoopClosureConfig
from fgslam.run.presets import config_class_for, load_preset_file
from fgslam.io.run_files import SUMMARY_FILE
from fgslam.run.config import SlamConfig, load_slam_config
from fgslam.run.prepare import open_slam_dataset
from fgslam.run.runner import run_slam
from fgslam.backend import Backend, BackendConfig
from patch_support import light_patch_config

RATE_HZ = 4.0
EXTRA_FRAMES = 19  # frames past the first return to the start (about 20 % of the loop)
REVISIT_M = 0.6  # an accepted loop joins frames whose true positions are at most this far apart
MIN_GAP_S = 10.0  # ... and at least this far apart in time (half the loop)


@pytest.fixture(scope="module")
def room(room_loop_clip):
    return room_loop_clip(RATE_HZ, EXTRA_FRAMES)  # (root, seq), rendered once per session (conftest.py)


def slam_config(mode: str, sensor: str = "mono") -> SlamConfig:
    cfg = SlamConfig(sensor=sensor, patch=light_patch_config())
    cfg.loop_closure = LoopClosureConfig(mode=mode, run_in_thread=False)
    cfg.output.plot = False
    cfg.validate()
    return cfg


@pytest.fixture(scope="module")
def runs(room, tmp_path_factory):
    """summary.json of the runner with loop closure classical, off and proximity; under
    ``proximity_frontend`` the PatchFrontend of the proximity run (handed to the runner, which builds
    the run's system around it)."""
    root, _ = room
    out = {}
    for mode in ("classical", "off", "proximity"):
        cfg = slam_config(mode)
        folder = tmp_path_factory.mktemp(f"run_{mode}")
        dataset = open_slam_dataset(root, cfg)
        frontend = PatchFrontend(cfg.patch, dataset.calibration, cfg.sensor, backend=Backend(cfg.map))
        run_slam(dataset, cfg, folder, progress=False, frontend=frontend)
        out[mode] = json.loads((folder / SUMMARY_FILE).read_text())
        if mode == "proximity":
            out["proximity_frontend"] = frontend
    return out


def test_loop_closed_at_the_return_and_ate_not_worse(room, runs):
    _, seq = room
    on, off = runs["classical"], runs["off"]
    loop = on["loop"]
    assert loop is not None and loop["mode"] == "classical"
    assert loop["accepted_loops"] > 0 and loop["corrections_applied"] > 0
    assert on["stage_s"]["loop"] > 0
    # every accepted loop joins the return to the start of the drive, nowhere else
    T = seq.camera_poses(np.arange(seq.cfg.frames) / RATE_HZ)
    accepted = [(q, c) for q, c, status in loop["loop_frames"] if status == "accepted"]
    assert accepted
    for q, c in accepted:
        assert (q - c) / RATE_HZ >= MIN_GAP_S, (q, c)
        assert np.linalg.norm(T[q][:3, 3] - T[c][:3, 3]) <= REVISIT_M, (q, c)
    ate_on, ate_off = on["evaluation"]["ate"]["rmse"], off["evaluation"]["ate"]["rmse"]
    assert on["frames_with_pose"] >= off["frames_with_pose"] - 1
    assert ate_on <= ate_off, f"ATE with loop closure {ate_on:.4f} m > without {ate_off:.4f} m"


def test_runner_summary_loop_counts(runs):
    on, off = runs["classical"], runs["off"]
    loop = on["loop"]
    for key in ("corrections_applied", "keyframes_added", "verified_loops", "accepted_loops", "verifications",
                "relocalization_attempts", "relocalized"):
        assert isinstance(loop[key], int) and loop[key] >= 0, key
    assert loop["keyframes_added"] > 0 and loop["verified_loops"] >= loop["accepted_loops"]
    assert set(loop["closer_s"]) >= {"describe", "detect", "verify", "pose_graph"}
    assert on["config"]["loop_closure"]["mode"] == "classical"
    assert off["loop"] is None and "loop" not in off["stage_s"]
    assert off["config"]["loop_closure"]["mode"] == "off"


def _closer_threads() -> int:
    return sum(t.name == "fgslam-loop-closer" for t in threading.enumerate())


def _system(config=None, calibration=None, loop_config=None) -> SlamSystem:
    """A patch frontend on its own backend in a system with loop closure from ``loop_config``."""
    fe = PatchFrontend(config or light_patch_config(), calibration, "mono", backend=Backend(BackendConfig()))
    return SlamSystem.around(fe, loop_config)


def test_mode_off_creates_no_closer(room):
    before = _closer_threads()
    system = _system()  # no loop config: off
    assert system.loops is None and not system.frontend.loops.enabled
    system = _system(loop_config=LoopClosureConfig(mode="off"))
    assert system.loops is None and system.loop_summary() is None and "loop" not in system.stage_times()
    assert _closer_threads() == before
    system = _system(loop_config=LoopClosureConfig(mode="classical", run_in_thread=True))
    assert system.loops.closer is not None and system.frontend.loops is system.loops
    assert _closer_threads() == before + 1
    system.finish()  # stops the worker
    assert _closer_threads() == before


def test_registry_and_presets_pass_the_loop_config(room):
    root, _ = room
    cfg = slam_config("classical")
    ds = open_slam_dataset(root, cfg)
    system = SlamSystem.build(cfg, ds.calibration)
    assert system.loops.closer is not None and system.loops.config is cfg.loop_closure
    assert SlamSystem.build(SlamConfig(), ds.calibration).loops is None  # default: off
    assert load_preset_file("patch_street_loop").loop_closure.mode == "both"
    assert load_preset_file("patch_mono").loop_closure.mode == "off"
    assert config_class_for(Path("loop_street.yaml")) is LoopClosureConfig  # loop_*.yaml presets


@pytest.mark.parametrize("override", ["loop_closure.mode=sometimes", "loop_closure.mode=true",
                                      "loop_closure.bogus=1", "loop_closure.max_candidates=0"])
def test_bad_loop_config_is_rejected(override):
    with pytest.raises(ConfigError, match="loop_closure"):
        load_slam_config(None, [override])


def test_bare_yaml_off_selects_mode_off():
    # YAML 1.1 reads a bare off as false; the config loader maps it back to the "off" option
    assert load_slam_config("patch_street_loop", ["loop_closure.mode=off"]).loop_closure.mode == "off"


def test_bad_mode_in_the_system():
    with pytest.raises(ConfigError, match="mode"):
        _system(loop_config=LoopClosureConfig(mode="sometimes"))


def test_relocalisation_after_a_jump_back(room):
    """Frames 0..FIRST_PASS-1, then the camera jumps back to frame JUMP_TO and goes on from there:
    tracking fails, and after ``max_motion_model_frames`` failures the lost frame is relocalised on
    the keyframes of the first pass, close to the pose estimated for the same view then."""
    import cv2

    from fgslam.io.calibration import Calibration
    from fgslam.io.frame import Frame

    first_pass, jump_to, after = 26, 6, 6
    root, seq = room
    cal = Calibration(seq.cfg.camera.width, seq.cfg.camera.height, np.array(seq.K))
    order = list(range(first_pass)) + list(range(jump_to, jump_to + after))
    images = sorted((root / "mav0" / "cam0" / "data").iterdir())  # the clip's frames, rendered once
    cfg = light_patch_config()
    cfg.tracking.max_motion_model_frames = 2
    system = _system(cfg, cal, LoopClosureConfig(mode="classical", run_in_thread=False))
    statuses = []
    for i, k in enumerate(order):
        image = cv2.imread(str(images[k]), cv2.IMREAD_UNCHANGED)
        statuses.append(system.step(Frame(i, i, i / RATE_HZ, image, cal)))
    first_pass_T = {s.index: s.T_WC for s in statuses[:first_pass]}
    system.finish()
    summary = system.loop_summary()
    assert summary["relocalization_attempts"] >= 1 and summary["relocalized"] == 1
    reloc = [s for s in statuses if s.pose_source == "relocalized"]
    assert len(reloc) == 1 and "relocalised" in reloc[0].events
    same_view = order[reloc[0].index]  # the first-pass frame with the same true pose
    path = sum(np.linalg.norm(first_pass_T[k + 1][:3, 3] - first_pass_T[k][:3, 3])
               for k in range(first_pass - 1) if first_pass_T[k] is not None)
    err = np.linalg.norm(reloc[0].T_WC[:3, 3] - first_pass_T[same_view][:3, 3])
    assert err <= 0.01 * path, f"relocalised {err:.3f} from the first-pass pose (path {path:.3f})"


# ----------------------------------------------------------------------------------- proximity
def _accepted_pairs_are_true_revisits(pairs, seq):
    T = seq.camera_poses(np.arange(seq.cfg.frames) / RATE_HZ)
    for q, c in pairs:
        assert (q - c) / RATE_HZ >= MIN_GAP_S, (q, c)
        assert np.linalg.norm(T[q][:3, 3] - T[c][:3, 3]) <= REVISIT_M, (q, c)


def test_proximity_loop_closed_at_the_return_and_cuts_ate(room, runs):
    _, seq = room
    prox, off = runs["proximity"], runs["off"]
    summary = prox["loop"]["proximity"]
    assert prox["loop"]["mode"] == "proximity" and "accepted_loops" not in prox["loop"]  # no classical part
    assert summary["accepted"] >= 1 and summary["global_ba_runs"] >= summary["accepted"]
    assert summary["queries"] > 0 and summary["stored_keyframes"] > 0 and summary["global_ba_s"] > 0
    accepted = [(q, c) for q, c, status in summary["loop_frames"] if status == "accepted"]
    assert len(accepted) == summary["accepted"]
    _accepted_pairs_are_true_revisits(accepted, seq)
    ate_prox, ate_off = prox["evaluation"]["ate"]["rmse"], off["evaluation"]["ate"]["rmse"]
    assert prox["frames_with_pose"] == off["frames_with_pose"]
    assert ate_prox <= 0.4 * ate_off, f"proximity ATE {ate_prox:.4f} m vs {ate_off:.4f} m without loop closure"
    assert prox["stage_s"]["proximity"] > 0


@pytest.fixture(scope="module")
def prox_frontend(room, runs):
    """The PatchFrontend that ran over the clip with proximity loop closure (the runner's proximity
    run, finished), for its state, the true camera poses of the frames, and its loop service (the
    port the run's system connected)."""
    _, seq = room
    fe = runs["proximity_frontend"]
    assert isinstance(fe, PatchFrontend)
    return fe, seq.camera_poses(np.arange(seq.cfg.frames) / RATE_HZ), fe.loops


def test_proximity_loop_edges_join_the_inactive_store(prox_frontend):
    fe, _, service = prox_frontend
    store = fe.inactive_edges()
    first = min(service.proximity_loops, key=lambda rec: rec[0])
    q_fid, c_fid, status = first
    assert status == "accepted"
    loop = (store["src"] == c_fid) | (store["tgt"] == c_fid)
    loop &= np.abs(store["src"] - store["tgt"]) > fe.config.proximity.min_gap
    assert loop.sum() >= fe.config.proximity.min_loop_edges
    assert service.closer is None and service.summary()["mode"] == "proximity"


def test_wrong_proximity_candidate_is_rejected_by_verification(prox_frontend):
    """A candidate on the far side of the room (no shared view) gets no verified loop edges."""
    fe, T_gt, service = prox_frontend
    q = fe.graph.frames[len(fe.graph) // 2]
    if q.features is None:  # the newest graph frames keep their source features
        q = next(f for f in reversed(fe.graph.frames) if f.features is not None)
    stored = [fid for fid in fe._prox_store.order if fid in fe._prox_store]
    index = {f.fid: f.index for f in list(fe._final.values()) + fe.graph.frames}
    axis = lambda i: T_gt[i][:3, 2]
    far = min(stored, key=lambda fid: float(axis(index[fid]) @ axis(q.index)))  # most opposite view
    assert float(axis(index[far]) @ axis(q.index)) < 0
    assert fe.contributor.long_range_edges(q.fid, far) is None


def test_inconsistent_loop_edges_are_undone(prox_frontend):
    """Loop edges whose observations are random pixels: the global BA keeps too few of them, so its
    result is discarded and the map is unchanged."""
    fe, _, service = prox_frontend
    rng = np.random.default_rng(0)
    a, b = fe.graph.frames[0], fe.graph.frames[-1]
    n = fe.config.graph.patches_per_frame
    fake = {"src": np.full(n, a.fid), "patch": np.arange(n), "tgt": np.full(n, b.fid), "right": np.zeros(n, bool),
            "uv_src": a.uv.astype(np.float32),
            "uv": np.stack([rng.uniform(0, fe.state.width, n), rng.uniform(0, fe.state.height, n)], 1).astype(np.float32),
            "confidence": np.ones(n, np.float32), "inv_depth": a.inv_depth.astype(np.float32)}
    before = {f.fid: f.T_WC.copy() for f in fe.graph.frames}
    stored = fe.graph.inactive.count
    assert service.proximity_closer.run_global_ba(fake) is False
    assert all(np.array_equal(f.T_WC, before[f.fid]) for f in fe.graph.frames)
    assert fe.graph.inactive.count == stored


def test_rgbd_loop_closure_both_keeps_metric_scale(room, room_loop_rgbd_both, tmp_path):
    """RGB-D (metric map): classical corrections are SE(3) (metric closer) and the global BA holds
    every pose scale, so the SE(3)-aligned ATE improves on the run without loop closure. The run with
    loop closure (in its threads, which give the synchronous bytes) is also test_determinism's."""
    root, seq = room
    cfg = slam_config("off", sensor="rgbd")
    run_slam(open_slam_dataset(root, cfg), cfg, tmp_path / "off", progress=False)
    on, off = room_loop_rgbd_both[1], json.loads((tmp_path / "off" / SUMMARY_FILE).read_text())
    assert on["evaluation"]["align"] == off["evaluation"]["align"] == "se3"
    loop = on["loop"]
    assert loop["corrections_applied"] > 0 and loop["proximity"]["accepted"] >= 1
    accepted = [(q, c) for q, c, status in loop["proximity"]["loop_frames"] if status == "accepted"]
    _accepted_pairs_are_true_revisits(accepted, seq)
    ate_on, ate_off = on["evaluation"]["ate"]["rmse"], off["evaluation"]["ate"]["rmse"]
    assert ate_on <= 0.8 * ate_off, f"RGB-D ATE with loop closure {ate_on:.4f} m vs {ate_off:.4f} m without"


def test_global_ba_holds_keyframes_known_only_through_loop_edges():
    from fgslam.frontends.patch.proximity import held_frames

    # frames 0-1 lost their edges (store bound), 2..5 are chained, loop edges join 5 and 0
    src = np.array([2, 3, 4, 5, 0, 5])
    tgt = np.array([3, 4, 5, 4, 5, 0])
    is_loop = np.array([False, False, False, False, True, True])
    assert held_frames(6, src, tgt, is_loop, gauge=2).tolist() == [True, True, True, True, False, False]
    assert held_frames(6, src, tgt, is_loop, gauge=1).tolist() == [True, True, True, False, False, False]


def test_keyframe_store_bound_order_and_neighbours():
    from fgslam.frontends.patch.proximity import KeyframeStore

    store = KeyframeStore(capacity=3)
    for fid in (10, 12, 15, 20, 21):
        store.add(fid, f"img{fid}")
    assert store.order == [10, 12, 15, 20, 21] and store.dropped == 2 and store.last == 21
    assert 10 not in store and 12 not in store and store.get(15) == "img15" and store.get(10) is None
    assert store.ordinal(20) == 3
    assert store.neighbours(20, 2) == [15, 21]  # 12 was dropped
    assert store.neighbours(15, 1) == [20]


def test_pose_filter_and_fundamental_check():
    from fgslam.frontends.patch.proximity import fundamental_inliers, pose_filter

    def yaw(a, t):
        c, s = np.cos(np.radians(a)), np.sin(np.radians(a))
        T = np.eye(4)
        T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        T[:3, 3] = t
        return T

    cands = np.stack([yaw(5, [0.3, 0, 0]), yaw(50, [0.1, 0, 0]), yaw(0, [2.0, 0, 0])])
    ok, dist, angle = pose_filter(yaw(0, [0, 0, 0]), cands, radius=1.0, max_angle_deg=30)
    assert ok.tolist() == [True, False, False]
    assert np.allclose(dist, [0.3, 0.1, 2.0]) and np.allclose(angle, [5, 50, 0])
    rng = np.random.default_rng(0)
    X = np.stack([rng.uniform(-2, 2, 200), rng.uniform(-1, 1, 200), rng.uniform(4, 8, 200)], 1)
    K = np.array([[300, 0, 160], [0, 300, 120], [0, 0, 1.0]])
    T = yaw(8, [0.4, 0.05, 0.1])
    X_b = (X - T[:3, 3]) @ T[:3, :3]  # points in camera b (T = T_AB)
    uv_a = (X @ K.T)[:, :2] / X[:, 2:]
    uv_b = (X_b @ K.T)[:, :2] / X_b[:, 2:]
    uv_b[:40] = rng.uniform(0, 320, (40, 2))  # 20 % wrong correspondences
    inl = fundamental_inliers(uv_a, uv_b, 1.0)
    assert inl[40:].mean() > 0.95 and inl[:40].mean() < 0.2
    assert not fundamental_inliers(uv_a[:7], uv_b[:7], 1.0).any()


def test_run_report_shows_loop_counts(runs):
    from fgslam.commands.run import format_report

    classical = format_report(runs["classical"])
    loop = runs["classical"]["loop"]
    assert f"classical {loop['accepted_loops']} accepted of {loop['verified_loops']} verified" in classical
    prox = runs["proximity"]["loop"]["proximity"]
    assert f"proximity {prox['accepted']} accepted of {prox['candidates']} candidates" in format_report(runs["proximity"])
    assert "loops:" not in format_report(runs["off"])


def test_textureless_proximity_candidate_is_rejected(prox_frontend):
    """The newest frame's proximity candidate verifies with its real images; with the candidate's
    (and its neighbours') stored images blank (no texture) no loop edge survives."""
    from fgslam.frontends.patch.lk import LKFeatures

    fe, _, service = prox_frontend
    q = next(f for f in reversed(fe.graph.frames) if f.features is not None and f.fid in fe._prox_store)
    cand = fe.contributor.proximity_candidate(q.fid, service.proximity_closer.eligible_candidates(q.fid))
    assert cand is not None and fe.contributor.long_range_edges(q.fid, cand.fid) is not None
    old = [cand.fid] + fe._prox_store.neighbours(cand.fid, fe.config.proximity.old_neighbours)
    saved = {fid: fe._prox_store.get(fid) for fid in old}
    for fid, packed in saved.items():
        real = fe.source.unpack(packed)
        fe._prox_store._items[fid] = fe.source.pack(LKFeatures(np.full_like(real.image, 128), real.width, real.height))
    try:
        assert fe.contributor.long_range_edges(q.fid, cand.fid) is None
    finally:
        fe._prox_store._items.update(saved)
