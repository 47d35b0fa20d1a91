"""tools/bench_loop_scaling.py at tiny sizes: the parts run and give well-formed JSON (no timing checks)."""

import json

import numpy as np
import pytest
from tool_support import load_tool


@pytest.fixture(scope="module")
def bench():
    return load_tool("bench_loop_scaling")


def _small_ba(bench):
    return bench.BAScenarioConfig(patches_per_keyframe=12, window=3, loop_every=4)


def test_lap_trajectory_revisits_with_rigid_poses(bench):
    T_WC, lap_kf = bench.lap_trajectory(130, bench.LapConfig(), np.random.default_rng(0))
    assert T_WC.shape == (130, 4, 4) and lap_kf == 65
    R = T_WC[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    pos = T_WC[:, :3, 3]
    step = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert np.median(step) == pytest.approx(1.0, rel=0.1)
    # the second lap passes the first one within a few lap offsets; the half-lap point is far
    revisit = np.linalg.norm(pos[lap_kf:] - pos[: 130 - lap_kf], axis=1)
    assert revisit.max() < 3.0
    assert np.linalg.norm(pos[lap_kf // 2] - pos[0]) > 10.0
    # the camera looks along the direction of travel
    z = T_WC[:-1, :3, 2]
    assert np.all(np.sum(z * np.diff(pos, axis=0), axis=1) > 0.9 * step)


def test_lap_bows_keep_lap_zero_and_permute_later_laps(bench):
    from fgslam.loop.vocabulary import BowVector

    base = [BowVector(np.array([1, 5, 7], np.int32), np.array([0.2, 0.3, 0.5]), 3),
            BowVector(np.array([0, 5], np.int32), np.array([0.4, 0.6]), 2)]
    out = bench.lap_bows(base, 5, 20, np.random.default_rng(0))
    assert out[0] is base[0] and out[1] is base[1]
    for b, src in zip(out[2:], [base[0], base[1], base[0]]):
        assert np.all(np.diff(b.words) > 0) and b.weights.sum() == pytest.approx(1.0)
        assert sorted(b.weights) == sorted(src.weights)
    # one permutation per lap: word 5 (shared by both base images) maps to one word within lap 1
    assert set(out[2].words[out[2].weights == 0.3]) == set(out[3].words[out[3].weights == 0.6])


def test_retrieval_part(bench):
    report = bench.run_retrieval([12, 30], n_images=3, seed=0)
    json.dumps(report)
    assert [e["keyframes"] for e in report["sizes"]] == [12, 30]
    for e in report["sizes"]:
        assert e["process_per_keyframe"]["count"] == e["keyframes"]
        assert sum(e["status_counts"].values()) == e["keyframes"]
        assert 0 < e["process_per_keyframe"]["mean_ms"] <= e["process_per_keyframe"]["max_ms"]
        assert len(e["load_average_before"]) == 3
    assert report["describe_per_image"]["count"] == 3


def test_pose_graph_part(bench):
    entry = bench.bench_pose_graph(120, 0, bench.LapConfig(), loop_every=5)
    json.dumps(entry)
    assert entry["keyframes"] == 120 and entry["true_loops"] > 0
    assert entry["true_accepted"] > 0 and entry["solve_time_s"] > 0
    assert entry["ate_after_m"] < entry["ate_before_m"]


def test_ba_problem_is_consistent(bench):
    cfg = _small_ba(bench)
    scn = bench.make_ba_problem(110, cfg, seed=1)
    P, n = cfg.patches_per_keyframe, 110
    assert scn.T_WC.shape == (n, 4, 4) and scn.inv_depth.shape == (n * P,)
    assert scn.fixed.sum() == cfg.fixed_keyframes
    np.testing.assert_array_equal(scn.T_WC[scn.fixed], scn.T_WC_true[scn.fixed])
    np.testing.assert_array_equal(scn.struct_idx // P, scn.src)  # each patch belongs to its source frame
    assert np.all(scn.src != scn.tgt)
    far = np.abs(scn.src - scn.tgt) > cfg.window
    assert far.sum() == scn.n_loop_edges > 0
    # true projections are in the image; the noisy observations fit the truth at the noise level
    uv, z = bench.project_edges(scn.T_WC_true, scn.inv_depth_true, scn.src, scn.tgt, scn.uv_src,
                                scn.struct_idx, scn.K)
    assert np.all(z > cfg.min_z_m)
    assert bench.median_error_px(scn, scn.T_WC_true, scn.inv_depth_true) == pytest.approx(
        cfg.pixel_noise_px * np.sqrt(2 * np.log(2)), rel=0.15)  # median of a 2D Gaussian norm
    assert np.all((uv >= 0) & (uv < [cfg.width, cfg.height]))
    assert bench.reprojection_rms(scn, scn.T_WC_true, scn.inv_depth_true) == pytest.approx(cfg.pixel_noise_px, rel=0.1)
    assert bench.reprojection_rms(scn, scn.T_WC, scn.inv_depth) > 3 * cfg.pixel_noise_px


def test_global_ba_part_in_process(bench):
    pytest.importorskip("fgslam.backend.global_ba")
    entry = bench.bench_global_ba(110, 0, _small_ba(bench))
    json.dumps(entry)
    assert entry["linear_solver"] == "gtsam"
    assert entry["edges"] > 0 and entry["iterations"] >= entry["linearizations"] >= 1
    assert entry["cpu_s"] > 0 and entry["solve_s_per_step"] > 0 and entry["construct_s_per_linearization"] > 0
    assert entry["rms_px_final"] < entry["rms_px_start"]
    assert entry["rms_px_final_inliers"] < 2 * entry["pixel_noise_px"]


def test_global_ba_child_failure_is_recorded(bench):
    entry = bench.run_global_ba_isolated(100, 0, threads=1, timeout_s=0.5, memory_gb=6.0)
    json.dumps(entry)
    assert entry["keyframes"] == 100 and entry["status"].startswith("stopped after")


def test_main_prints_one_json_document(bench, capsys):
    argv = ["--keyframes", "60", "--parts", "pose_graph", "global_ba", "--loop-every", "5", "--in-process",
            "--ba-option", "iterations=1", "--ba-option", "robust_rounds=1"]
    assert bench.main(argv) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["pose_graph"]["sizes"][0]["keyframes"] == 60
    ba = report["global_ba"]["sizes"][0]
    assert ba["keyframes"] == 60 and ba["config"]["iterations"] == 1 and ba["config"]["robust_rounds"] == 1
    assert ba["iterations"] >= 1 and ba["edges"] > 0
    assert "load_average_end" in report and report["cpu_count"] >= 1


