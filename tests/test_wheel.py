"""Packaging: the wheel builds, and a non-editable install of it into a fresh venv runs ``fgslam demo``
and finds every preset and the BoW vocabulary from the installed package (not the checkout).

The wheel is built from this checkout with ``uv build --no-build-isolation`` (setuptools from the
test environment: no download at test time) and installed with ``--no-deps`` into a fresh venv
whose dependencies (gtsam, torch, ...) come from this environment's site-packages through a
``.pth`` line (copying torch's gigabytes into a second venv would make CI slow and heavy; the
editable install's finder is not a ``.pth`` of that folder's own, so it is not activated there).
Needs ``uv`` (``.ci/run`` installs it as ``python3 -m uv``); skipped with the reason otherwise.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

pytestmark = pytest.mark.wheel

REPO = Path(__file__).resolve().parents[1]
DEMO_FRAMES = 30


def _uv() -> list[str]:
    if shutil.which("uv"):
        return ["uv"]
    for python in ("python3", sys.executable):
        exe = shutil.which(python) or python
        if subprocess.run([exe, "-m", "uv", "--version"], capture_output=True).returncode == 0:
            return [exe, "-m", "uv"]
    pytest.skip("uv is not installed (.ci/run installs it with `python3 -m pip install uv`)")


def _run(cmd, **kwargs) -> subprocess.CompletedProcess:
    result = subprocess.run(cmd, capture_output=True, text=True, **kwargs)
    assert result.returncode == 0, f"{cmd} failed ({result.returncode}):\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


@pytest.fixture(scope="module")
def wheel_venv(tmp_path_factory) -> Path:
    uv = _uv()
    work = tmp_path_factory.mktemp("wheel")
    _run([*uv, "build", "-q", "--wheel", "--no-build-isolation", "--python", sys.executable, "--out-dir",
          str(work / "dist"), str(REPO)])
    wheels = list((work / "dist").glob("fgslam-*.whl"))
    assert len(wheels) == 1
    venv = work / "venv"
    _run([*uv, "venv", "-q", "--python", sys.executable, str(venv)])
    python = venv / "bin" / "python"
    _run([*uv, "pip", "install", "-q", "--no-deps", "--python", str(python), str(wheels[0])])
    site = _run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip()
    (Path(site) / "_fgslam_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return venv


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["MPLBACKEND"] = "Agg"
    return env


def test_installed_package_finds_presets_and_vocabulary(wheel_venv, tmp_path):
    code = (
        "import fgslam, pathlib\n"
        "from fgslam.run.presets import available_presets, load_preset_file, resolve_preset\n"
        "from fgslam.loop.vocabulary import default_vocabulary_path, load_vocabulary\n"
        "names = available_presets()\n"
        "for n in names: load_preset_file(resolve_preset(n))\n"
        "v = load_vocabulary(str(default_vocabulary_path()))\n"
        "print(fgslam.__file__); print(len(names)); print(default_vocabulary_path())\n"
    )
    out = _run([str(wheel_venv / "bin" / "python"), "-c", code], cwd=tmp_path, env=_env()).stdout.split("\n")
    site = str(wheel_venv)
    assert out[0].startswith(site) and "site-packages" in out[0]  # the installed copy, not the checkout
    shipped = sorted(p.stem for p in (REPO / "fgslam" / "configs").glob("*.yaml"))
    assert int(out[1]) == len(shipped)
    assert out[2].startswith(site) and out[2].endswith(".npz")


def test_installed_demo_runs(wheel_venv, tmp_path):
    result = _run([str(wheel_venv / "bin" / "fgslam"), "demo", "--out", str(tmp_path / "demo"), "--frames",
                   str(DEMO_FRAMES), "-o", "scene.width=320", "-o", "scene.height=240", "--json"], cwd=tmp_path, env=_env(), timeout=600)
    import json

    summary = json.loads(result.stdout.strip().splitlines()[-1])
    text = json.dumps(summary)
    assert "ate" in text and (tmp_path / "demo" / "run" / "summary.json").is_file()
