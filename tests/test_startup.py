"""Start-up: a run's config and its checks before any work import neither torch, nor
gtsam, nor OpenCV, so that a refused ``fgslam run`` answers at once. Deterministic: what is imported, not
how long it takes (each test runs a fresh interpreter)."""

import subprocess
import sys

HEAVY = ("torch", "gtsam", "cv2", "scipy", "matplotlib", "pycolmap", "numba")
# every family, and a factor plugin (the position-prior plugin of patch_mono_gps still checks its noise model
# with gtsam: not listed)
PRESETS = ("handheld_rgbd", "patch_7scenes_rgbd", "dense_7scenes_rgbd", "pointmap_7scenes_rgbd", "patch_mono_planar")


def run_python(code: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args, "-c", code], capture_output=True, text=True, timeout=120)


def test_config_and_checks_import_no_heavy_library(tmp_path):
    # what `fgslam run` does before any work: load the config (presets of every family, and the factor
    # plugins), validate it, check the output folder and the --save-map path; the dataset folder is missing
    code = f"""
import sys
from fgslam.commands.run import run
from fgslam.core.errors import FGSlamError
from fgslam.run.config import load_slam_config
from fgslam.run.prepare import check_config, check_save_map_path, prepare_output, prepare_run

for preset in {PRESETS!r}:
    config = load_slam_config(preset, ["dataset.end=10"])
    check_config(config)
for bad in (["patch.bogus=1"], ["patch.graph.optimization_window=-3"]):
    try:
        load_slam_config("handheld_rgbd", bad)
    except FGSlamError:
        pass
    else:
        raise SystemExit("no error for " + repr(bad))
prepare_output({str(tmp_path / "out")!r}, None, overwrite=False)
check_save_map_path({str(tmp_path / "out" / "x.fgmap")!r}, {str(tmp_path / "out")!r}, None, False)
try:
    prepare_run("/nonexistent/data", config, {str(tmp_path / "out2")!r})
except FGSlamError:
    pass
else:
    raise SystemExit("no error for a missing dataset")
print(",".join(m for m in {HEAVY!r} if m in sys.modules))
"""
    result = run_python(code)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "", f"imported before any work: {result.stdout.strip()}"


def test_refused_run_answers_one_line_without_torch(tmp_path):
    # -X importtime lists every module imported (on stderr, each line "import time: ... | name"); the rest of
    # stderr is the command's own output
    code = "import sys; from fgslam.cli import main; sys.exit(main())"
    argv = ["run", "handheld_rgbd", "--data", "/nonexistent/data", "--out", str(tmp_path / "out")]
    result = subprocess.run([sys.executable, "-X", "importtime", "-c", code, *argv], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode != 0
    lines = result.stderr.splitlines()
    imported = {line.rsplit("|", 1)[1].strip() for line in lines if line.startswith("import time:") and "|" in line}
    own = [line for line in lines if not line.startswith("import time:")]
    assert len(own) == 1 and own[0].startswith("fgslam: error: ") and "/nonexistent/data" in own[0], own
    assert result.stdout == ""
    assert "fgslam.run.prepare" in imported  # the check ran (the parse of importtime's output is right)
    assert not imported & set(HEAVY), sorted(imported & set(HEAVY))


def test_startup_benchmark_reports_the_refusals(tmp_path):
    # tools/bench_startup.py: every refused command exits 2 (one-line error), --help exits 0; JSON out
    import json

    from pathlib import Path

    tool = Path(__file__).resolve().parents[1] / "tools" / "bench_startup.py"
    result = subprocess.run([sys.executable, str(tool), "--repeat", "1", "--skip-compilation",
                             "--data", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["refusals"]["help"]["exit_codes"] == [0]
    for name in ("missing_data", "unknown_key", "out_of_range", "unknown_preset"):
        assert report["refusals"][name]["exit_codes"] == [2], name
        assert report["refusals"][name]["wall_s_min"] > 0
