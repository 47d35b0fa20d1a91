"""The command line dispatcher."""

import subprocess
import sys
from pathlib import Path

import pytest

from fgslam.cli import COMMANDS, build_parser, main


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


def test_every_command_has_help(capsys):
    for name in COMMANDS:
        with pytest.raises(SystemExit) as info:
            main([name, "--help"])
        assert info.value.code == 0
        assert "usage: fgslam " + name in capsys.readouterr().out


def test_missing_command_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as info:
        main([])
    assert info.value.code == 2


def test_help_does_not_import_heavy_modules():
    code = (
        "import sys; from fgslam.cli import build_parser; build_parser(); "
        "heavy = [m for m in ('torch', 'gtsam', 'cv2', 'matplotlib') if m in sys.modules]; "
        "print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"building the CLI parser imported heavy modules: {out}"


def test_console_script_entry_point_runs():
    result = subprocess.run([sys.executable, "-m", "fgslam", "--version"], capture_output=True, text=True)
    assert result.returncode == 0
    assert result.stdout.startswith("fgslam ")


def test_parser_builds():
    assert build_parser().prog == "fgslam"


#: every command that reads a YAML config file the user names, and how it is named
_CONFIG_COMMANDS = {
    "run": lambda bad, d: ["run", bad, "--data", d, "--out", f"{d}/out"],
    "localize": lambda bad, d: ["localize", f"{d}/map.fgmap", "--data", d, "--out", f"{d}/out", "--config", bad],
    "batch": lambda bad, d: ["batch", bad, "--sequential"],
    "eval": lambda bad, d: ["eval", f"{d}/gt.txt", f"{d}/est.txt", "--format", "tum", "--config", bad],
    "info": lambda bad, d: ["info", d, "--config", bad],
    "pgo": lambda bad, d: ["pgo", f"{d}/graph.g2o", "--config", bad],
    "synth": lambda bad, d: ["synth", "--out", f"{d}/out", "--config", bad],
    "demo": lambda bad, d: ["demo", "--out", f"{d}/out", "--config", bad],
    "compare-colmap": lambda bad, d: ["compare-colmap", "--data", d, "--out", f"{d}/out", "--preset", bad],
}


def _image_folder(root: Path) -> Path:
    """Three textured frames with their calibration.yaml (a dataset that opens)."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(root / f"{i:04d}.png"), (rng.random((48, 64)) * 255).astype(np.uint8))
    (root / "calibration.yaml").write_text("width: 64\nheight: 48\nintrinsics: [50, 50, 32, 24]\n")
    return root


@pytest.mark.parametrize("command", sorted(_CONFIG_COMMANDS))
def test_a_binary_config_file_is_one_line_naming_it(command, tmp_path, capsys):
    """A binary file given as the config (``fgslam run /bin/ls ...``): the config errors' exit status and
    one line naming the file, not a UnicodeDecodeError traceback."""
    bad = tmp_path / "config.bin"
    bad.write_bytes(b"\x7fELF\x02\x01\x01\x00" + bytes(range(256)) * 4)
    data = tmp_path / "data"
    data.mkdir()
    _image_folder(data)
    assert main(_CONFIG_COMMANDS[command](str(bad), str(data))) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "UnicodeDecodeError" not in err
    assert err.strip().splitlines()[-1].startswith(f"fgslam: error: {bad}: not a UTF-8 YAML text file"), err
