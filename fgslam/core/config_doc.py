"""Every key of a typed config, described: type, default, allowed range and one-line meaning.

The meaning of a field is the comment that the config classes already carry (the house rule of
:mod:`fgslam.core.config`: "a default plus a one-line comment"): the comment at the end of the
field's line, else the comment lines right above it, else, for a section (a nested dataclass), the
first line of its class docstring. The reference pages of the documentation are built from
:func:`config_keys`, so that they list exactly the keys the code has.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import io
import re
import textwrap
import tokenize
import types
import typing
from collections.abc import Iterator
from typing import Any

from .config import _type_name, field_range

#: a Sphinx role in a docstring (``:class:`~fgslam.io.camera.Camera` ``); group 1: the name it shows
SPHINX_ROLE = re.compile(r":(?:class|meth|func|attr|data|mod|exc|obj):`~?(?:[\w.]*\.)?([^`.]+)`")
#: Shown as the default of a field without one (never the case for a loadable config).
NO_DEFAULT = "(required)"


@dataclasses.dataclass(frozen=True)
class KeyDoc:
    """One key of a config: ``key`` dotted from the root (``dataset.end``), its type, default and
    allowed range as text, its meaning (one line; empty where the code says nothing), and whether it
    is a section (a nested dataclass whose own keys follow it)."""

    key: str
    type_text: str
    default_text: str
    range_text: str
    meaning: str
    section: bool = False


def type_text(tp: object) -> str:
    """A field type as a reader writes it: ``float``, ``"auto" | "xy"``, ``int or none``, ``list of float``."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Literal:
        return " | ".join(f'"{a}"' if isinstance(a, str) else repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        named = [type_text(a) for a in args if a is not type(None)]
        text = " or ".join(named)
        return f"{text} or null" if type(None) in args else text
    if origin in (list, tuple, dict):
        if origin is dict:
            return f"mapping of {type_text(args[0])} to {type_text(args[1])}" if args else "mapping"
        if origin is tuple and args and args[-1] is not Ellipsis:
            return "(" + ", ".join(type_text(a) for a in args) + ")"
        return f"list of {type_text(args[0])}" if args else "list"
    if tp is Any:
        return "any"
    return _type_name(tp)


def default_text(f: dataclasses.Field, owner: object = None) -> str:
    """The field's default as YAML would show it (``null``, ``true``, ``[]``, ``1.5``, ``"auto"``): its
    value in ``owner`` (the default instance of its section, which may set it apart from the field's own
    default) when given, else the field's default."""
    if owner is not None:
        value = getattr(owner, f.name)
    elif f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return NO_DEFAULT
    if dataclasses.is_dataclass(value):
        return "(section)"
    return _yaml_text(value)


def _yaml_text(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_yaml_text(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_yaml_text(v)}" for k, v in value.items()) + "}"
    if isinstance(value, float):
        return _float_text(value)
    return str(value)


def _float_text(value: float) -> str:
    """A float exactly (``repr``), written so that YAML reads a float back: ``1e-06`` is a string to
    YAML 1.1, ``1.0e-06`` a float."""
    text = repr(value)
    mantissa, e, exponent = text.partition("e")
    return f"{mantissa}.0e{exponent}" if e and "." not in mantissa else text


def _comments_by_line(source: str) -> dict[int, str]:
    """1-based line number -> the text of the comment on that line (without ``#``)."""
    found: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            found[tok.start[0]] = tok.string.lstrip("#").strip()
    return found


def field_comments(cls: type) -> dict[str, str]:
    """Field name -> its comment in the class body of ``cls`` or of the dataclass it inherits the
    field from (trailing, else the lines above)."""
    out: dict[str, str] = {}
    for base in reversed(cls.__mro__):
        if dataclasses.is_dataclass(base):
            out.update({name: text for name, text in _own_field_comments(base).items() if text})
    return out


@functools.cache
def _own_field_comments(cls: type) -> dict[str, str]:
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):  # a class built in code has no source: no comments
        return {}
    comments = _comments_by_line(source)
    tree = ast.parse(source)
    body = next(node for node in ast.walk(tree) if isinstance(node, ast.ClassDef)).body
    out: dict[str, str] = {}
    for node in body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        end = node.end_lineno or node.lineno
        trailing = [comments[n] for n in range(node.lineno, end + 1) if n in comments]
        if trailing:
            out[node.target.id] = " ".join(trailing)
            continue
        above: list[str] = []
        line = node.lineno - 1
        while line in comments and source.splitlines()[line - 1].lstrip().startswith("#"):
            above.insert(0, comments[line])
            line -= 1
        out[node.target.id] = " ".join(above)
    return out


def _first_doc_line(cls: type) -> str:
    """The first paragraph of the class docstring, on one line, reST markup dropped."""
    doc = inspect.getdoc(cls) or ""
    text = " ".join(doc.split("\n\n")[0].split())
    return SPHINX_ROLE.sub(r"\1", text).replace("``", "`")


def _section_class(tp: object) -> type | None:
    """The dataclass of a section field (``X`` or ``X | None``), else None."""
    for t in (tp, *typing.get_args(tp)):
        if isinstance(t, type) and dataclasses.is_dataclass(t):
            return t
    return None


def _default_instance(cls: type) -> object | None:
    """``cls()``, or None for a class with a required field."""
    try:
        return cls()
    except TypeError:
        return None


def config_keys(cls: type, prefix: str = "", owner: object = None) -> Iterator[KeyDoc]:
    """Every key of the config dataclass ``cls`` and of its sections, in declaration order, with the
    defaults of ``owner`` (default: ``cls()``): a section's default is what its parent builds, which
    may differ from the section class's own defaults."""
    owner = _default_instance(cls) if owner is None else owner
    hints = typing.get_type_hints(cls)
    comments = field_comments(cls)
    for f in dataclasses.fields(cls):
        key = f"{prefix}{f.name}"
        tp = hints[f.name]
        section = _section_class(tp)
        meaning = comments.get(f.name, "")
        value = None if owner is None else getattr(owner, f.name)
        if section is not None and (value is None or dataclasses.is_dataclass(value)):
            unset = owner is not None and value is None  # an optional section, off by default
            yield KeyDoc(key, "section or none" if unset else "section", "null" if unset else "", "",
                         meaning or _first_doc_line(section), section=True)
            yield from config_keys(section, f"{key}.", value)
            continue
        rng = field_range(f)
        yield KeyDoc(key, type_text(tp), default_text(f, owner), "" if rng is None else rng.text(), meaning)


def key_names(cls: type) -> set[str]:
    """The dotted names of every key and section of ``cls`` (``dataset``, ``dataset.end``, ...)."""
    return {k.key for k in config_keys(cls)}
