"""tools/bench_stability.py: the perturbed copies of a sequence change the focal lengths of every
calibration format by the factor and nothing else; the pixels copy changes the camera images by one grey
level and nothing else; the old-CPU variables parse; the summary's ratio; synthetic sequences of a chosen
size and seed."""

from pathlib import Path

import numpy as np
import pytest
from tool_support import load_tool

FACTOR = 1.0 + 1e-6


@pytest.fixture(scope="module")
def bench():
    return load_tool("bench_stability")


def _numbers(text: str) -> np.ndarray:
    return np.array([float(v) for v in text.replace(":", " ").replace("[", " ").replace("]", " ").replace(",", " ").split()
                     if v.replace(".", "", 1).replace("e-", "", 1).replace("e+", "", 1).lstrip("-").isdigit()])


def _assert_scaled(original: str, perturbed: str, positions: tuple[int, ...]) -> None:
    """``perturbed`` holds the numbers of ``original``, those at ``positions`` multiplied by FACTOR."""
    expect = _numbers(original)
    expect[list(positions)] *= FACTOR
    np.testing.assert_array_equal(_numbers(perturbed), expect)


def test_seven_scenes_intrinsics_scale_fx_and_fy_only(bench, tmp_path):
    path = tmp_path / "camera-intrinsics.txt"
    path.write_text("5.85e+02 0 3.2e+02\n0 5.85e+02 2.4e+02\n0 0 1\n")
    _assert_scaled(path.read_text(), bench.perturbed_calibration(path, FACTOR), (0, 4))


def test_kitti_calib_scales_fx_fy_and_the_baseline_term(bench, tmp_path):
    path = tmp_path / "calib.txt"
    path.write_text("P0: 718.856 0 607.1928 0 0 718.856 185.2157 0 0 0 1 0\n"
                    "P1: 718.856 0 607.1928 -386.1448 0 718.856 185.2157 0 0 0 1 0\n")
    lines = bench.perturbed_calibration(path, FACTOR).splitlines()
    for line, original in zip(lines, path.read_text().splitlines()):
        assert line.split(":")[0] == original.split(":")[0]
        _assert_scaled(original, line, (0, 3, 5))  # fx, fx * baseline, fy: the baseline itself is unchanged


def test_euroc_sensor_yaml_scales_the_focal_entries(bench, tmp_path):
    path = tmp_path / "sensor.yaml"
    path.write_text("sensor_type: camera\nrate_hz: 20\nresolution: [752, 480]\n"
                    "intrinsics: [458.654, 457.296, 367.215, 248.375]\n")
    out = bench.perturbed_calibration(path, FACTOR).splitlines()
    assert out[:3] == path.read_text().splitlines()[:3]
    values = [float(v) for v in out[3].split("[")[1].rstrip("]").split(",")]
    assert values == [458.654 * FACTOR, 457.296 * FACTOR, 367.215, 248.375]


def test_perturbed_copy_links_everything_but_the_calibration(bench, tmp_path):
    root = tmp_path / "seq"
    (root / "mav0" / "cam0" / "data").mkdir(parents=True)
    (root / "mav0" / "cam0" / "data" / "0.png").write_bytes(b"x")
    (root / "mav0" / "cam0" / "sensor.yaml").write_text("intrinsics: [100.0, 100.0, 50.0, 40.0]\n")
    (root / "groundtruth.txt").write_text("0 0 0 0 1 0 0 0\n")
    copy = bench.perturbed_copy(root, tmp_path / "copy", FACTOR)
    assert (copy / "groundtruth.txt").is_symlink() and (copy / "mav0" / "cam0" / "data").is_symlink()
    sensor = copy / "mav0" / "cam0" / "sensor.yaml"
    assert not sensor.is_symlink() and sensor.read_text() == f"intrinsics: [{100.0 * FACTOR!r}, {100.0 * FACTOR!r}, 50.0, 40.0]\n"


def test_pixels_copy_moves_a_tenth_of_each_camera_image_by_one_level_and_links_the_rest(bench, tmp_path):
    import cv2

    rng = np.random.default_rng(3)
    root = tmp_path / "seq"
    images = {"mav0/cam0/data/0.png": rng.integers(0, 256, (48, 64, 3), dtype=np.uint8),  # colour, and the extremes
              "image_1/000000.png": np.array([[0, 255] * 32] * 48, dtype=np.uint8),      # grey (KITTI)
              "seq-01/frame-000000.color.jpg": rng.integers(0, 256, (48, 64), dtype=np.uint8)}
    depth = rng.integers(0, 5000, (48, 64), dtype=np.uint16)
    for rel, image in {**images, "mav0/depth0/data/0.png": depth}.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(root / rel), image)
    (root / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    copy = bench.pixels_copy(root, tmp_path / "copy")
    for rel in images:
        assert not (copy / rel).is_symlink()
        image = cv2.imread(str(root / rel), cv2.IMREAD_UNCHANGED)  # as the loader decodes it (the JPEG's, lossy)
        changed = cv2.imread(str(copy / rel), cv2.IMREAD_UNCHANGED).astype(np.int16) - image  # PNG bytes: by content
        assert set(np.unique(changed)) <= {-1, 0, 1}
        share = (changed != 0).mean()  # the drawn tenth, less the steps clipped at 0 and 255 (half, on image_1)
        assert 0.4 * bench.PIXEL_SHARE < share < bench.PIXEL_SHARE + 0.02
        if "image_1" not in rel:
            assert share > bench.PIXEL_SHARE - 0.02  # 3,072 or 9,216 draws: the binomial's spread is 0.003-0.005
        assert np.all(image[changed > 0] < 255) and np.all(image[changed < 0] > 0)  # clipped, never wrapped
    assert (copy / "mav0/depth0/data/0.png").is_symlink() and (copy / "calib.txt").is_symlink()
    again = bench.pixels_copy(root, tmp_path / "again")  # seeded: the same bytes
    assert all((copy / rel).read_bytes() == (again / rel).read_bytes() for rel in images)


def test_pixels_copy_changes_a_stereo_pairs_images_differently_and_refuses_an_unknown_layout(bench, tmp_path):
    import cv2

    root = tmp_path / "seq"
    image = np.full((48, 64), 128, np.uint8)
    for cam in ("cam0", "cam1"):
        (root / "mav0" / cam / "data").mkdir(parents=True)
        assert cv2.imwrite(str(root / "mav0" / cam / "data" / "0.png"), image)
    copy = bench.pixels_copy(root, tmp_path / "copy")
    left, right = (cv2.imread(str(copy / "mav0" / cam / "data" / "0.png"), cv2.IMREAD_UNCHANGED) for cam in ("cam0", "cam1"))
    assert not np.array_equal(left, right)
    (tmp_path / "other" / "rgb").mkdir(parents=True)
    assert cv2.imwrite(str(tmp_path / "other" / "rgb" / "0.png"), image)
    with pytest.raises(RuntimeError, match="no camera image"):
        bench.pixels_copy(tmp_path / "other", tmp_path / "other_copy")


def test_old_cpu_variables_parse(bench):
    env = bench.old_cpu_env()
    assert env["ATEN_CPU_CAPABILITY"] == "default" and "OPENCV_CPU_DISABLE" in env
    assert all(k.isupper() and v for k, v in env.items())


def test_summary_ratio_and_target(bench):
    case = bench.Case("p", "d", 1.25)
    runs = [{"perturbation": "base", "ate_rmse_m": 0.10}, {"perturbation": "oldcpu", "ate_rmse_m": 0.12}]
    s = bench.summarise("c", case, runs)
    assert s["ratio"] == pytest.approx(1.2) and s["ok"] and s["median_ate_m"] == pytest.approx(0.11)
    s = bench.summarise("c", case, runs + [{"perturbation": "threads1", "ate_rmse_m": 0.2}])
    assert s["ratio"] == pytest.approx(2.0) and not s["ok"]
    assert not bench.summarise("c", case, runs + [{"perturbation": "x", "error": "failed"}])["ok"]


def test_synthetic_sequences_take_a_size_and_a_seed(bench, tmp_path, monkeypatch):
    """``synth:PRESET:FRAMES[:WxH[:SEED]]``: the render command carries the size and the seed, each spec has
    a folder of its own, and a finished render is reused."""
    calls = []

    def fake_run(cmd, **kwargs):
        calls.append(cmd)
        Path(cmd[cmd.index("--out") + 1]).mkdir()

    monkeypatch.setattr(bench.subprocess, "run", fake_run)
    plain = bench.synth_sequence("synth:street-loop:200", tmp_path, "stability")
    sized = bench.synth_sequence("synth:kitti00-drive:101:1241x376:7", tmp_path, "size")
    assert plain != sized and len(calls) == 2
    assert "--width" not in calls[0] and "--seed" not in calls[0]
    cmd = calls[1]
    assert cmd[cmd.index("--width") + 1] == "1241" and cmd[cmd.index("--height") + 1] == "376"
    assert cmd[cmd.index("--seed") + 1] == "7" and cmd[cmd.index("--frames") + 1] == "101"
    assert cmd[cmd.index("--out") + 1] == str(sized)
    bench.synth_sequence("synth:kitti00-drive:101:1241x376:7", tmp_path, "size")
    assert len(calls) == 2  # reused
