"""The scripts of ``examples/`` run as a user runs them (their own process, small data) and say what they did."""

import subprocess
import sys

from conftest import CLIP_FRAMES

SEVEN_SCENES = "7scenes_redkitchen_0-599"
FRAMES = 30


def run_example(repo_root, name, *args):
    proc = subprocess.run([sys.executable, str(repo_root / "examples" / name), *map(str, args)],
                          capture_output=True, text=True, timeout=300, cwd=repo_root)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    return proc.stdout


def test_dataset_loop(repo_root, shared_data, tmp_path):
    out = run_example(repo_root, "dataset_loop.py", shared_data / SEVEN_SCENES, "--end", FRAMES,
                      "--out", tmp_path / "t.txt")
    assert f"{FRAMES} poses" in out
    rows = [r for r in (tmp_path / "t.txt").read_text().splitlines() if not r.startswith("#")]
    assert len(rows) == FRAMES and len(rows[0].split()) == 8  # TUM: t, position, quaternion


def test_live_camera_on_a_video_through_the_capture_path(repo_root, video_clip, tmp_path):
    out = run_example(repo_root, "live_camera.py", f"camera:{video_clip}", "--calibration",
                      video_clip.with_suffix(".yaml"), "--preset", "driving_mono", "--speed", "2",
                      "--queue", CLIP_FRAMES,  # room for every frame: poses on any machine (drops: tests/test_live.py)
                      "--out", tmp_path / "live.txt")
    poses, tracked, dropped = (int(out.split(marker)[0].split()[-1].lstrip("(")) for marker in
                               (" poses", " frames tracked", " dropped)"))
    assert poses > 0 and tracked + dropped == CLIP_FRAMES
    assert len([r for r in (tmp_path / "live.txt").read_text().splitlines() if not r.startswith("#")]) == poses


def test_custom_factor(repo_root, shared_data):
    out = run_example(repo_root, "custom_factor.py", shared_data / SEVEN_SCENES, "--end", FRAMES)
    added = int(out.split("the plugin added ")[1].split()[0])
    assert added > 0


def test_read_map(repo_root, shared_data, tmp_path):
    out = run_example(repo_root, "read_map.py", shared_data / SEVEN_SCENES, "--end", 2 * FRAMES,
                      "--map", tmp_path / "kitchen.map", "--every", 10)
    assert "saved" in out and "keyframes" in out
    found, total = (int(v) for v in out.split("localised ")[1].split(" frames")[0].split(" of "))
    assert total == 6 and found >= total // 2  # the map's own frames localise in it
