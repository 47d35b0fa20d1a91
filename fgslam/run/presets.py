"""YAML presets shipped inside the package (``fgslam/configs/``) and the config class each one fills.

A preset is named by its file stem; the part before the first ``_`` says which dataclass it
configures (``pgo.yaml`` -> ``PGOConfig``, ``patch_kitti_mono.yaml`` -> ``SlamConfig``: every
frontend family's name and every sensor class of the recommended presets, ``handheld_rgbd.yaml``,
``driving_mono.yaml``, ..., select the run config). Commands accept either a path to a YAML file or a
bare preset name resolved here. The presets are package data, found through
:mod:`importlib.resources`, so an installed (non-editable) fgslam finds them as well as a checkout.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from .. import frontends
from ..core.config import import_object, load_config
from ..core.errors import ConfigError

#: Package (and folder inside it) holding the preset YAML files.
PRESETS_PACKAGE = "fgslam"
PRESETS_FOLDER = "configs"

#: Preset stem prefix -> "module:Class" of the dataclass it configures (besides the run presets'
#: prefixes, :func:`run_preset_prefixes`, which all select :data:`RUN_CONFIG_CLASS`).
PRESET_CLASSES: dict[str, str] = {
    "pgo": "fgslam.run.pgo:PGOConfig",
    "eval": "fgslam.eval.trajectory:EvalConfig",
    "dataset": "fgslam.io.datasets.common:DatasetConfig",
    "synth": "fgslam.io.synth.scenarios:SynthConfig",
    "map": "fgslam.backend.config:BackendConfig",
    "bow": "fgslam.loop.bow:BowConfig",
    "loop": "fgslam.loop.records:LoopClosureConfig",
    "demo": "fgslam.run.demo:DemoConfig",
    "localize": "fgslam.localize.localizer:LocalizeConfig",
}

#: The run config every frontend family's presets (``<family>_*.yaml``) and the recommended
#: presets (``<sensor class>_*.yaml``) fill.
RUN_CONFIG_CLASS = "fgslam.run.config:SlamConfig"

#: Sensor classes of the recommended presets, one preset per class and sensor (``handheld_rgbd``,
#: ``handheld_mono``, ``handheld_stereo``, ``driving_mono``, ``driving_stereo``): the family and
#: settings measured best on that class, so a user need not know which family works where.
SENSOR_CLASSES: tuple[str, ...] = ("handheld", "driving")


def run_preset_prefixes() -> tuple[str, ...]:
    """The one table of stem prefixes that select :data:`RUN_CONFIG_CLASS` (the presets of ``fgslam
    run``): the sensor classes of the recommended presets, then every frontend family's name (read
    from the registry at each call: a family registered later is included)."""
    return (*SENSOR_CLASSES, *frontends.FRONTEND_NAMES)


def configs_dir() -> Path:
    """The folder of the shipped presets, ``fgslam/configs/`` inside the installed package."""
    folder = resources.files(PRESETS_PACKAGE).joinpath(PRESETS_FOLDER)
    if not isinstance(folder, Path):  # a zipped install: the presets are not files on disk
        raise ConfigError(f"the presets ({folder}) are not files on disk; install fgslam unzipped")
    return folder


def available_presets() -> list[str]:
    folder = configs_dir()
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


#: The comment line that describes a run preset in one line (the first line of its file), read by
#: ``fgslam run --help``: what data the preset is for.
DESCRIPTION_PREFIX = "# description:"


def preset_description(path: Path) -> str:
    """The one-line description of a preset file (its ``# description:`` line among the leading
    comments), "" when it has none."""
    with open(path, encoding="utf-8") as f:
        for line in f:
            if not line.startswith("#"):
                break
            if line.startswith(DESCRIPTION_PREFIX):
                return line[len(DESCRIPTION_PREFIX):].strip()
    return ""


def run_presets() -> dict[str, str]:
    """The presets of ``fgslam run`` (a prefix of :func:`run_preset_prefixes`), name -> description:
    the recommended per-sensor-class presets first, then the families' presets, each group sorted."""
    prefixes = run_preset_prefixes()
    folder = configs_dir()
    names = [name for name in available_presets() if name.split("_", 1)[0] in prefixes]
    names.sort(key=lambda name: (name.split("_", 1)[0] not in SENSOR_CLASSES, name))
    return {name: preset_description(folder / f"{name}.yaml") for name in names}


def resolve_preset(name_or_path: str | Path) -> Path:
    """An existing YAML path as given, else the preset ``fgslam/configs/<name>.yaml`` for a bare name such as
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
    run_prefixes = run_preset_prefixes()
    target = PRESET_CLASSES.get(prefix) or (RUN_CONFIG_CLASS if prefix in run_prefixes else None)
    if target is None:
        known = sorted(set(PRESET_CLASSES) | set(run_prefixes))
        raise ConfigError(f"{path}: no config class known for preset prefix '{prefix}' ({', '.join(known)})")
    return import_object(target, f"preset prefix '{prefix}'")


def load_preset_file(path: str | Path, overrides=()):
    """Load a preset file into the dataclass its name selects."""
    path = resolve_preset(path)
    return load_config(config_class_for(path), path, overrides)
