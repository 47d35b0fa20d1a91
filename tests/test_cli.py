"""The command line dispatcher."""

import subprocess
import sys

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
