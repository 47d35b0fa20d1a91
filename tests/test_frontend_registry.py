"""The frontend registry (fgslam/frontends/__init__.py) and the per-family sections of SlamConfig.

The registry must not import the run package (fgslam.run imports it, never the reverse), and adding a
family must be one registry entry: SlamConfig, the YAML loader, overrides, the config dump and the
preset prefixes pick the new section up without an edit.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from fgslam.core.config import to_dict
from fgslam.core.errors import ConfigError
from fgslam.frontends import FAMILIES, FRONTEND_NAMES, family_config_classes, frontend_family, make_frontend
from fgslam.frontends.patch.config import PatchConfig
from fgslam.run.config import SlamConfig, load_slam_config
from fgslam.backend import Backend, BackendConfig

REPO = Path(__file__).resolve().parents[1]


def _imported_modules(path: Path, module: str) -> set[str]:
    """Absolute names of every module ``path`` (module ``module``) imports, TYPE_CHECKING blocks included."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            names.add(prefix)
            names.update(f"{prefix}.{alias.name}" for alias in node.names)
    return names


def test_no_frontend_module_imports_the_runner():
    """Static: no module under fgslam/frontends/ imports fgslam.run, not even for type checking."""
    offenders = []
    for path in sorted((REPO / "fgslam" / "frontends").rglob("*.py")):
        module = ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
        if any(name == "fgslam.run" or name.startswith("fgslam.run.") for name in _imported_modules(path, module)):
            offenders.append(str(path.relative_to(REPO)))
    assert not offenders, f"frontend modules importing the run package fgslam.run: {offenders}"


def test_importing_the_registry_does_not_import_the_runner():
    """Importing fgslam.frontends and resolving every family's config class leaves fgslam.run unloaded."""
    code = ("import sys, fgslam.frontends as f; classes = f.family_config_classes(); "
            "print(' '.join(sorted(classes)), 'fgslam.run' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["dense", "patch", "pointmap", "False"]


def test_slam_config_sections_come_from_the_registry():
    names = [f.name for f in __import__("dataclasses").fields(SlamConfig)]
    sections = family_config_classes()
    from fgslam.frontends.dense import DenseConfig
    from fgslam.frontends.pointmap.config import PointmapConfig

    assert sections == {"patch": PatchConfig, "dense": DenseConfig, "pointmap": PointmapConfig}
    for family, cls in sections.items():
        assert family in names and isinstance(getattr(SlamConfig(), family), cls)
    # every family of the registry is implemented: each has its section
    assert {f.name for f in FAMILIES if f.config is None} == set()
    for planned in ("orb",):
        assert planned not in names
        with pytest.raises(ConfigError, match=f"unknown key '{planned}'"):
            load_slam_config("patch_mono", [f"{planned}.window=3"])
    # the frontend key accepts exactly the registry's names
    with pytest.raises(ConfigError, match=r"key 'frontend': must be one of \['patch', 'dense', 'pointmap'\]"):
        load_slam_config(None, ["frontend=orb"])
    assert FRONTEND_NAMES == ("patch", "dense", "pointmap")


def test_patch_section_keeps_its_yaml_key_overrides_and_dump(tmp_path):
    config = load_slam_config("patch_kitti_mono", ["patch.ba.iterations=3"])
    assert config.patch.ba.iterations == 3
    dumped = to_dict(config)
    assert list(dumped)[:8] == ["frontend", "sensor", "threads", "log_interval_frames", "log_interval_s",
                                "auto_align", "dataset", "patch"]  # the section sits where it always did
    assert dumped["patch"]["ba"]["iterations"] == 3
    own = tmp_path / "mine.yaml"
    own.write_text("patch:\n  graph:\n    patches_per_frame: 40\n")
    assert load_slam_config(own).patch.graph.patches_per_frame == 40
    with pytest.raises(ConfigError, match="unknown key 'patch.ba.nonsense'"):
        load_slam_config(own, ["patch.ba.nonsense=1"])


def test_make_frontend_takes_the_section_or_the_root_config():
    config = load_slam_config(None, ["patch.graph.patches_per_frame=40"])
    backend = Backend(config.map)
    from_root = make_frontend("patch", config, None, "mono", backend=backend)
    from_section = make_frontend("patch", config.patch, None, "mono", backend=backend)
    assert from_root.config is config.patch and from_section.config is config.patch
    assert from_root.backend is backend and from_section.backend is backend
    with pytest.raises(TypeError, match="must be a PatchConfig"):
        make_frontend("patch", {"graph": {}}, None, "mono", backend=Backend(BackendConfig()))
    with pytest.raises(ConfigError, match="unknown frontend 'orb'"):
        frontend_family("orb")


TOY_FAMILY = '''
from dataclasses import dataclass, field

from fgslam.core.config import ranged


@dataclass
class ToyWindow:
    size: int = ranged(4, ge=2)  # frames


@dataclass
class ToyConfig:
    gain: float = ranged(1.0, gt=0)  # a toy tunable
    window: ToyWindow = field(default_factory=ToyWindow)


def build(section, calibration, sensor_mode, backend):
    return {"section": section, "calibration": calibration, "sensor_mode": sensor_mode, "backend": type(backend).__name__}
'''

TOY_RUN = '''
import dataclasses, json, sys
from pathlib import Path

import fgslam.frontends as registry

# the one edit a new family needs: its registry entry (FRONTEND_NAMES is derived from FAMILIES)
registry.FAMILIES = registry.FAMILIES + (
    registry.FrontendFamily("toy", "a toy family", config="toy_family:ToyConfig", builder="toy_family:build"),)
registry.FRONTEND_NAMES = tuple(f.name for f in registry.FAMILIES)

from fgslam.core.config import to_dict
from fgslam.core.errors import ConfigError
from fgslam.run.config import SlamConfig, load_slam_config
from fgslam.run.presets import load_preset_file
from fgslam.backend import Backend

config = load_slam_config(sys.argv[1], ["toy.window.size=7"])
built = registry.make_frontend(config.frontend, config, "calib", config.sensor, backend=Backend(config.map))
errors = []
for bad in (["toy.nope=1"], ["toy.gain=0"]):
    try:
        load_slam_config(sys.argv[1], bad)
    except ConfigError as exc:
        errors.append(str(exc))
print(json.dumps({
    "fields": [f.name for f in dataclasses.fields(SlamConfig)],
    "gain": config.toy.gain, "size": config.toy.window.size, "patch": config.patch.ba.iterations,
    "dump": to_dict(config)["toy"],
    "built": [type(built["section"]).__name__, built["calibration"], built["sensor_mode"], built["backend"]],
    "preset_class": type(load_preset_file(sys.argv[1])).__name__,
    "errors": errors,
}))
'''


def test_a_new_family_is_one_registry_entry(tmp_path):
    """A toy family registered in FAMILIES (and nothing else) gets its SlamConfig section, YAML key,
    overrides, range checks, config dump, <family>_*.yaml preset prefix and builder call."""
    (tmp_path / "toy_family.py").write_text(textwrap.dedent(TOY_FAMILY))
    (tmp_path / "run_toy.py").write_text(textwrap.dedent(TOY_RUN))
    preset = tmp_path / "toy_indoor.yaml"
    preset.write_text("frontend: toy\nsensor: rgbd\ntoy:\n  gain: 2.5\npatch:\n  ba:\n    iterations: 2\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    proc = subprocess.run([sys.executable, str(tmp_path / "run_toy.py"), str(preset)], capture_output=True,
                          text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout)
    # family sections after dataset, in registry order (patch, dense, pointmap, then the new one)
    assert (got["fields"].index("toy") == got["fields"].index("pointmap") + 1 == got["fields"].index("dense") + 2
            == got["fields"].index("patch") + 3)
    assert (got["gain"], got["size"], got["patch"]) == (2.5, 7, 2)
    assert got["dump"] == {"gain": 2.5, "window": {"size": 7}}
    assert got["built"] == ["ToyConfig", "calib", "rgbd", "Backend"]
    assert got["preset_class"] == "SlamConfig"
    assert "unknown key 'toy.nope'" in got["errors"][0] and "key 'toy.gain': must be > 0" in got["errors"][1]
