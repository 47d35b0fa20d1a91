"""tools/bench_peers.py without ORB-SLAM3: the no-peer path, argument handling, the mapping of the
peer's stamps, the common-frames ATE, and a whole run with a fake peer script and a fake fgslam."""

import json
import os
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from tool_support import load_tool

from fgslam.eval.trajectory import EvalConfig, evaluate
from fgslam.io.trajectory import Trajectory, write_trajectory


@pytest.fixture(scope="module")
def bench():
    load_tool("bench_run")  # bench_peers imports its case table (tools/ is not a package)
    return load_tool("bench_peers")


def _curve(n: int, rate: float = 10.0) -> Trajectory:
    """A planar drive (x forward, gentle bend in y), camera looking along x, n poses at ``rate``."""
    t = np.arange(n) / rate
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = 2.5 * np.arange(n)
    T[:, 1, 3] = 8.0 * (1 - np.cos(2 * np.pi * np.arange(n) / n))
    yaw = np.arctan2(np.gradient(T[:, 1, 3]), np.gradient(T[:, 0, 3]))
    c, s = np.cos(yaw), np.sin(yaw)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    return Trajectory(t, T)


def _sim3(traj: Trajectory, scale: float, yaw: float, shift) -> Trajectory:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    T = traj.T_WC.copy()
    T[:, :3, :3] = R @ T[:, :3, :3]
    T[:, :3, 3] = scale * T[:, :3, 3] @ R.T + np.asarray(shift)
    return Trajectory(traj.timestamps.copy(), T)


# ------------------------------------------------------------------------------ no peer, arguments

def test_without_peer_it_says_how_to_create_it_and_exits_0(bench, tmp_path, monkeypatch, capsys):
    monkeypatch.delenv(bench.PEER_ENV, raising=False)
    assert bench.main([]) == 0
    out, err = capsys.readouterr()
    report = json.loads(out)
    assert "no ORB-SLAM3 peer venv" in report["skipped"]
    assert "setup.sh" in report["how_to_create_the_peer"] and "setup.sh" in err
    # a folder that is not a peer venv: named, and still exit 0
    assert bench.main(["--peer", str(tmp_path / "nothing")]) == 0
    report = json.loads(capsys.readouterr().out)
    assert str(tmp_path / "nothing") in report["skipped"] and "setup.sh" in report["how_to_create_the_peer"]


def test_peer_from_environment_and_flag(bench, tmp_path, monkeypatch):
    monkeypatch.setenv(bench.PEER_ENV, str(tmp_path / "env_peer"))
    assert bench.parse_args([]).peer == tmp_path / "env_peer"
    assert bench.parse_args(["--peer", str(tmp_path / "flag")]).peer == tmp_path / "flag"  # the flag wins


@pytest.mark.parametrize("argv", [["--sequences", "kitti00_mono,nope"], ["--sequences", ","], ["--repeats", "0"],
                                  ["--fgslam-repeats", "0"], ["--highway-frames", "1"]])
def test_bad_arguments_are_rejected(bench, argv, capsys):
    with pytest.raises(SystemExit) as exc:
        bench.parse_args(argv)
    assert exc.value.code == 2
    assert "error" in capsys.readouterr().err


def test_sequence_selection_and_commands(bench, tmp_path):
    args = bench.parse_args(["--peer", str(tmp_path), "--sequences", "highway_mono, 7scenes_rgbd", "--repeats", "5",
                             "-o", "patch.ba.iterations=3", "-o", "loop_closure.mode=off"])
    assert args.names == ["highway_mono", "7scenes_rgbd"] and args.repeats == 5
    cmd = bench.peer_command(args, "mono", tmp_path / "s.yaml", tmp_path / "seq", 201, tmp_path / "o")
    assert cmd[0] == str(tmp_path / "bin" / "python") and cmd[-1] == "--pace"
    assert cmd[cmd.index("--n") + 1] == "201" and cmd[cmd.index("--mode") + 1] == "mono"
    unpaced = bench.parse_args(["--peer", str(tmp_path), "--no-pace"])
    assert "--pace" not in bench.peer_command(unpaced, "rgbd", tmp_path / "s", tmp_path / "q", 3, tmp_path / "o")
    fg = bench.fgslam_command("patch_kitti_mono", tmp_path / "d", tmp_path / "out", args.overrides)
    assert fg[fg.index("run") + 1] == "patch_kitti_mono"
    assert [fg[i + 1] for i, a in enumerate(fg) if a == "-o"] == ["patch.ba.iterations=3", "loop_closure.mode=off"]
    # every sequence's fgslam preset exists
    from fgslam.run.config import load_slam_config

    for seq in bench.SEQUENCES.values():
        load_slam_config(seq.preset, [])


def test_generated_settings_hold_the_intrinsics(bench):
    text = bench.orbslam3_settings([368.1, 368.2, 320.0, 100.0], 640, 200, 10.0, 1500)
    assert text.startswith("%YAML:1.0\n")
    values = dict(line.split(": ", 1) for line in text.splitlines()[1:])
    assert float(values["Camera1.fx"]) == 368.1 and float(values["Camera1.fy"]) == 368.2
    assert float(values["Camera1.cy"]) == 100.0 and values["Camera.width"] == "640" and values["Camera.height"] == "200"
    assert values["Camera.fps"] == "10" and values["ORBextractor.nFeatures"] == "1500"


# ------------------------------------------------------------------------------ time mapping, ATE

def test_peer_stamps_map_to_dataset_time(bench):
    fed = np.arange(10) * 0.1                     # what the peer was fed (from 0)
    dataset_t = 1000.0 + np.arange(10) * 0.1      # fgslam's own stamps
    peer = np.array([0.0, 0.10002, 0.29999, 0.55, 0.9])  # 0.55 is between frames: dropped
    ok, t = bench.to_dataset_time(peer, fed, dataset_t)
    np.testing.assert_array_equal(ok, [True, True, True, False, True])
    np.testing.assert_allclose(t, dataset_t[[0, 1, 3, 9]])


def test_ate_only_over_frames_both_posed(bench):
    gt = _curve(100)
    # a: exact (shifted) on frames 20-99; its frames 0-19 are off by metres but b never posed them
    a_T = gt.T_WC.copy()
    a_T[:, :3, 3] += [3.0, -1.0, 0.5]
    a_T[:20, 2, 3] += 25.0
    a = Trajectory(gt.timestamps.copy(), a_T)
    # b: a similarity transform of the truth on frames 20-99 with +-0.2 m alternating height errors
    b = _sim3(gt, 0.37, 0.8, [5.0, 2.0, 1.0]).subset(np.arange(20, 100))
    b_T = b.T_WC.copy()
    b_T[:, 2, 3] += 0.37 * 0.2 * np.where(np.arange(80) % 2 == 0, 1.0, -1.0)
    b = Trajectory(b.timestamps.copy(), b_T)
    c = bench.ate_on_common_frames(gt, a, b, "sim3", 0.01)
    assert c["error"] is None and c["common_frames"] == 80
    assert c["ate_a_m"] < 1e-9                     # a's bad frames are not common
    assert c["ate_b_m"] == pytest.approx(0.2, rel=0.02)
    assert c["scale_b"] == pytest.approx(1 / 0.37, rel=0.01)
    path = np.linalg.norm(np.diff(gt.t_WC[20:], axis=0), axis=1).sum()
    assert c["path_m"] == pytest.approx(path) and c["ate_b_percent"] == pytest.approx(100 * c["ate_b_m"] / path)
    # over all of its own frames a is far off: the common-frame rule is what removes its bad frames
    assert bench.own_ate(gt, a, "sim3", 0.01) > 1.0
    # SE(3) cannot undo b's scale
    assert bench.ate_on_common_frames(gt, a, b, "se3", 0.01)["ate_b_m"] > 5.0
    # nothing in common: reported, not raised
    none = bench.ate_on_common_frames(gt, a.subset(np.arange(0, 20)), b, "sim3", 0.01)
    assert none["common_frames"] == 0 and none["ate_a_m"] is None and none["error"]


def test_frames_per_cpu_second_without_the_reader(bench):
    """Like for like beside ORB-SLAM3's runner (it decodes before timing): the reader thread's CPU is left
    out; runs without the figure (an older fgslam) are skipped, not counted as zero."""
    runs = [{"frames": 600, "cpu_s": 20.0, "read_cpu_s": 4.0}, {"frames": 600, "cpu_s": 22.0, "read_cpu_s": 2.0},
            {"frames": 600, "cpu_s": 21.0, "read_cpu_s": None}]
    assert bench._per_cpu(runs) == pytest.approx(600 / 21.0)
    assert bench._per_cpu_without_reading(runs) == pytest.approx((600 / 16.0 + 600 / 20.0) / 2)  # median of two
    assert bench._per_cpu_without_reading(runs[2:]) is None


# ------------------------------------------------------------------------------ whole run, fakes

FAKE_PEER = textwrap.dedent('''\
    """Stands in for run_orbslam3.py: writes OUT.tum from $FAKE_PEER_TUM (times in the fed base) with
    its last pose repeated for the frames after it (as ORB-SLAM3 writes lost frames), and OUT.json."""
    import argparse, json, os, shutil
    import numpy as np
    ap = argparse.ArgumentParser()
    for k in ("--mode", "--vocab", "--settings", "--seq", "--n", "--out"):
        ap.add_argument(k, required=True)
    ap.add_argument("--pace", action="store_true")
    a = ap.parse_args()
    rows = np.loadtxt(os.environ["FAKE_PEER_TUM"], ndmin=2)
    fed = np.loadtxt(os.path.join(a.seq, "times.txt")) if a.mode == "mono" else np.arange(int(a.n)) / 30.0
    assert len(fed) == int(a.n), (len(fed), a.n)
    tail = [np.concatenate([[rows[-1, 0]], rows[-1, 1:]]) for _ in range(3)]
    np.savetxt(a.out + ".tum", np.vstack([rows] + tail), fmt="%.9f")
    json.dump({"frames": int(a.n), "fps": 9.5, "cpu_s": 4.0, "online_posed": len(rows), "final_posed": len(rows) + 3,
               "states": {"OK": len(rows)}, "paced": a.pace, "settings": a.settings}, open(a.out + ".json", "w"))
''')


def _fake_peer(tmp_path: Path) -> tuple[Path, Path]:
    venv, scripts = tmp_path / "peer", tmp_path / "scripts"
    (venv / "bin").mkdir(parents=True)
    python = venv / "bin" / "python"  # a wrapper: a bare link to the venv's interpreter loses the venv
    python.write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    python.chmod(0o755)
    (venv / "orbvoc.txt").write_text("fake vocabulary\n")
    (scripts / "settings").mkdir(parents=True)
    (scripts / "run_orbslam3.py").write_text(FAKE_PEER)
    (scripts / "settings" / "kitti00-02_mono.yaml").write_text("%YAML:1.0\n")
    return venv, scripts


def test_whole_run_with_fake_peer_and_fake_fgslam(bench, shared_data, tmp_path, monkeypatch, capsys):
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset

    ds = open_slam_dataset(shared_data / "kitti00_0-199", load_slam_config("patch_kitti_mono", []))
    gt = ds.groundtruth
    t0 = float(ds.timestamps[0])
    # the peer: a similarity transform of the truth on frames 30-199, stamps in its fed base (from 0)
    peer = _sim3(gt, 0.5, -0.3, [1.0, 2.0, 3.0]).subset(np.arange(30, 200))
    peer_file = tmp_path / "peer_in.tum"
    write_trajectory(peer_file, Trajectory(peer.timestamps - t0, peer.T_WC), "tum")
    monkeypatch.setenv("FAKE_PEER_TUM", str(peer_file))
    # fgslam: the truth with a 0.3 m lateral error on every other frame, frames 0-149
    fg_T = gt.T_WC[:150].copy()
    fg_T[:, 0, 3] += 0.3 * np.where(np.arange(150) % 2 == 0, 1.0, -1.0)
    fg = Trajectory(gt.timestamps[:150].copy(), fg_T)
    calls = []

    def fake_fgslam(preset, data, out, overrides, timeout):
        calls.append((preset, Path(data).name, list(overrides)))
        return {"posed": len(fg), "frames": 200, "fps": 19.0, "cpu_s": 10.0, "error": None, "trajectory": fg}

    venv, scripts = _fake_peer(tmp_path)
    argv = ["--peer", str(venv), "--peer-scripts", str(scripts), "--data", str(shared_data), "--sequences",
            "kitti00_mono", "--repeats", "2", "--fgslam-repeats", "1", "--keep-outputs", str(tmp_path / "out"),
            "-o", "patch.ba.iterations=2"]
    assert bench.main(argv, fgslam_runner=fake_fgslam) == 0
    report = json.loads(capsys.readouterr().out)
    r = report["sequences"]["kitti00_mono"]
    assert calls == [("patch_kitti_mono", "kitti00_0-199", ["patch.ba.iterations=2"])]
    assert r["align"] == "sim3" and r["frames"] == 200 and r["orbslam3_paced"] is True
    assert r["orbslam3"]["posed"] == 170 and r["fgslam"]["posed"] == 150  # repeated last pose kept once
    assert len(r["orbslam3"]["runs"]) == 2 and len(r["common"]["pairs"]) == 2
    assert r["common"]["frames"] == 120                                  # frames 30-149
    expected_fg = evaluate(gt, fg.subset(np.arange(30, 150)), EvalConfig(align="sim3", rpe_delta_meters=None)).ate.rmse
    assert r["common"]["ate_fgslam_m"] == pytest.approx(expected_fg, rel=1e-9)
    assert 0.25 < r["common"]["ate_fgslam_m"] < 0.31
    assert r["common"]["ate_orbslam3_m"] < 1e-6
    assert r["ratios"]["fps_fgslam_over_orbslam3"] == pytest.approx(19.0 / 9.5)
    assert r["fgslam"]["frames_per_cpu_s"] == pytest.approx(20.0) and r["orbslam3"]["frames_per_cpu_s"] == 50.0
    assert r["ratios"]["frames_per_cpu_s_fgslam_over_orbslam3"] == pytest.approx(0.4)
    assert r["ratios"]["ate_fgslam_over_orbslam3"] == pytest.approx(r["common"]["ate_fgslam_m"] / r["common"]["ate_orbslam3_m"])
    # the peer got a KITTI-layout view of the stored images, linked, with stamps from 0
    view = tmp_path / "out" / "kitti00_mono" / "peer_view"
    links = sorted((view / "image_0").iterdir())
    assert len(links) == 200 and os.path.samefile(links[7], shared_data / "kitti00_0-199" / "image_0" / "000007.png")
    np.testing.assert_allclose(np.loadtxt(view / "times.txt"), ds.timestamps - t0, atol=1e-9)


def test_preset_and_baseline_tree_run_alternately(bench, shared_data, tmp_path, monkeypatch, capsys):
    """--preset runs another preset on a sequence; --baseline runs each fgslam run also on another
    source tree, alternating (and with the peer's runs), and reports the ratios to it."""
    from fgslam.run.config import load_slam_config
    from fgslam.run.prepare import open_slam_dataset

    gt = open_slam_dataset(shared_data / "kitti00_0-199", load_slam_config("patch_kitti_mono", [])).groundtruth
    t0 = float(gt.timestamps[0])
    peer_file = tmp_path / "peer_in.tum"
    write_trajectory(peer_file, Trajectory(gt.timestamps - t0, gt.T_WC), "tum")
    monkeypatch.setenv("FAKE_PEER_TUM", str(peer_file))
    shifted = gt.T_WC.copy()
    shifted[:, 0, 3] += 0.2 * np.where(np.arange(len(gt)) % 2 == 0, 1.0, -1.0)
    calls = []

    def fake_fgslam(preset, data, out, overrides, timeout, tree=None):
        calls.append((preset, None if tree is None else Path(tree).name))
        cpu = 10.0 if tree is None else 20.0  # this tree twice as fast per CPU second
        T = gt.T_WC if tree is None else shifted
        return {"posed": 200, "frames": 200, "fps": 10.0, "cpu_s": cpu, "error": None,
                "trajectory": Trajectory(gt.timestamps.copy(), T)}

    base = tmp_path / "main"
    (base / "fgslam").mkdir(parents=True)
    (base / "fgslam" / "__init__.py").write_text("")
    venv, scripts = _fake_peer(tmp_path)
    argv = ["--peer", str(venv), "--peer-scripts", str(scripts), "--data", str(shared_data), "--sequences",
            "kitti00_mono", "--repeats", "1", "--fgslam-repeats", "2", "--preset", "kitti00_mono=driving_mono",
            "--baseline", str(base)]

    def peer(*args):
        calls.append(("orbslam3", None))
        return bench.run_peer(*args)

    assert bench.main(argv, fgslam_runner=fake_fgslam, peer_runner=peer) == 0
    r = json.loads(capsys.readouterr().out)["sequences"]["kitti00_mono"]
    assert calls == [("driving_mono", None), ("driving_mono", "main"), ("orbslam3", None),
                     ("driving_mono", None), ("driving_mono", "main")]
    assert r["fgslam_preset"] == "driving_mono"
    b = r["baseline"]
    assert b["frames_per_cpu_s"] == 10.0 and len(b["runs"]) == 2
    assert b["ratios"]["frames_per_cpu_s_new_over_baseline"] == pytest.approx(2.0)
    assert b["ratios"]["ate_new_over_baseline"] < 1e-3  # this tree: the truth; the baseline: 0.2 m off
    with pytest.raises(SystemExit):
        bench.parse_args(["--baseline", str(tmp_path / "nowhere")])
    with pytest.raises(SystemExit):
        bench.parse_args(["--preset", "nosuchsequence=driving_mono"])
