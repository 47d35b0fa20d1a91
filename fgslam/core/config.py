"""Typed configuration: dataclasses loaded from YAML with command-line overrides.

Every tunable of fgslam lives in a dataclass field (defaults plus a one-line comment). A YAML file
in ``fgslam/configs/`` (the presets) sets some of them; ``-o section.key=value`` overrides set more. Anything that does
not fit the dataclass (an unknown key, a string where a float belongs, a value outside a ``Literal``)
is a :class:`~fgslam.core.errors.ConfigError` naming the key and where it came from. A number in
exponent notation that YAML 1.1 reads as a string (``1e-4``, ``1.5e3``) is a number for a float field.

Numeric fields declare their allowed range with :func:`ranged` (``x: float = ranged(1.0, gt=0, le=MAX_SCALAR)``);
loading rejects a value outside it, naming the key, before any work starts. A range on a list or
tuple field applies to each item. Every numeric field has a finite upper bound (one of the ``MAX_*``
constants below or a tighter one of its own): a value no real use needs to exceed, so that a typo
such as ``patches_per_frame=100000000`` is refused at load time instead of exhausting memory. Infinity
and NaN are never valid values of a numeric field.

A mapping changes only the keys it names, at every depth: the other keys of a section keep the
defaults its parent gives it (a field's ``default_factory`` may set them differently from the section
class, as a family does for a shared source), not the section class's own. A field that a section's
``__post_init__`` derives from another is carried over from that default, not derived again.

Supported field types: ``bool``, ``int``, ``float``, ``str``, ``pathlib.Path``, ``Literal[...]``,
``Optional[T]`` / ``T | None``, ``list[T]``, ``tuple[T, ...]``, ``tuple[T1, T2]``, ``dict[str, T]``
and nested dataclasses.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import math
import re
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import yaml

from .errors import ConfigError, FGSlamError

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

T = TypeVar("T")

#: Metadata key under which :func:`ranged` stores a field's :class:`Range`.
RANGE_KEY = "fgslam_range"

# Upper bounds of the numeric config fields (``ranged(..., le=MAX_...)``): each is far above any real
# use, and low enough that a typo or an absurd value is refused at load time rather than exhausting
# memory or time. A field with a tighter natural bound (a probability, an angle) declares that instead.
#: px: image widths, heights and sizes (resize targets, network input widths), and pixel
#: distances stored as integers (borders, strides, windows, disparities)
MAX_IMAGE_SIDE = 8192
#: patches (or points) tracked per frame
MAX_PATCHES_PER_FRAME = 4096
#: iterations, rounds, steps, retries of any solver or loop
MAX_ITERATIONS = 10_000
#: threads, workers, CPUs
MAX_THREADS = 1024
#: random seeds (numpy's legacy seeding accepts 32 bits)
MAX_SEED = 2**32 - 1
#: ns: a timestamp (int64 nanoseconds)
MAX_TIME_NS = 2**63 - 1
#: s: clock offsets between two sources (large enough for an epoch-to-zero offset)
MAX_TIME_OFFSET_S = 1e10
#: frame indices, frame counts and intervals in frames
MAX_FRAMES = 10_000_000
#: sliding windows of frames or keyframes (the optimised / active part of a graph)
MAX_WINDOW = 1000
#: keyframe counts, gaps and intervals in keyframes
MAX_KEYFRAMES = 100_000
#: pyramid levels (image, mip, vocabulary tree)
MAX_LEVELS = 32
#: percentages
MAX_PERCENT = 100
#: MiB of memory a config may ask for
MAX_MEMORY_MIB = 1 << 20
#: counts of features, matches, points, edges, rows
MAX_COUNT = 10_000_000
#: Levenberg-Marquardt damping values (initial, bounds)
MAX_LAMBDA = 1e16
#: any other real quantity: sigmas, thresholds, tolerances, ratios, weights, distances (px or m),
#: durations (s), rates (Hz), densities
MAX_SCALAR = 1e6
#: milliseconds per second (figures reported in ms)
MS_PER_S = 1000.0


@dataclasses.dataclass(frozen=True)
class Range:
    """Allowed interval of a numeric config field: ``ge``/``gt`` below, ``le``/``lt`` above (None: open)."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None

    def contains(self, value: float) -> bool:
        if not math.isfinite(value):  # inf and nan are never valid, bounded or not
            return False
        return ((self.ge is None or value >= self.ge) and (self.gt is None or value > self.gt)
                and (self.le is None or value <= self.le) and (self.lt is None or value < self.lt))

    def text(self) -> str:
        parts = [f"{op} {bound:g}" for op, bound in ((">=", self.ge), (">", self.gt), ("<=", self.le), ("<", self.lt))
                 if bound is not None]
        return " and ".join(parts) if parts else "finite"


def ranged(default: Any = dataclasses.MISSING, *, ge: float | None = None, gt: float | None = None,
           le: float | None = None, lt: float | None = None, default_factory: Any = dataclasses.MISSING) -> Any:
    """A dataclass field with an allowed range: ``pixel_sigma: float = ranged(1.0, gt=0)``.

    Loading (:func:`load_config`, :func:`from_dict`) rejects a value outside the range with a
    :class:`~fgslam.core.errors.ConfigError` naming the key; None passes for ``Optional`` fields, and for a
    list/tuple field every item is checked.
    """
    meta = {RANGE_KEY: Range(ge=ge, gt=gt, le=le, lt=lt)}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def field_range(f: dataclasses.Field) -> Range | None:
    """The :class:`Range` a field declared with :func:`ranged`, or None."""
    return f.metadata.get(RANGE_KEY)


def _check_range(value: object, rng: Range, key: str, source: str) -> None:
    items = value if isinstance(value, (list, tuple)) else [value]
    for item in items:
        if item is None or isinstance(item, bool) or not isinstance(item, (int, float)):
            continue
        try:
            inside = rng.contains(float(item))
        except OverflowError:  # an integer too large for a float is outside every finite range
            inside = False
        if not inside:
            raise ConfigError(f"{source}: key '{key}': must be {rng.text()} (got {value!r})")


def check_ranges(obj: DataclassInstance, prefix: str = "", source: str = "config") -> None:
    """Check every :func:`ranged` field of the dataclass instance ``obj`` and of its nested sections
    (for configs built in code, which :func:`load_config` never saw); ConfigError naming the key."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        rng = field_range(f)
        if rng is not None:
            _check_range(value, rng, prefix + f.name, source)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            check_ranges(value, f"{prefix}{f.name}.", source)


def import_object(target: str, what: str = "") -> Any:
    """The object a ``"package.module:Name"`` path names (imported on demand).

    ConfigError saying ``what`` it is for (a config key, a registry entry) when the path is malformed,
    the module does not import or has no such name."""
    where = f"{what}: " if what else ""
    module_name, sep, attr = target.partition(":")
    if not sep or not module_name or not attr:
        raise ConfigError(f"{where}'{target}' is not of the form 'package.module:Name'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"{where}cannot import module '{module_name}' of '{target}': {exc}") from exc
    obj = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ConfigError(f"{where}'{target}': module '{module_name}' has no attribute '{attr}'")
        obj = getattr(obj, part)
    return obj


def with_sections(sections: Callable[[], Mapping[str, type]], after: str) -> Callable[[type[T]], type[T]]:
    """Class decorator, placed below ``@dataclass``: adds one section field ``name: cls`` (default
    ``cls()``) per entry of ``sections()`` to the class, right after its field ``after``, so that
    a registry (the frontend families) rather than the class body says which sections exist.

    ``@dataclass`` then treats them as ordinary fields: YAML keys, ``-o name.key=value`` overrides,
    :func:`to_dict` and :func:`check_ranges` see them like any section written in the class body."""

    def add(cls: type[T]) -> type[T]:
        own = dict(cls.__dict__.get("__annotations__", {}))
        if after not in own:
            raise TypeError(f"{cls.__name__}: with_sections(after={after!r}): no such field")
        added = dict(sections())
        clash = sorted(set(added) & set(own))
        if clash:
            raise TypeError(f"{cls.__name__}: section {clash[0]!r} is both a field and a registered section")
        annotations: dict[str, object] = {}
        for name, tp in own.items():
            annotations[name] = tp
            if name == after:
                annotations.update(added)
        cls.__annotations__ = annotations
        for name, section in added.items():
            setattr(cls, name, dataclasses.field(default_factory=section))
        return cls

    return add


#: Words YAML 1.1 turns into booleans, tried in this order when a Literal field gets a boolean.
_BOOL_WORDS = {False: ("off", "no", "false"), True: ("on", "yes", "true")}
# a number in exponent notation that YAML 1.1 (PyYAML) reads as a string and YAML 1.2 and Python as a
# float: ``1e-4`` (no point), ``1.5e3`` (a point, no exponent sign); a float field takes it
_EXPONENT_NUMBER = re.compile(r"[-+]?([0-9]+\.?[0-9]*|\.[0-9]+)[eE][-+]?[0-9]+")


def _type_name(tp: object) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _convert(value: Any, tp: object, key: str, source: str, base: Any = None) -> Any:
    """Check/convert ``value`` (parsed YAML, or a value given in code) to the field type ``tp`` (a
    class or a typing form); raise ConfigError naming ``key`` and ``source``. ``base``: the field's
    default when it is a section (a mapping then changes only the keys it names)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)

    def fail(why: str) -> ConfigError:
        return ConfigError(f"{source}: key '{key}': {why} (got {value!r})")

    if tp is Any:
        return value
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise fail(f"expected a mapping for section {_type_name(tp)}")
        return _build(tp, value, source, prefix=key + ".", base=base if isinstance(base, tp) else None)
    if origin is typing.Union or origin is types.UnionType:
        if value is None:
            if type(None) in args:
                return None
            raise fail("null is not allowed")
        options = [a for a in args if a is not type(None)]
        if len(options) == 1:  # Optional[T]: T's own error (say, "must be a finite number")
            return _convert(value, options[0], key, source, base)
        errors = []
        for option in args:
            if option is type(None):
                continue
            try:
                return _convert(value, option, key, source, base)
            except ConfigError as exc:
                errors.append(str(exc))
        raise fail(f"expected {' or '.join(_type_name(a) for a in args if a is not type(None))}")
    if origin is typing.Literal:
        if isinstance(value, bool) and not any(isinstance(a, bool) for a in args):
            # YAML 1.1 reads unquoted off/on/no/yes as booleans: map them back to the option spelled so
            value = next((a for a in _BOOL_WORDS[value] if a in args), value)
        if value not in args:
            raise fail(f"must be one of {list(args)}")
        return value
    if origin in (list, Sequence) or tp is list:
        if not isinstance(value, (list, tuple)):
            raise fail("expected a list")
        item_tp = args[0] if args else Any
        return [_convert(v, item_tp, f"{key}[{i}]", source) for i, v in enumerate(value)]
    if origin is tuple or tp is tuple:
        if not isinstance(value, (list, tuple)):
            raise fail("expected a list")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{key}[{i}]", source) for i, v in enumerate(value))
        if args and len(args) != len(value):
            raise fail(f"expected {len(args)} items")
        if not args:
            return tuple(value)
        return tuple(_convert(v, a, f"{key}[{i}]", source) for i, (v, a) in enumerate(zip(value, args)))
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise fail("expected a mapping")
        val_tp = args[1] if len(args) == 2 else Any
        return {str(k): _convert(v, val_tp, f"{key}.{k}", source) for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise fail("expected true or false")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise fail("expected an integer")
        return value
    if tp is float:
        exponent = isinstance(value, str) and _EXPONENT_NUMBER.fullmatch(value.strip()) is not None
        if not exponent and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise fail("expected a number")
        try:
            number = float(value)
        except OverflowError:  # an integer beyond any float
            raise fail("must be a finite number") from None
        if not math.isfinite(number):
            raise fail("must be a finite number")
        return number
    if tp is str:
        if not isinstance(value, str):
            raise fail("expected a string")
        return value
    if tp is Path:
        if not isinstance(value, (str, Path)):
            raise fail("expected a path")
        return Path(value)
    raise ConfigError(f"{source}: key '{key}': unsupported field type {_type_name(tp)}")


def _section_default(f: dataclasses.Field, base: Any) -> Any:
    """The default a mapping given for field ``f`` starts from: ``base``'s value of it (a section inside a
    section with its own defaults), else the field's default factory's section (a family that sets its own
    defaults of a shared section, say ``dense.source.flow``); None where neither is a section."""
    if base is not None:
        value = getattr(base, f.name)
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return None
    return value if dataclasses.is_dataclass(value) else None


def _build(cls: type[T], data: Mapping[str, Any], source: str, prefix: str = "", base: Any = None) -> T:
    """``cls`` from ``data``; keys it does not name keep ``base``'s values (a section's own defaults, as its
    parent sets them) or else the class defaults."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"{source}: unknown key '{prefix}{unknown[0]}' (valid keys of {cls.__name__}: {', '.join(sorted(fields))})"
        )
    kwargs = {name: _convert(value, hints[name], prefix + name, source,
                             _section_default(fields[name], base) if isinstance(value, Mapping) else None)
              for name, value in data.items()}
    if base is not None:  # the keys not given keep the section's own defaults
        kwargs = {**{name: copy.deepcopy(getattr(base, name)) for name in fields if name not in data}, **kwargs}
    for name, value in kwargs.items():
        rng = field_range(fields[name])
        if rng is not None:
            _check_range(value, rng, prefix + name, source)
    try:
        obj = cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{source}: section '{prefix.rstrip('.') or cls.__name__}': {exc}") from exc
    validate = getattr(obj, "validate", None)
    if callable(validate):
        try:
            validate()
        except (ValueError, ConfigError) as exc:
            raise ConfigError(f"{source}: {prefix.rstrip('.') or cls.__name__}: {exc}") from exc
    return obj


def from_dict(cls: type[T], data: Mapping[str, Any] | None, source: str = "<dict>", prefix: str = "") -> T:
    """Build dataclass ``cls`` from a (nested) mapping; missing keys keep their defaults (in a nested section,
    the defaults its parent gives it). ``prefix``
    is put before every key named in errors (``"factors[0].options."`` for a section nested elsewhere)."""
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        where = f"key '{prefix.rstrip('.')}'" if prefix else "the top level"
        raise ConfigError(f"{source}: {where} must be a mapping of keys to values")
    return _build(cls, data, source, prefix=prefix)


def to_dict(obj: object) -> Any:
    """Plain-YAML/JSON form of a config dataclass (paths and tuples become strings and lists)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {str(k): to_dict(v) for k, v in obj.items()}
    if isinstance(obj, Path):
        return str(obj)
    return obj


def yaml_error_text(exc: Exception, source: str) -> str:
    """One line for a YAML syntax error: ``source:line: invalid YAML: problem (context)``, naming
    ``source`` (a file, or the ``-o`` override) where PyYAML says ``"<unicode string>"``."""
    mark = getattr(exc, "problem_mark", None)
    where = f":{mark.line + 1}" if mark is not None else ""
    problem = getattr(exc, "problem", None) or str(exc).strip().splitlines()[0]
    context = getattr(exc, "context", None)
    return f"{source}{where}: invalid YAML: {problem}" + (f" ({context})" if context else "")


#: how a YAML directive line starts (``%YAML 1.1``, or OpenCV's ``%YAML:1.0`` of EuRoC's ``sensor.yaml``, which
#: PyYAML refuses): such a line is read as blank
YAML_DIRECTIVE = "%YAML"


def read_yaml(path: str | Path, error: type[FGSlamError] = ConfigError, what: str = "config file") -> dict[str, Any]:
    """Read a YAML mapping from a UTF-8 text file (the one reader of fgslam's YAML files: configs,
    calibrations, dataset sensor files); an empty file is an empty mapping, a ``%YAML`` directive line
    is read as blank (:data:`YAML_DIRECTIVE`). Errors are one ``error`` line naming the file (``what``
    when it is missing or unreadable; the line for syntax errors; a binary or otherwise non-UTF-8 file
    is said to be one)."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{what} not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:  # a binary file (an executable, an image, random bytes) given as YAML
        raise error(f"{path}: not a UTF-8 YAML text file (byte {exc.start}: {exc.reason})") from exc
    except OSError as exc:
        raise error(f"{path}: cannot read the {what}: {exc.strerror or exc}") from exc
    text = "".join("\n" if line.startswith(YAML_DIRECTIVE) else line  # blank: line numbers kept
                   for line in text.splitlines(keepends=True))
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise error(yaml_error_text(exc, str(path))) from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise error(f"{path}: the top level must be a mapping of keys to values")
    return data


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split ``"a.b.c=value"`` into (["a", "b", "c"], parsed YAML value)."""
    if "=" not in text:
        raise ConfigError(f"override '{text}': expected the form section.key=value")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise ConfigError(f"override '{text}': empty key")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError as exc:
        raise ConfigError(yaml_error_text(exc, f"-o override '{text}' (value)")) from exc
    return key.split("."), value


def merge_overrides(data: dict[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Return a copy of ``data`` with each ``section.key=value`` override applied."""
    merged = _deep_copy(data)
    for text in overrides:
        path, value = parse_override(text)
        node = merged
        for part in path[:-1]:
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            elif not isinstance(child, dict):
                raise ConfigError(f"override '{text}': '{part}' is a value, not a section")
            node = child
        node[path[-1]] = value
    return merged


def _deep_copy(data: Any) -> Any:
    if isinstance(data, dict):
        return {k: _deep_copy(v) for k, v in data.items()}
    if isinstance(data, list):
        return [_deep_copy(v) for v in data]
    return data


def load_config(cls: type[T], path: str | Path | None = None, overrides: Sequence[str] = ()) -> T:
    """Build ``cls`` from the YAML file ``path`` (optional) and command-line ``overrides``.

    Errors name the offending key together with the file it came from, or the override text.
    """
    data: dict[str, Any] = read_yaml(path) if path is not None else {}
    source = str(path) if path is not None else "<defaults>"
    if overrides:
        # Validate the file alone first so that a bad key in the file is blamed on the file.
        _build(cls, data, source)
        data = merge_overrides(data, overrides)
        source = f"{source} with overrides {list(overrides)}"
    return _build(cls, data, source)
