"""Classical loop closure (fgslam.loop.closure): retrieval -> verification -> Sim(3) pose graph ->
correction, relocalisation, threading, config switches.

Scene: synthetic street-loop (seed 0, ~600 m per loop, 640x200), keyframes every 4th frame of one
loop and then every 4th frame (offset by 2 frames: the revisit views are 1.2 m off the first ones)
of the first 8 % of the loop again. Odometry: ground-truth keyframe steps with a growing scale drift
(x1.8 by the end) and a heading drift (15 deg over the run), continued from the corrected poses after
every applied correction (as a frontend would). Metric odometry (stereo / RGB-D, metric closer): the
same heading drift and a sideways drift, no scale drift."""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import pytest
from geometry_support import rigid, rot_y

from fgslam.core.config import load_config
from fgslam.core.errors import ConfigError
from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.io.trajectory import Trajectory
from fgslam.loop.closure import LoopCloser
from fgslam.loop.records import LoopClosureConfig, LoopCorrection
from fgslam.loop.verification import epipolar_mask, triangulate_pair

LOOP_FRAMES = 1000            # street-loop frames per loop (100 s at 10 Hz)
STRIDE = 4                    # frames between keyframes
REVISIT_END = 1080            # last frame (exclusive) of the return stretch
SCALE_DRIFT_TOTAL = 0.6       # log of the scale drift at the end of the run
HEADING_DRIFT_DEG = 15.0      # heading drift at the end of the run
SAME_PLACE_M = 10.0           # a loop (q, c) is true when the ground-truth cameras are this close
METRIC_LATERAL_DRIFT = 0.02   # metric odometry: sideways drift per metre driven (with the heading drift)


# ----------------------------------------------------------------------------------- fixtures

def _rotation_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


@pytest.fixture(scope="module")
def street():
    from fgslam.io.synth import SynthSequence, default_config

    cfg = default_config("street-loop")
    cfg.seed = 0
    seq = SynthSequence(cfg)
    frames = np.array(list(range(0, LOOP_FRAMES, STRIDE)) + list(range(LOOP_FRAMES + STRIDE // 2, REVISIT_END, STRIDE)))
    t = frames / cfg.camera.rate_hz
    T_gt = seq.camera_poses(t)
    images = [np.clip(seq.render_view(T).image, 0, 255).astype(np.uint8) for T in T_gt]
    n = len(frames)
    rate, yaw = SCALE_DRIFT_TOTAL / n, math.radians(HEADING_DRIFT_DEG) / n
    steps, metric_steps = [], []                 # drifted odometry steps T_Ck-1Ck (mono; metric)
    for k in range(1, n):
        D = np.linalg.inv(T_gt[k - 1]) @ T_gt[k]
        S = np.eye(4)
        S[:3, :3] = rot_y(yaw) @ D[:3, :3]
        M = S.copy()
        S[:3, 3] = math.exp(rate * (k - 1)) * D[:3, 3]
        M[:3, 3] = D[:3, 3] + METRIC_LATERAL_DRIFT * np.linalg.norm(D[:3, 3]) * np.array([1.0, 0.0, 0.0])
        steps.append(S)
        metric_steps.append(M)
    return dict(seq=seq, K=seq.K, frames=frames, t=t, T_gt=T_gt, images=images, steps=steps,
                metric_steps=metric_steps, scale_rate=rate, first_revisit=int(np.searchsorted(frames, LOOP_FRAMES)))


def _ate(street, ids, T_WC, align: str = "sim3") -> float:
    t = street["t"][ids]
    res = evaluate(Trajectory(t, street["T_gt"][ids]), Trajectory(t, rigid(np.stack(T_WC))),
                   EvalConfig(align=align, rpe_delta_meters=None))
    return float(res.ate.rmse)


def _drifted(street, ids, steps_key: str = "steps") -> list[np.ndarray]:
    poses = [street["T_gt"][ids[0]].copy()]
    for a, b in zip(ids[:-1], ids[1:]):
        step = np.eye(4)
        for k in range(a, b):
            step = step @ street[steps_key][k]
        poses.append(poses[-1] @ step)
    return poses


def _run(street, ids, config: LoopClosureConfig, blank=(), wait=True, pace_s=0.0, metric=False):
    """Feed keyframes ``ids`` (positions in the street fixture) to a closer as a frontend would:
    odometry continues from the corrected poses, corrections are applied when polled (folding the
    scale into the units of the following steps). ``wait``: wait for the worker before each poll;
    ``pace_s``: sleep between keyframes (a frontend's frame time); ``metric``: a metric closer on
    the odometry without scale drift (``metric_steps``)."""
    closer = LoopCloser(config, metric=metric)
    steps = street["metric_steps" if metric else "steps"]
    poses: list[np.ndarray] = []
    state = {"unit": 1.0}
    corrections = []

    def poll(n_added: int) -> None:
        corr = closer.poll()
        if corr is None:
            return
        new, factors = corr.apply({int(i): T for i, T in zip(ids[:n_added], poses)})
        poses[:] = [new[int(i)] for i in ids[:n_added]]
        state["unit"] *= factors[int(ids[n_added - 1])]
        corrections.append(corr)
        closer.update_poses(new)

    for pos, k in enumerate(ids):
        if pos:
            step = np.eye(4)
            for j in range(ids[pos - 1], k):
                step = step @ steps[j]
            step[:3, 3] *= state["unit"]
            poses.append(poses[-1] @ step)
        else:
            poses.append(street["T_gt"][k].copy())
        image = np.zeros_like(street["images"][k]) if k in blank else street["images"][k]
        closer.add_keyframe(int(k), float(street["t"][k]), image, street["K"], poses[-1])
        if wait:
            closer.wait_idle(timeout=120)
        elif pace_s:
            time.sleep(pace_s)
        poll(pos + 1)
    closer.close()
    poll(len(ids))
    return dict(closer=closer, poses=poses, corrections=corrections, loops=closer.loops,
                verifications=closer.verifications)


@pytest.fixture(scope="module")
def sync_run(street):
    n = len(street["frames"])
    blank = {street["first_revisit"] + 8}                 # a textureless keyframe in the revisit
    out = _run(street, list(range(n)), LoopClosureConfig(mode="classical", run_in_thread=False), blank=blank)
    out["blank"] = blank
    return out


def _gt_distance(street, q: int, c: int) -> float:
    return float(np.linalg.norm(street["T_gt"][q][:3, 3] - street["T_gt"][c][:3, 3]))


# ----------------------------------------------------------------------------------- pipeline

def test_loop_detected_at_the_return_only(street, sync_run):
    first = street["first_revisit"]
    accepted = [l for l in sync_run["loops"] if l.status == "accepted"]
    assert len(accepted) >= 5
    for v in sync_run["verifications"]:
        if v.accepted:                                    # every verified loop is a true revisit
            assert v.query_id >= first and _gt_distance(street, v.query_id, v.candidate_id) < SAME_PLACE_M
    verified_queries = sorted(v.query_id for v in sync_run["verifications"] if v.accepted)
    assert verified_queries[0] <= first + 5               # found soon after the drive returns
    # candidates far from the query (different places) reached verification and were rejected
    for v in sync_run["verifications"]:
        if _gt_distance(street, v.query_id, v.candidate_id) > 3 * SAME_PLACE_M:
            assert not v.accepted and v.reason


def test_correction_cuts_keyframe_ate(street, sync_run):
    ids = list(range(len(street["frames"])))
    ate_drift = _ate(street, ids, _drifted(street, ids))
    ate_closed = _ate(street, ids, sync_run["poses"])
    logging.getLogger(__name__).info("keyframe ATE: drift %.2f m, with loop closure %.2f m", ate_drift, ate_closed)
    assert ate_drift > 5.0
    assert ate_closed < ate_drift / 8.0
    corr = sync_run["corrections"][0]
    assert corr.n_accepted >= 2 and corr.fold_scale
    # the scale drift (x1.8 between the ends) is largely undone at the revisit
    assert max(corr.scale.values()) / min(corr.scale.values()) > 1.3


def test_blank_keyframe_gives_no_loop(sync_run):
    (blank,) = sync_run["blank"]
    for v in sync_run["verifications"]:
        assert blank not in (v.query_id, v.candidate_id)
    assert all(blank not in (l.query_id, l.candidate_id) for l in sync_run["loops"])


@pytest.fixture(scope="module")
def pair_closer(street):
    """A closer holding the start of the loop and the return (drifted poses, no pose graph)."""
    first = street["first_revisit"]
    ids = list(range(0, 14)) + [100, 101, 102] + list(range(first, first + 14))
    poses = _drifted(street, list(range(len(street["frames"]))))
    closer = LoopCloser(LoopClosureConfig(mode="classical", run_in_thread=False))
    for k in ids:
        closer.add_keyframe(k, float(street["t"][k]), street["images"][k], street["K"], poses[k],
                            neighbours=[k - 1, k + 1])
    return closer


def test_verified_sim3_matches_drifted_truth(street, pair_closer):
    first = street["first_revisit"]
    rate = street["scale_rate"]
    rot_err, t_err, n_ok = [], [], 0
    for q in range(first + 1, first + 12):
        c = int(np.argmin([_gt_distance(street, q, j) for j in range(13)]))
        v = pair_closer.verify(q, c)
        if not v.accepted:
            continue
        n_ok += 1
        G = np.linalg.inv(street["T_gt"][q]) @ street["T_gt"][c]
        sigma_q, sigma_c = math.exp(rate * (q - 0.5)), math.exp(rate * (c - 0.5))   # local units
        sR = v.T_CqCc[:3, :3]
        s = np.cbrt(np.linalg.det(sR))
        assert s == pytest.approx(sigma_q / sigma_c, rel=0.06)
        rot_err.append(_rotation_deg((sR / s).T @ G[:3, :3]))
        t_err.append(np.linalg.norm(v.T_CqCc[:3, 3] / sigma_q - G[:3, 3]))
    assert n_ok >= 6
    assert np.median(rot_err) < 1.0 and max(rot_err) < 3.0
    assert np.median(t_err) < 0.6                          # metres (units divided by the local scale)


def test_false_candidate_rejected_by_verification(street, pair_closer):
    first = street["first_revisit"]
    for q, c in ((first + 5, 101), (first + 9, 2)):         # 300 m away; 20 m along the road
        assert _gt_distance(street, q, c) > 15.0
        v = pair_closer.verify(q, c)
        assert not v.accepted and v.T_CqCc is None and v.reason


def test_relocalisation(street, sync_run):
    closer = sync_run["closer"]
    seq = street["seq"]
    frame = 402                                            # between keyframes 100 and 101
    T_gt_q = seq.camera_poses(np.array([frame / seq.cfg.camera.rate_hz]))[0]
    image = np.clip(seq.render_view(T_gt_q).image, 0, 255).astype(np.uint8)
    found = closer.relocalize(image, street["K"])
    assert found is not None
    kf, T_WC = found
    assert kf in (99, 100, 101, 102)
    T_kf = sync_run["poses"][kf]
    rel = np.linalg.inv(rigid(T_kf)) @ rigid(T_WC)        # estimated T_CkCq (keyframe units)
    rel_gt = np.linalg.inv(street["T_gt"][kf]) @ T_gt_q
    assert _rotation_deg(rel[:3, :3].T @ rel_gt[:3, :3]) < 2.0
    # position in the keyframe's units: compare directions and the local metric scale
    nxt = sync_run["poses"][kf + 1]
    unit = np.linalg.norm((np.linalg.inv(T_kf) @ nxt)[:3, 3]) / np.linalg.norm(
        (np.linalg.inv(street["T_gt"][kf]) @ street["T_gt"][kf + 1])[:3, 3])
    assert np.linalg.norm(rel[:3, 3] / unit - rel_gt[:3, 3]) < 0.5
    assert closer.relocalize(np.zeros_like(image), street["K"]) is None
    # a view the drive never had (looking backwards along the road): no relocalisation
    T_back = seq.camera_poses(np.array([500 / seq.cfg.camera.rate_hz]))[0].copy()
    T_back[:3, :3] = T_back[:3, :3] @ np.diag([-1.0, 1.0, -1.0])
    back = np.clip(seq.render_view(T_back).image, 0, 255).astype(np.uint8)
    assert closer.relocalize(back, street["K"]) is None


def test_threaded_equals_synchronous(street, sync_run):
    """Reproducible: the worker's results are taken at fixed polls, so a threaded closer that is
    never waited for gives exactly the synchronous closer's corrections and poses."""
    ids = list(range(len(street["frames"])))
    run = _run(street, ids, LoopClosureConfig(mode="classical", run_in_thread=True), blank=sync_run["blank"],
               wait=False)
    assert len(run["corrections"]) == len(sync_run["corrections"]) >= 1
    assert [(l.query_id, l.candidate_id, l.status) for l in run["loops"]] == \
        [(l.query_id, l.candidate_id, l.status) for l in sync_run["loops"]]
    np.testing.assert_array_equal(np.stack(run["poses"]), np.stack(sync_run["poses"]))


def test_threaded_concurrent_polling_corrects(street):
    """No waiting: the worker lags behind the keyframes, so corrections arrive for snapshots that
    later keyframes are not part of (moved with their nearest corrected keyframe). A solve after every
    verified loop (``solve_every=1``) makes the worker lag most."""
    ids = list(range(len(street["frames"])))
    cfg = LoopClosureConfig(mode="classical", run_in_thread=True, solve_every=1)
    run = _run(street, ids, cfg, wait=False, pace_s=0.01)
    assert run["corrections"]
    assert any(len(c.T_update) < len(ids) for c in run["corrections"])
    assert _ate(street, ids, run["poses"]) < _ate(street, ids, _drifted(street, ids)) / 5.0


def test_pose_graph_throttled_per_cluster(sync_run):
    """One return = one loop cluster: the pose graph is solved far less often than loops are verified
    (test_correction_cuts_keyframe_ate checks the result), and close() solves the last ones."""
    counts = sync_run["closer"].counts
    loops = sync_run["loops"]
    logging.getLogger(__name__).info("%d verified loops, %d pose-graph solves", len(loops), counts["pose_graph_solves"])
    assert counts["loop_clusters"] == 1
    assert 1 <= counts["pose_graph_solves"] < len(loops)
    assert all(l.status != "pending" for l in loops)            # nothing left unsolved
    assert counts["corrections"] == len(sync_run["corrections"])  # synchronous: each one polled


@pytest.fixture(scope="module")
def metric_run(street):
    ids = list(range(len(street["frames"])))
    return _run(street, ids, LoopClosureConfig(mode="classical", run_in_thread=False), metric=True)


def test_metric_closer_corrects_rigidly(street, metric_run):
    """Metric map (stereo / RGB-D): rigid loop measurements, SE(3) corrections, scale kept at 1."""
    ids = list(range(len(street["frames"])))
    ate_drift = _ate(street, ids, _drifted(street, ids, "metric_steps"), align="se3")
    ate_closed = _ate(street, ids, metric_run["poses"], align="se3")
    logging.getLogger(__name__).info("metric keyframe ATE (SE(3)-aligned): drift %.2f m, closed %.2f m",
                                     ate_drift, ate_closed)
    assert ate_drift > 5.0
    assert ate_closed < ate_drift / 5.0
    verified = [v for v in metric_run["verifications"] if v.accepted]
    assert verified and all(np.linalg.det(v.T_CqCc[:3, :3]) == pytest.approx(1.0, abs=1e-12) for v in verified)
    for v in verified:
        assert _gt_distance(street, v.query_id, v.candidate_id) < SAME_PLACE_M
    assert metric_run["corrections"] and any(c.n_accepted >= 2 for c in metric_run["corrections"])
    for corr in metric_run["corrections"]:
        assert not corr.fold_scale and all(s == 1.0 for s in corr.scale.values())
    scales = np.cbrt(np.linalg.det(np.stack(metric_run["poses"])[:, :3, :3]))
    np.testing.assert_allclose(scales, 1.0, atol=1e-9)


def test_metric_relocalisation(street, metric_run):
    """Relocalisation on a metric map gives the metric pose (no unit rescaling)."""
    seq = street["seq"]
    frame = 402                                            # between keyframes 100 and 101
    T_gt_q = seq.camera_poses(np.array([frame / seq.cfg.camera.rate_hz]))[0]
    image = np.clip(seq.render_view(T_gt_q).image, 0, 255).astype(np.uint8)
    found = metric_run["closer"].relocalize(image, street["K"])
    assert found is not None
    kf, T_WC = found
    assert np.cbrt(np.linalg.det(T_WC[:3, :3])) == pytest.approx(1.0, abs=1e-9)
    rel = np.linalg.inv(metric_run["poses"][kf]) @ T_WC
    rel_gt = np.linalg.inv(street["T_gt"][kf]) @ T_gt_q
    assert _rotation_deg(rel[:3, :3].T @ rel_gt[:3, :3]) < 2.0
    assert np.linalg.norm(rel[:3, 3] - rel_gt[:3, 3]) < 0.5      # metres


# ----------------------------------------------------------------------------------- units

def _random_sim3(rng, scale_range=(0.5, 2.0)) -> np.ndarray:
    A = rng.normal(size=(3, 3))
    Q, R = np.linalg.qr(A)
    Q *= np.sign(np.diag(R))
    if np.linalg.det(Q) < 0:
        Q[:, 0] *= -1
    T = np.eye(4)
    T[:3, :3] = rng.uniform(*scale_range) * Q
    T[:3, 3] = rng.normal(size=3)
    return T


def test_correction_apply_and_fold():
    rng = np.random.default_rng(3)
    old = {k: _random_sim3(rng) for k in (0, 2, 5)}
    new = {k: _random_sim3(rng) for k in old}
    updates = {k: new[k] @ np.linalg.inv(old[k]) for k in old}
    scale = {k: float(np.cbrt(np.linalg.det(updates[k][:3, :3]))) for k in old}
    corr = LoopCorrection(updates, scale, new, [], fold_scale=False, n_accepted=1, solve_time_s=0.0)
    for k in old:                                           # own update reproduces the new pose
        np.testing.assert_allclose(corr.apply_pose(k, old[k])[0], new[k], atol=1e-12)
    # keyframes outside the snapshot move with the nearest corrected id (ties: the older)
    assert corr.update_for(1)[0] is updates[0] and corr.update_for(4)[0] is updates[5]
    assert corr.update_for(9)[0] is updates[5] and corr.update_for(-3)[0] is updates[0]
    # rounding errors do not build up over repeated corrections: the result is a similarity
    T_noisy = old[0] + 1e-6 * rng.normal(size=(4, 4)) * np.r_[1.0, 1.0, 1.0, 0.0][:, None]
    A = corr.apply_pose(0, T_noisy)[0][:3, :3]
    A = A / np.cbrt(np.linalg.det(A))
    np.testing.assert_allclose(A.T @ A, np.eye(3), atol=1e-12)
    # a later keyframe keeps its pose relative to its corrected neighbour
    T_later = old[5] @ _random_sim3(rng)
    moved, _ = corr.apply_pose(7, T_later)
    np.testing.assert_allclose(np.linalg.inv(new[5]) @ moved, np.linalg.inv(old[5]) @ T_later, atol=1e-10)
    # folding: same rotation and translation, old scale, depth factor = the update's scale; world
    # points (pose x camera point, camera points scaled by the factor) are unchanged
    folded = LoopCorrection(updates, scale, new, [], fold_scale=True, n_accepted=1, solve_time_s=0.0)
    T_f, s = folded.apply_pose(2, old[2])
    X_C = rng.normal(size=3) + np.array([0, 0, 5.0])
    world = lambda T, X: T[:3, :3] @ X + T[:3, 3]       # noqa: E731
    np.testing.assert_allclose(world(T_f, s * X_C), world(new[2], X_C), atol=1e-10)
    assert np.cbrt(np.linalg.det(T_f[:3, :3])) == pytest.approx(np.cbrt(np.linalg.det(old[2][:3, :3])))
    # a non-keyframe anchored to keyframe 2 follows: folded anchor @ folded relative pose
    T_KF = _random_sim3(rng, (1.0, 1.0))
    T_F_new = new[2] @ T_KF
    np.testing.assert_allclose(rigid(T_f @ LoopCorrection.fold_relative(T_KF, s)), rigid(T_F_new), atol=1e-10)


def test_triangulation_and_epipolar_geometry():
    rng = np.random.default_rng(4)
    K = np.array([300.0, 300.0, 160.0, 120.0])
    T_CaCb = np.eye(4)
    T_CaCb[:3, :3] = 1.7 * np.array([[math.cos(0.1), 0, math.sin(0.1)], [0, 1, 0], [-math.sin(0.1), 0, math.cos(0.1)]])
    T_CaCb[:3, 3] = [1.0, 0.1, 0.2]
    X_a = np.column_stack([rng.uniform(-3, 3, 50), rng.uniform(-2, 2, 50), rng.uniform(4, 12, 50)])
    sR, t = T_CaCb[:3, :3], T_CaCb[:3, 3]
    X_b = (X_a - t) @ np.linalg.inv(sR).T
    proj = lambda X: np.column_stack([K[0] * X[:, 0] / X[:, 2] + K[2], K[1] * X[:, 1] / X[:, 2] + K[3]])  # noqa: E731
    uv_a, uv_b = proj(X_a), proj(X_b)
    X, ok = triangulate_pair(uv_a, uv_b, K, K, T_CaCb, 0.5, 0.5)
    assert ok.all()
    np.testing.assert_allclose(X, X_a, atol=1e-8)
    mask = epipolar_mask(uv_a, uv_b, K, K, T_CaCb, 1.0)
    assert mask.diagonal().all() and mask.mean() < 0.5
    # no parallax (pure rotation): rejected
    T_rot = T_CaCb.copy()
    T_rot[:3, 3] = 0.0
    uv_b_rot = proj(X_a @ np.linalg.inv(T_rot[:3, :3]).T)
    assert not triangulate_pair(uv_a, uv_b_rot, K, K, T_rot, 0.5, 0.5)[1].any()


def test_config_switches_and_validation(tmp_path):
    path = tmp_path / "loop.yaml"
    path.write_text("mode: both\nverification:\n  min_matches: 30\n  ransac:\n    min_inliers: 15\n")
    cfg = load_config(LoopClosureConfig, path, ["run_in_thread=false"])
    assert cfg.mode == "both" and cfg.classical and cfg.proximity and not cfg.run_in_thread
    assert cfg.verification.min_matches == 30 and cfg.verification.ransac.min_inliers == 15
    with pytest.raises(ConfigError):
        load_config(LoopClosureConfig, None, ["mode=sometimes"])
    with pytest.raises(ConfigError):
        LoopClosureConfig(mode="classical", max_candidates=0).validate()
    for field in ("solve_every", "cluster_gap"):
        with pytest.raises(ConfigError, match=field):
            load_config(LoopClosureConfig, None, [f"{field}=0"])
    for mode in ("off", "proximity"):
        closer = LoopCloser(LoopClosureConfig(mode=mode))
        assert not closer.enabled
        closer.add_keyframe(0, 0.0, np.zeros((20, 20), np.uint8), (10, 10, 10, 10), np.eye(4))
        assert closer.poll() is None and closer.relocalize(np.zeros((20, 20), np.uint8), (10, 10, 10, 10)) is None
        closer.close()
