"""Typed configuration: YAML loading, overrides and error messages."""

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import pytest

from fgslam.core.config import from_dict, load_config, merge_overrides, to_dict
from fgslam.core.errors import ConfigError


@dataclass
class SolverSection:
    kind: Literal["lm", "isam2"] = "lm"
    iterations: int = 10  # test value
    tolerance: float = 1e-6  # test value
    robust_delta: Optional[float] = None


@dataclass
class RootConfig:
    name: str = "default"
    solver: SolverSection = field(default_factory=SolverSection)
    sizes: tuple[int, int] = (640, 480)
    weights: list[float] = field(default_factory=lambda: [1.0, 2.0])
    output: Path = Path("out")
    verbose: bool = False

    def validate(self) -> None:
        if self.solver.iterations <= 0:
            raise ValueError("solver.iterations must be positive")


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    return path


def test_defaults_without_file():
    cfg = load_config(RootConfig)
    assert cfg == RootConfig()


def test_yaml_sets_nested_values_and_keeps_defaults(tmp_path):
    path = write(tmp_path, "name: run1\nsolver:\n  kind: isam2\n  tolerance: 1.0e-3\nsizes: [320, 240]\n")
    cfg = load_config(RootConfig, path)
    assert cfg.name == "run1"
    assert cfg.solver.kind == "isam2"
    assert cfg.solver.tolerance == pytest.approx(1e-3)
    assert cfg.solver.iterations == 10
    assert cfg.sizes == (320, 240)
    assert isinstance(cfg.output, Path)


def test_int_is_accepted_for_float_but_not_string_for_float(tmp_path):
    cfg = load_config(RootConfig, write(tmp_path, "solver:\n  tolerance: 1\n"))
    assert isinstance(cfg.solver.tolerance, float)
    with pytest.raises(ConfigError, match=r"cfg.yaml.*'solver.tolerance'.*number"):
        load_config(RootConfig, write(tmp_path, "solver:\n  tolerance: small\n"))


def test_overrides_parse_yaml_values(tmp_path):
    path = write(tmp_path, "solver:\n  kind: isam2\n")
    cfg = load_config(RootConfig, path, ["solver.iterations=3", "verbose=true", "weights=[0.5, 1.5]"])
    assert cfg.solver.kind == "isam2"
    assert cfg.solver.iterations == 3
    assert cfg.verbose is True
    assert cfg.weights == [0.5, 1.5]
    assert load_config(RootConfig, None, ["solver.robust_delta=2.5"]).solver.robust_delta == 2.5


@pytest.mark.parametrize("text, number", [("1e-4", 1e-4), ("2E3", 2000.0), ("-5e-1", -0.5), ("+3e+2", 300.0),
                                          ("1.5e3", 1500.0), ("1.e5", 1e5), (".5e3", 500.0)])
def test_exponent_forms_yaml_reads_as_strings_are_numbers(tmp_path, text, number):
    """YAML 1.1 (PyYAML) reads 1e-4 and 1.5e3 as strings; a float field takes them as the numbers they mean, in a
    file and in an override, and a string that is no number is still refused naming the key."""
    assert load_config(RootConfig, None, [f"solver.robust_delta={text}"]).solver.robust_delta == number
    path = write(tmp_path, f"solver:\n  robust_delta: {text}\n")
    assert load_config(RootConfig, path).solver.robust_delta == number
    with pytest.raises(ConfigError, match=r"'solver.robust_delta'.*expected a number"):
        load_config(RootConfig, None, ["solver.robust_delta=1e"])
    with pytest.raises(ConfigError, match=r"'solver.robust_delta'.*finite number \(got '1e999'\)"):
        load_config(RootConfig, None, ["solver.robust_delta=1e999"])  # the error shows what was written
    with pytest.raises(ConfigError, match=r"'solver.iterations'.*expected an integer"):
        load_config(RootConfig, None, ["solver.iterations=1e3"])  # an integer field takes integers only


def test_unknown_key_in_file_names_key_and_file(tmp_path):
    path = write(tmp_path, "solver:\n  iteratons: 3\n")
    with pytest.raises(ConfigError) as info:
        load_config(RootConfig, path)
    assert "solver.iteratons" in str(info.value)
    assert str(path) in str(info.value)


def test_unknown_key_in_override_names_override():
    with pytest.raises(ConfigError, match="solver.nope"):
        load_config(RootConfig, None, ["solver.nope=1"])


def test_invalid_literal_bool_and_tuple_length(tmp_path):
    with pytest.raises(ConfigError, match=r"solver.kind.*one of"):
        load_config(RootConfig, None, ["solver.kind=gauss"])
    with pytest.raises(ConfigError, match=r"'verbose'.*true or false"):
        load_config(RootConfig, None, ["verbose=1"])
    with pytest.raises(ConfigError, match=r"'sizes'.*2 items"):
        load_config(RootConfig, write(tmp_path, "sizes: [1, 2, 3]\n"))


@dataclass
class SwitchConfig:
    mode: Literal["off", "on", "auto"] = "auto"
    answer: Literal["yes", "no", "maybe"] = "maybe"


def test_yaml_boolean_words_map_back_to_literal_options(tmp_path):
    cfg = load_config(SwitchConfig, write(tmp_path, "mode: off\nanswer: yes\n"), ["mode=on"])
    assert cfg.mode == "on" and cfg.answer == "yes"
    assert load_config(SwitchConfig, None, ["mode=off", "answer=no"]) == SwitchConfig("off", "no")
    with pytest.raises(ConfigError, match="one of"):
        load_config(RootConfig, None, ["solver.kind=true"])


def test_validate_hook_errors_are_config_errors():
    with pytest.raises(ConfigError, match="iterations must be positive"):
        load_config(RootConfig, None, ["solver.iterations=0"])


def test_bad_yaml_names_file_and_line(tmp_path):
    path = write(tmp_path, "name: a\nsolver: [unclosed\n")
    with pytest.raises(ConfigError, match=r"cfg.yaml:\d+: invalid YAML"):
        load_config(RootConfig, path)


def test_binary_file_is_named_not_a_yaml_text_file(tmp_path):
    """A binary file (an executable, random bytes) given as a config: one ConfigError naming the file,
    no UnicodeDecodeError."""
    path = tmp_path / "ls"
    path.write_bytes(b"\x7fELF\x02\x01\x01\x00" + bytes(range(256)) * 4)
    with pytest.raises(ConfigError) as info:
        load_config(RootConfig, path)
    assert str(info.value).startswith(f"{path}: not a UTF-8 YAML text file") and "\n" not in str(info.value)


def test_missing_file_and_non_mapping(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(RootConfig, tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(RootConfig, write(tmp_path, "- 1\n- 2\n"))


def test_malformed_override():
    with pytest.raises(ConfigError, match="section.key=value"):
        load_config(RootConfig, None, ["solver.iterations"])
    with pytest.raises(ConfigError, match="is a value"):
        merge_overrides({"name": "x"}, ["name.sub=1"])


def test_to_dict_round_trip():
    cfg = load_config(RootConfig, None, ["solver.kind=isam2", "sizes=[8, 16]"])
    assert from_dict(RootConfig, to_dict(cfg)) == cfg


def test_shipped_presets_load_from_the_package_data():
    """The presets are package data: importlib.resources lists them under fgslam/configs/, and each
    names a module config class, loads by its bare name and passes its range and validate checks."""
    from importlib import resources

    from fgslam.run.presets import available_presets, load_preset_file

    listed = sorted(p.name[: -len(".yaml")] for p in resources.files("fgslam").joinpath("configs").iterdir()
                    if p.name.endswith(".yaml"))
    for needed in ("patch_kitti_mono", "patch_mono", "patch_stereo", "patch_rgbd", "demo", "pgo", "eval",
                   "dataset", "synth", "map"):
        assert needed in listed
    assert available_presets() == listed
    for name in listed:
        config = load_preset_file(name)
        check_ranges(config, source=name)
        if hasattr(config, "validate"):
            config.validate()


def test_pyproject_ships_every_preset(repo_root):
    """Every file under fgslam/configs/ matches a package-data pattern of pyproject.toml, so a wheel
    (a non-editable install) carries it."""
    import glob

    tomllib = pytest.importorskip("tomllib")
    patterns = tomllib.loads((repo_root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["fgslam"]
    package = repo_root / "fgslam"
    shipped = {Path(p) for pattern in patterns for p in glob.glob(pattern, root_dir=package, recursive=True)}
    presets = {p.relative_to(package) for p in (package / "configs").rglob("*") if p.is_file()}
    assert presets
    assert not presets - shipped, f"presets missing from [tool.setuptools.package-data]: {sorted(presets - shipped)}"


# --------------------------------------------------------------------------------------- declared ranges

import dataclasses  # noqa: E402
import importlib  # noqa: E402
import types  # noqa: E402
import typing  # noqa: E402

import math  # noqa: E402
import re  # noqa: E402

from fgslam.core.config import MAX_COUNT, MAX_SCALAR, Range, check_ranges, field_range, ranged  # noqa: E402

#: Config dataclasses used in code but not reachable from a preset root (factor tunables, vocabulary training).
EXTRA_CONFIG_CLASSES = (
    "fgslam.io.live:LiveConfig",
    "fgslam.factors.pointmap:PointmapResidualConfig",
    "fgslam.factors.reprojection:ReprojectionConfig",
    "fgslam.factors.depth:DepthPriorConfig",
    "fgslam.factors.robust:RobustConfig",
    "fgslam.factors.visual_block:BlockConfig",
    "fgslam.factors.dense:DenseBlockConfig",
    "fgslam.frontends.dense.source:DenseSourceConfig",
    "fgslam.factors.pointmap_block:PointmapBlockConfig",
    "fgslam.frontends.pointmap.source:PointmapSourceConfig",
    "fgslam.frontends.pointmap.matching:MatchingConfig",
    "fgslam.loop.vocabulary:VocabularyTrainingConfig",
    "fgslam.loop.vlad:CentreTrainingConfig",
    "fgslam.services.plugins:PositionPriorOptions",
    "fgslam.services.plugins:PlanarMotionOptions",
    "fgslam.export.colmap:ColmapExportConfig",
    "fgslam.export.compare:CompareConfig",
    "fgslam.export.ply:PlyExportConfig",
    "fgslam.run.batch:BatchMatrix",
    "fgslam.run.batch:BatchOptions",
    "fgslam.frontends.pointmap.mix:PointmapMixOptions",
    "fgslam.nets.dba:DenseBAStepConfig",
)


def _load_class(target: str) -> type:
    module, name = target.split(":")
    return getattr(importlib.import_module(module), name)


def _config_classes() -> list[type]:
    """Every config dataclass reachable from the preset roots (fgslam/run/presets.py) and the extras."""
    from fgslam.run.presets import PRESET_CLASSES, RUN_CONFIG_CLASS

    seen: list[type] = []

    def walk(cls: type) -> None:
        if cls in seen:
            return
        seen.append(cls)
        for tp in typing.get_type_hints(cls).values():
            for t in (tp, *typing.get_args(tp)):
                if dataclasses.is_dataclass(t):
                    walk(t)

    for target in (*PRESET_CLASSES.values(), RUN_CONFIG_CLASS, *EXTRA_CONFIG_CLASSES):
        walk(_load_class(target))
    return seen


def _is_numeric(tp) -> bool:
    """int / float, Optional of them, list / tuple of them (bool is not numeric)."""
    if tp in (int, float):
        return True
    origin, args = typing.get_origin(tp), [a for a in typing.get_args(tp) if a not in (type(None), Ellipsis)]
    if origin in (typing.Union, types.UnionType, list, tuple) and args:
        return all(_is_numeric(a) for a in args)
    return False


def _has_finite_upper_bound(f: dataclasses.Field) -> bool:
    rng = field_range(f)
    upper = None if rng is None else (rng.le if rng.le is not None else rng.lt)
    return upper is not None and math.isfinite(upper)


def unranged_numeric_fields(cls: type) -> list[str]:
    """Numeric fields of ``cls`` without a ranged(...) of a finite upper bound (issue 21: every
    numeric value has one that real use never needs to exceed)."""
    hints = typing.get_type_hints(cls)
    return [f"{cls.__module__}.{cls.__name__}.{f.name}" for f in dataclasses.fields(cls)
            if _is_numeric(hints[f.name]) and not _has_finite_upper_bound(f)]


def test_every_numeric_config_field_declares_its_range():
    classes = _config_classes()
    assert len(classes) > 30  # the walk reaches the nested sections (patch.*, loop_closure.bow.*, synth presets...)
    missing = [name for cls in classes for name in unranged_numeric_fields(cls)]
    assert not missing, f"numeric config fields without ranged(..., le=...) (a finite upper bound): {missing}"


def test_the_range_walk_catches_a_missing_range():
    @dataclass
    class Probe:
        a: int = 3
        b: Optional[float] = ranged(None, gt=0, le=MAX_SCALAR)
        c: list[float] = field(default_factory=lambda: [1.0])
        d: tuple[int, int] = (1, 2)
        e: bool = True
        f: str = "x"
        g: float = ranged(1.0, gt=0)  # a range without an upper bound
        h: int = ranged(1, ge=0, lt=MAX_COUNT)

    assert [n.rsplit(".", 1)[1] for n in unranged_numeric_fields(Probe)] == ["a", "c", "d", "g"]


def test_the_walk_reaches_every_config_class_that_declares_ranges():
    """Every dataclass of fgslam/ with a ranged(...) field is reached by the walk above (from the
    preset roots or the extras), so none escapes the upper-bound test."""
    import ast

    package = Path(importlib.import_module("fgslam").__file__).parent
    walked = {f"{c.__module__}:{c.__qualname__}" for c in _config_classes()}
    walked |= {f"{b.__module__}:{b.__qualname__}" for c in _config_classes() for b in c.__mro__}  # bases
    declared = set()
    for path in package.rglob("*.py"):
        text = path.read_text()
        module = ".".join(path.relative_to(package.parent).with_suffix("").parts).removesuffix(".__init__")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef) and "ranged(" in (ast.get_source_segment(text, node) or ""):
                declared.add(f"{module}:{node.name}")
    assert not declared - walked, f"config classes the walk misses (add them to EXTRA_CONFIG_CLASSES): {sorted(declared - walked)}"


def test_every_default_lies_in_its_range():
    from fgslam.io.synth.scenarios import PRESET_NAMES, default_config

    for cls in _config_classes():
        check_ranges(cls(), source=cls.__name__)  # ConfigError naming the field otherwise
        if hasattr(cls, "validate"):
            cls().validate()
    for name in PRESET_NAMES:  # the synthetic presets' own defaults
        check_ranges(default_config(name), source=f"synth preset {name}")


#: The out-of-range values of issue 9 (override, key it must name); test_run checks them on the CLI.
ISSUE9_OUT_OF_RANGE = [
    ("patch.ba.pixel_sigma=0", "patch.ba.pixel_sigma"),
    ("patch.ba.pixel_sigma=-1", "patch.ba.pixel_sigma"),
    ("patch.lk.levels=-1", "patch.lk.levels"),
    ("patch.lk.scale=-1", "patch.lk.scale"),
    ("dataset.resize_scale=0.01", "dataset.resize_scale"),
]


@pytest.mark.parametrize("override, key", ISSUE9_OUT_OF_RANGE + [
    ("patch.graph.border=-1", "patch.graph.border"),
    ("loop_closure.pose_graph.loop_sigmas=[0.01, 0.01, 0.01, 0.1, 0.1, 0, 0.01]", "loop_closure.pose_graph.loop_sigmas"),
    ("eval.rpe_delta_meters=-2", "eval.rpe_delta_meters"),
    ("log_interval_s=0", "log_interval_s"),
])
def test_load_slam_config_rejects_out_of_range_values_naming_the_key(override, key):
    from fgslam.run.config import load_slam_config

    with pytest.raises(ConfigError, match=rf"patch_mono.yaml with overrides .*key '{key}': must be "):
        load_slam_config("patch_mono", [override])


def test_ranges_hold_for_configs_built_in_code():
    from fgslam.frontends.patch.config import BAConfig, PatchConfig

    with pytest.raises(ConfigError, match=r"key 'patch.ba.pixel_sigma': must be > 0"):
        PatchConfig(ba=BAConfig(pixel_sigma=0.0)).validate()


#: Infinite values of issue 21 that ran to a garbage trajectory with exit 0 (test_run checks them on the CLI).
ISSUE21_INFINITE = [
    ("patch.ba.pixel_sigma=.inf", "patch.ba.pixel_sigma"),
    ("dense.graph.motion_filter_flow=.inf", "dense.graph.motion_filter_flow"),
    ("map.window.lambda_factor=.inf", "map.window.lambda_factor"),
    ("imu.noise_inflation=.inf", "imu.noise_inflation"),
]

#: Values of issue 21 far beyond any real use (memory exhaustion, unkillable runs); test_run checks them on the CLI.
ISSUE21_TOO_LARGE = [
    ("dataset.resize_width=100000", "dataset.resize_width"),
    ("patch.graph.patches_per_frame=100000000", "patch.graph.patches_per_frame"),
    ("pointmap.image_width=100000", "pointmap.image_width"),
]


@pytest.mark.parametrize("override, key", ISSUE21_INFINITE + [
    ("patch.ba.pixel_sigma=-.inf", "patch.ba.pixel_sigma"),
    ("eval.time_offset=.inf", "eval.time_offset"),  # a field without a lower bound
    ("imu.gyroscope_noise_density=.inf", "imu.gyroscope_noise_density"),  # an Optional[float]
    ("loop_closure.pose_graph.loop_sigmas=[0.01, 0.01, 0.01, 0.1, 0.1, .inf, 0.01]", "loop_closure.pose_graph.loop_sigmas[5]"),
    ("patch.ba.pixel_sigma=.nan", "patch.ba.pixel_sigma"),
])
def test_infinity_and_nan_are_refused_naming_the_key(override, key):
    from fgslam.run.config import load_slam_config

    with pytest.raises(ConfigError, match=rf"key '{re.escape(key)}': must be a finite number \(got -?(inf|nan)\)"):
        load_slam_config("patch_mono", [override])


@pytest.mark.parametrize("override, key", ISSUE21_TOO_LARGE)
def test_values_beyond_any_real_use_are_refused_naming_the_key(override, key):
    from fgslam.run.config import load_slam_config

    with pytest.raises(ConfigError, match=rf"key '{key}': must be >= \d+ and <= \d+ \(got \d+\)"):
        load_slam_config("patch_mono", [override])


@pytest.mark.parametrize("override, key", [("patch.graph.patches_per_frame=1" + "0" * 400, "patch.graph.patches_per_frame"),
                                           ("patch.ba.pixel_sigma=1" + "0" * 400, "patch.ba.pixel_sigma")])
def test_integers_beyond_any_float_are_refused_naming_the_key(override, key):
    """An integer too large for a float (an OverflowError before) is a ConfigError naming the key."""
    from fgslam.run.config import load_slam_config

    with pytest.raises(ConfigError, match=rf"key '{re.escape(key)}': must be"):
        load_slam_config("patch_mono", [override])


def test_infinity_is_refused_by_every_range_also_for_configs_built_in_code():
    from fgslam.frontends.patch.config import BAConfig, PatchConfig

    for rng in (Range(), Range(gt=0), Range(ge=1), Range(ge=0, le=1)):
        assert not rng.contains(math.inf) and not rng.contains(-math.inf) and not rng.contains(math.nan)
    with pytest.raises(ConfigError, match=r"key 'patch.ba.pixel_sigma': must be > 0 and <= 1e\+06 \(got inf\)"):
        PatchConfig(ba=BAConfig(pixel_sigma=math.inf)).validate()
    with pytest.raises(ConfigError, match=r"key 'solver.tolerance': must be a finite number"):
        load_config(RootConfig, None, ["solver.tolerance=.inf"])  # an unranged float too


def test_range_text_and_limits():
    rng = field_range(next(f for f in dataclasses.fields(_load_class("fgslam.io.datasets.common:DatasetConfig"))
                           if f.name == "max_skipped_fraction"))
    assert rng.text() == ">= 0 and < 1" and rng.contains(0.0) and not rng.contains(1.0)
    assert not rng.contains(float("inf")) and not rng.contains(float("nan"))


# --------------------------------------------------------------------------------------- registered sections


def test_with_sections_adds_registered_sections_after_a_field():
    from fgslam.core.config import with_sections

    @dataclass
    class Extra:
        rate: float = ranged(2.0, gt=0)

    @dataclass
    @with_sections(lambda: {"extra": Extra, "solver": SolverSection}, after="name")
    class Root:
        name: str = "root"
        tail: int = ranged(1, ge=0)

    assert [f.name for f in dataclasses.fields(Root)] == ["name", "extra", "solver", "tail"]
    cfg = load_config(Root, None, ["extra.rate=3", "solver.iterations=4"])
    assert cfg.extra == Extra(3.0) and cfg.solver.iterations == 4 and Root().extra is not Root().extra
    assert from_dict(Root, to_dict(cfg)) == cfg
    with pytest.raises(ConfigError, match=r"key 'extra.rate': must be > 0"):
        load_config(Root, None, ["extra.rate=0"])
    with pytest.raises(ConfigError, match="unknown key 'extra.nope'"):
        load_config(Root, None, ["extra.nope=1"])
    with pytest.raises(TypeError, match="'name' is both a field and a registered section"):
        with_sections(lambda: {"name": Extra}, after="tail")(type("Clash", (), {"__annotations__": {"name": str, "tail": int}}))
    with pytest.raises(TypeError, match="no such field"):
        with_sections(lambda: {"extra": Extra}, after="missing")(type("NoAnchor", (), {"__annotations__": {"name": str}}))


def test_import_object_errors_name_what_it_is_for():
    from fgslam.core.config import import_object

    assert import_object("fgslam.core.config:import_object") is import_object
    for target, why in (("fgslam.core.config.import_object", "not of the form"), ("fgslam.nonexistent:X", "cannot import"),
                        ("fgslam.core.config:Nothing", "has no attribute 'Nothing'")):
        with pytest.raises(ConfigError, match=f"factors\\[0\\].class: .*{why}"):
            import_object(target, "factors[0].class")


def test_localize_yaml_shows_every_key_with_its_default():
    """fgslam/configs/localize.yaml says "every key is optional, defaults shown": it lists exactly the
    fields of LocalizeConfig, each with its default."""
    from importlib.resources import files

    import yaml

    from fgslam.core.config import to_dict
    from fgslam.localize.localizer import LocalizeConfig

    shown = yaml.safe_load(files("fgslam").joinpath("configs", "localize.yaml").read_text())
    assert shown == to_dict(LocalizeConfig())


def test_map_yaml_shows_every_key_with_its_default():
    """fgslam/configs/map.yaml says "every key is optional; defaults are shown": it lists exactly the
    fields of BackendConfig, each with its default."""
    from importlib.resources import files

    import yaml

    from fgslam.backend.config import BackendConfig
    from fgslam.core.config import to_dict

    shown = yaml.safe_load(files("fgslam").joinpath("configs", "map.yaml").read_text())
    assert shown == to_dict(BackendConfig())


def test_bag_only_dataset_keys_warn_for_other_loaders(tmp_path, caplog):
    """``dataset.T_BC`` / ``dataset.topics`` do nothing outside ROS bags: a warning names them."""
    import logging

    from fgslam.io.datasets.common import BagTopicsConfig, DatasetConfig

    assert DatasetConfig().warn_unused_bag_keys("folder") == []
    cfg = DatasetConfig(T_BC=[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0], topics=BagTopicsConfig(left="/cam0"))
    assert cfg.warn_unused_bag_keys("rosbag") == []
    with caplog.at_level(logging.WARNING):
        assert cfg.warn_unused_bag_keys("euroc") == ["dataset.T_BC", "dataset.topics"]
    assert "only apply to ROS bags: ignored for the euroc loader" in caplog.text


@pytest.mark.parametrize("override, section, kept", [
    # the dense family's own default of the shared flow source: aperture confidence 1.5 (the source's: 3.0)
    ("dense.source.flow.preset=medium", lambda c: c.dense.source.flow, {"aperture_gradient": 1.5}),
    ("dense.source.kind=flow", lambda c: c.dense.source.flow, {"aperture_gradient": 1.5}),
    # the pointmap family's pose flow: no warm start, full resolution (the source's: true, 0.5)
    ("pointmap.source.pose.flow.preset=fast", lambda c: c.pointmap.source.pose.flow,
     {"warm_start": False, "image_scale": 1.0}),
    ("dense.depth_align.enabled=true", lambda c: c.dense.depth_align, {"window_pairs": 4}),
])
def test_a_key_set_in_a_section_keeps_the_sections_own_defaults(override, section, kept):
    """A section whose parent sets its own defaults (a family's settings of a shared source) keeps them
    when a user sets another key of it: an override changes only what it names. Before, setting any key
    rebuilt the section from the class defaults, so a no-op override changed a run's result."""
    from fgslam.run.config import load_slam_config

    plain = section(load_slam_config("dense_rgbd"))
    changed = section(load_slam_config("dense_rgbd", overrides=[override]))
    for key, value in kept.items():
        assert getattr(plain, key) == value and getattr(changed, key) == value, key
    noop = load_slam_config("dense_rgbd", overrides=["dense.source.flow.preset=medium"])
    assert to_dict(noop) == to_dict(load_slam_config("dense_rgbd"))


def test_from_dict_starts_a_section_from_its_parents_default():
    @dataclass
    class Inner:
        a: int = 1
        b: int = 2

    @dataclass
    class Middle:
        inner: Inner = field(default_factory=lambda: Inner(b=20))
        c: int = 3

    @dataclass
    class Outer:
        middle: Middle = field(default_factory=lambda: Middle(inner=Inner(a=10, b=30), c=4))

    built = from_dict(Outer, {"middle": {"inner": {"a": 5}}})
    assert built.middle == Middle(inner=Inner(a=5, b=30), c=4)  # the parent's defaults, at every depth
    assert from_dict(Outer, {}).middle == Middle(inner=Inner(a=10, b=30), c=4)
    assert from_dict(Middle, {"inner": {"a": 7}}) == Middle(inner=Inner(a=7, b=20), c=3)
    with pytest.raises(ConfigError, match="unknown key 'middle.inner.z'"):
        from_dict(Outer, {"middle": {"inner": {"z": 1}}})
