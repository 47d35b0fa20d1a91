"""The public API's types: a type checker (mypy, pinned in the test extra; settings in pyproject.toml) passes on
the public modules and on the examples, which use nothing but the public names."""

import subprocess
import sys

PUBLIC_MODULES = ["fgslam/__init__.py", "fgslam/run/session.py", "fgslam/io/camera.py", "fgslam/io/live.py",
                  "fgslam/core/tracking.py", "fgslam/localize/localizer.py"]


def test_the_public_surface_and_the_examples_type_check(repo_root, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(tmp_path / "cache"), *PUBLIC_MODULES,
                           "examples"], capture_output=True, text=True, cwd=repo_root, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.startswith("Success")


def test_the_examples_use_only_public_names(repo_root):
    # an example reaching into fgslam's private modules would break when they move
    for script in sorted((repo_root / "examples").glob("*.py")):
        text = script.read_text()
        assert "from fgslam." not in text and "import fgslam." not in text, script.name
        assert "fgslam." in text, script.name
