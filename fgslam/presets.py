"""YAML presets in the repository's ``configs/`` folder and the config class each one fills.

A preset is named by its file stem; the part before the first ``_`` says which dataclass it
configures (``pgo.yaml`` -> ``PGOConfig``, ``patch_kitti_mono.yaml`` -> ``SlamConfig``...).
Commands accept either a path to a YAML file or a bare preset name resolved here.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from .config import load_config
from .errors import ConfigError

#: Preset stem prefix -> "module:Class" of the dataclass it configures.
PRESET_CLASSES: dict[str, str] = {
    "pgo": "fgslam.pgo:PGOConfig",
    "eval": "fgslam.eval:EvalConfig",
    "dataset": "fgslam.io.datasets.common:DatasetConfig",
    "synth": "fgslam.io.synth.presets:SynthConfig",
    "map": "fgslam.backend.config:BackendConfig",
    "bow": "fgslam.loop.bow:BowConfig",
    "loop": "fgslam.loop.closure:LoopClosureConfig",
    "patch": "fgslam.slam:SlamConfig",
    "demo": "fgslam.demo:DemoConfig",
}


def configs_dir() -> Path:
    """The ``configs/`` folder next to the package (a source checkout or editable install)."""
    return Path(__file__).resolve().parent.parent / "configs"


def available_presets() -> list[str]:
    folder = configs_dir()
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def resolve_preset(name_or_path: str | Path) -> Path:
    """An existing YAML path as given, else the preset ``configs/<name>.yaml`` for a bare name such as
    ``patch_kitti_mono`` (or ``patch_kitti_mono.yaml``); ConfigError listing the presets otherwise."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    if path.parent == Path("."):
        stem = path.name[: -len(path.suffix)] if path.suffix in (".yaml", ".yml") else path.name
        candidate = configs_dir() / f"{stem}.yaml"
        if candidate.is_file():
            return candidate
    raise ConfigError(
        f"config '{name_or_path}': no such file and no preset of that name "
        f"(presets in {configs_dir()}: {', '.join(available_presets()) or 'none'})"
    )


def config_class_for(path: Path) -> type:
    """The dataclass a preset file configures, from its stem prefix."""
    prefix = path.stem.split("_", 1)[0]
    target = PRESET_CLASSES.get(prefix)
    if target is None:
        raise ConfigError(f"{path}: no config class known for preset prefix '{prefix}' ({', '.join(PRESET_CLASSES)})")
    module_name, class_name = target.split(":")
    return getattr(importlib.import_module(module_name), class_name)


def load_preset_file(path: str | Path, overrides=()):
    """Load a preset file into the dataclass its name selects."""
    path = resolve_preset(path)
    return load_config(config_class_for(path), path, overrides)
