"""tools/bench_classes.py: the ranking that chooses the recommended presets, the degraded views of the
clips, the peer's stereo settings, and the README's preset table, which must be the one the committed
report generates, from presets that have not changed since they were measured."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tool_support import load_tool

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "docs" / "benchmarks" / "classes.json"


@pytest.fixture(scope="module")
def bench():
    load_tool("bench_run")  # bench_classes imports its data folder and repository root
    load_tool("bench_peers")
    return load_tool("bench_classes")


def _run(ate, posed=100, frames=100, speed=20.0):
    return {"ate_m": ate, "posed": posed, "frames": frames, "frames_per_cpu_s": speed}


def test_the_ranking_scores_each_case_against_its_best_and_penalises_missing_poses(bench):
    cases = {"a": {"p": _run(0.10), "q": _run(0.20), "r": _run(0.10, posed=90)},
             "b": {"p": _run(0.40), "q": _run(0.20), "r": _run(None)}}
    ranking = bench.rank_class(cases, live_floor=5.0)
    by = {r["preset"]: r for r in ranking}
    assert by["p"]["score"] == pytest.approx(np.sqrt(2.0), rel=1e-3)
    assert by["q"]["score"] == pytest.approx(np.sqrt(2.0), rel=1e-3)
    # 10 % of the frames without a pose doubles the case score; a failed run scores FAILED_SCORE
    assert by["r"]["score"] == pytest.approx(np.sqrt(2.0 * bench.FAILED_SCORE), rel=1e-3)
    assert [r["preset"] for r in ranking] == ["p", "q", "r"]  # ties broken by name: deterministic
    # ... except that the recommended preset wins a tie (a tie is not a loss)
    assert [r["preset"] for r in bench.rank_class(cases, live_floor=5.0, prefer="q")][:2] == ["q", "p"]


def test_a_candidate_below_the_live_floor_ranks_after_every_live_one(bench):
    cases = {"a": {"fast": _run(0.20, speed=20.0), "slow": _run(0.05, speed=2.0)}}
    ranking = bench.rank_class(cases, live_floor=5.0)
    assert [r["preset"] for r in ranking] == ["fast", "slow"]
    assert ranking[1]["score"] < ranking[0]["score"] and not ranking[1]["live"]


def _write_kitti(root: Path, n: int = 4) -> None:
    (root / "image_0").mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), np.full((8, 12), 100, np.uint8))
    (root / "times.txt").write_text("\n".join(str(0.1 * i) for i in range(n)) + "\n")


def test_the_brightness_view_changes_only_the_images_and_links_the_rest(bench, tmp_path):
    src = tmp_path / "seq"
    _write_kitti(src)
    view = bench.brightness_view(src, tmp_path / "view", amplitude=0.3, seed=0)
    assert (view / "times.txt").is_symlink()
    greys = [int(cv2.imread(str(view / "image_0" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)[0, 0]) for i in range(4)]
    assert not (view / "image_0" / "000000.png").is_symlink()
    assert len(set(greys)) > 1 and all(0 < g < 255 for g in greys)
    again = bench.brightness_view(src, tmp_path / "view2", amplitude=0.3, seed=0)
    assert all(np.array_equal(cv2.imread(str(view / "image_0" / f"{i:06d}.png")),
                              cv2.imread(str(again / "image_0" / f"{i:06d}.png"))) for i in range(4))


def test_each_camera_gets_its_own_exposure(bench):
    rng = np.random.default_rng(0)
    left, right = bench._gains(60, 0.3, rng, 0.0), bench._gains(60, 0.3, rng, 1.0)
    assert np.exp(np.log(left).mean()) == pytest.approx(1.0) and np.abs(np.log(left / right)).max() > 0.1


def test_the_peer_gets_a_stereo_rig_with_the_datasets_baseline(bench, tmp_path):
    from fgslam.io.calibration import Calibration

    T = np.eye(4)
    T[0, 3] = 0.54
    right = Calibration(640, 200, [400.0, 400.0, 320.0, 100.0])
    cal = Calibration(640, 200, [400.0, 400.0, 320.0, 100.0], right=right, T_CLCR=T)
    out = bench.peer_settings(cal, "stereo", 10.0, tmp_path / "s.yaml")
    text = out.read_text()
    assert "Camera2.fx: 400.000000" in text and "0.540000" in text and "Stereo.ThDepth" in text


def test_the_readme_table_is_rewritten_between_its_markers_only(bench, tmp_path):
    report = {"machine": {"cpus": 2}, "load_average_start": [1.0],
              "classes": {"handheld_rgbd": {
                  "preset": "handheld_rgbd", "who": "hand-held RGB-D",
                  "ranking": [{"preset": "handheld_rgbd", "score": 1.0}, {"preset": "patch_rgbd", "score": 1.5}],
                  "cases": {"7scenes": {"frames": 600, "fgslam": {"handheld_rgbd": _run(0.032, 600, 600)},
                                        "orbslam3": {"ate_m": 0.034, "posed": 600}}}}}}
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{bench.TABLE_BEGIN}\nold\n{bench.TABLE_END}\noutro\n")
    bench.write_readme(readme, report)
    text = readme.read_text()
    assert text.startswith("intro\n") and text.endswith("\noutro\n") and "old" not in text
    assert "`handheld_rgbd` | 1st of 2 (next: patch_rgbd, 1.50x)" in text
    assert "7scenes: 0.032 m (600/600) / 0.034 m (600/600)" in text
    readme.write_text("no markers\n")
    with pytest.raises(SystemExit, match="markers"):
        bench.write_readme(readme, report)


def test_the_readme_preset_table_is_the_committed_reports_and_each_recommended_preset_ranks_first(bench):
    report = json.loads(REPORT.read_text())
    readme = (REPO / "README.md").read_text()
    assert bench.table(report) in readme, "regenerate: tools/bench_classes.py --from docs/benchmarks/classes.json --readme README.md"
    assert set(report["classes"]) == set(bench.CLASSES)
    for name, c in report["classes"].items():
        assert c["preset"] == bench.CLASSES[name].preset
        assert c["ranking"] == bench.class_report(name, bench.CLASSES[name], c["cases"])["ranking"]  # as scored now
        assert c["ranking"][0]["preset"] == c["preset"], f"{name}: {c['ranking'][0]['preset']} ranks above {c['preset']}"
        assert c["recommended_is_best"]


def test_the_committed_report_measured_the_presets_as_they_are_now(bench):
    """A preset (or a default it takes) changed since the report: rerun the class benchmark."""
    report = json.loads(REPORT.read_text())
    stale = {p: d for p, d in report["digests"].items() if bench.config_digest(p) != d}
    assert not stale, f"presets changed since docs/benchmarks/classes.json was measured: {sorted(stale)}"


def test_the_peer_gets_the_loaders_undistorted_frames_of_a_distorted_clip(bench, tmp_path):
    from types import SimpleNamespace as NS

    frames = [NS(index=i, image=np.full((6, 8), 10 * i, np.uint8), rgb=None, image_right=None,
                 depth=np.full((6, 8), 1.5, np.float32)) for i in range(3)]

    class Clip(list):
        timestamps = np.array([5.0, 5.1, 5.2])

    view, fed = bench.undistorted_peer_view(Clip(frames), "rgbd", tmp_path)
    depth = cv2.imread(str(view / "seq-01" / "frame-000002.depth.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and int(depth[0, 0]) == 1500
    assert fed.tolist() == pytest.approx([0.0, 1 / 30, 2 / 30])
    view, fed = bench.undistorted_peer_view(Clip(frames), "mono", tmp_path)
    assert int(cv2.imread(str(view / "image_0" / "000001.png"), cv2.IMREAD_GRAYSCALE)[0, 0]) == 10
    assert fed.tolist() == pytest.approx([0.0, 0.1, 0.2])


def test_the_benchmark_page_carries_the_committed_reports_results(bench):
    report = json.loads(REPORT.read_text())
    page = (REPO / "docs" / "benchmarks" / "classes.md").read_text()
    assert bench.details(report) in page, "regenerate: tools/bench_classes.py --from docs/benchmarks/classes.json --details docs/benchmarks/classes.md"


def test_refreshing_digests_records_the_reason_and_needs_one(bench, tmp_path, capsys):
    report = json.loads(REPORT.read_text())
    report["digests"]["handheld_rgbd"] = "0" * 16  # as if measured before a config change
    path = tmp_path / "classes.json"
    path.write_text(json.dumps(report))
    assert bench.main(["--update", str(path), "--refresh-digests", "a removed key that no preset set"]) == 0
    refreshed = json.loads(path.read_text())
    assert refreshed["digests"]["handheld_rgbd"] == bench.config_digest("handheld_rgbd")
    assert refreshed["updates"][-1] == {"digests_refreshed": "a removed key that no preset set",
                                        "presets": ["handheld_rgbd"]}
    assert refreshed["classes"] == report["classes"]  # no runs, no figures changed
    for argv in (["--refresh-digests", "why"], ["--update", str(path), "--refresh-digests", " "]):
        with pytest.raises(SystemExit):
            bench.parse_args(argv)
