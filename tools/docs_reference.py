"""The generated reference pages of the documentation site, and the MkDocs hook that adds them.

``mkdocs build`` (mkdocs.yml, ``hooks:``) calls :func:`on_files`, which adds two pages built from the
code at every build, so that they cannot go stale:

- ``reference/config.md``: every key of every typed config (type, default, range, meaning), from the
  config dataclasses through :func:`fgslam.core.config_doc.config_keys`; plus the shipped presets;
- ``reference/cli.md``: every command and option, from the argument parsers of ``fgslam.cli``.

Run it alone to print a page: ``python tools/docs_reference.py config`` (or ``cli``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable


from fgslam.cli import build_parser
from fgslam.core.config import import_object
from fgslam.core.config_doc import SPHINX_ROLE, KeyDoc, config_keys
from fgslam.run.presets import PRESET_CLASSES, RUN_CONFIG_CLASS, run_presets

#: site paths of the generated pages
CONFIG_PAGE = "reference/config.md"
CLI_PAGE = "reference/cli.md"

#: (heading, config class, how a user sets its keys), in page order after ``fgslam run``'s
OTHER_CONFIGS: tuple[tuple[str, str, str], ...] = (
    ("fgslam localize", PRESET_CLASSES["localize"], "`fgslam localize MAP --data PATH --out DIR --config FILE -o key=value`"),
    ("fgslam pgo", PRESET_CLASSES["pgo"], "`fgslam pgo FILE.g2o --config FILE -o key=value`"),
    ("fgslam eval", PRESET_CLASSES["eval"],
     "`fgslam eval GT EST --format FMT --config FILE -o key=value`; in a run, by its `eval` section"),
    ("fgslam synth", PRESET_CLASSES["synth"], "`fgslam synth --out DIR --config FILE -o key=value`"),
    ("fgslam demo", PRESET_CLASSES["demo"], "`fgslam demo --config FILE -o key=value`"),
    ("fgslam batch: the matrix file", "fgslam.run.batch:BatchMatrix", "the keys of `MATRIX.yaml`"),
    ("fgslam batch: an entry of configs", "fgslam.run.batch:ConfigEntry", "a mapping under `configs:` of `MATRIX.yaml`"),
    ("fgslam batch: an entry of datasets", "fgslam.run.batch:DatasetEntry",
     "a mapping under `datasets:` of `MATRIX.yaml`"),
    ("fgslam export --ply", "fgslam.export.ply:PlyExportConfig", "`fgslam export RUN_DIR --ply FILE --max-point-range FACTOR`"),
    ("Factor plugin: position prior", "fgslam.services.plugins:PositionPriorOptions",
     "the `options:` of a `factors:` entry"),
    ("Factor plugin: planar motion", "fgslam.services.plugins:PlanarMotionOptions",
     "the `options:` of a `factors:` entry"),
    ("Python API: LiveConfig", "fgslam.io.live:LiveConfig", "`fgslam.LiveConfig(...)`; `fgslam run --live-speed/--live-queue`"),
)


def cell(text: str) -> str:
    """Text safe in one cell of a Markdown table (no column break, no HTML, no emphasis)."""
    return (text.replace("\\", "\\\\").replace("|", "\\|").replace("<", "&lt;").replace("*", "\\*")
            .replace("_", "\\_").replace("\n", " "))


def key_table(keys: Iterable[KeyDoc]) -> list[str]:
    lines = ["| key | type | default | allowed | meaning |", "|---|---|---|---|---|"]
    for k in keys:
        lines.append(f"| `{k.key}` | {cell(k.type_text)} | {cell(k.default_text)} | {cell(k.range_text)} "
                     f"| {cell(k.meaning)} |")
    return lines


def config_sections(cls: type) -> list[tuple[str, list[KeyDoc]]]:
    """The keys of ``cls`` grouped by top-level section: ("top-level keys", [...]), ("dataset", [...])."""
    groups: dict[str, list[KeyDoc]] = {}
    for k in config_keys(cls):
        head = k.key.split(".")[0]
        is_top = "." not in k.key and not k.section
        groups.setdefault("" if is_top else head, []).append(k)
    return [(name, keys) for name, keys in groups.items()]


def config_page() -> str:
    run_cls = import_object(RUN_CONFIG_CLASS)
    out = [
        "# Configuration reference",
        "",
        "Generated from the typed config classes at every build of this site: every key that the code "
        "has, with its type, default, allowed range and meaning. A YAML preset sets some keys; "
        "`-o section.key=value` on the command line sets any other (repeat `-o` for several). "
        "An unknown key, a wrong type or a value outside its range is refused before any work, "
        "naming the key.",
        "",
        "## Presets of fgslam run",
        "",
        "`fgslam run PRESET --data PATH --out DIR`; a preset is a YAML file of `fgslam run` keys "
        "(below), shipped in `fgslam/configs/`. A path to your own YAML file works the same way.",
        "",
        "| preset | what it is for |",
        "|---|---|",
    ]
    out += [f"| `{name}` | {cell(text)} |" for name, text in run_presets().items()]
    out += ["", "## fgslam run", "",
            f"The keys of `{run_cls.__name__}`, the root of a run's config; the same keys are the "
            "`overrides` of the Python API (`fgslam.Slam.from_preset`).", ""]
    for name, keys in config_sections(run_cls):
        out += [f"### {name or 'Top-level keys'}", ""]
        section = next((k for k in keys if k.section and k.key == name), None)
        if section is not None and section.meaning:
            out += [cell(section.meaning), ""]
        out += key_table(k for k in keys if k is not section) + [""]
    for heading, target, how in OTHER_CONFIGS:
        cls = import_object(target)
        out += [f"## {heading}", "", f"Set by {how}.", ""] + key_table(config_keys(cls)) + [""]
    return "\n".join(out)


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _option_row(action: argparse.Action) -> str | None:
    if isinstance(action, argparse._HelpAction) or action.help == argparse.SUPPRESS:
        return None
    if action.option_strings:
        names = ", ".join(action.option_strings)
        if action.nargs != 0:
            names += f" {action.metavar or action.dest.upper()}"
    else:
        names = action.metavar or action.dest
    default = action.default
    unset = default is None or default is False or default == [] or default == argparse.SUPPRESS
    shown = "" if unset or action.nargs == 0 else str(default)
    help_text = (action.help or "") % {"default": default, "prog": "fgslam"} if action.help else ""
    return f"| `{names}` | {cell(help_text)} | {cell(shown)} |"


def cli_page() -> str:
    parser = build_parser()
    out = ["# Command-line reference", "",
           "Generated from the argument parsers of `fgslam` at every build of this site. "
           "`fgslam COMMAND --help` prints the same.", "",
           "Every command takes the global options before the command name: "
           "`fgslam [-v | -q] COMMAND ...` (`-v` debug logging, `-q` warnings and errors only). "
           "Exit codes: 0 done; 1 `fgslam batch` with a failed cell; 2 refused (a one-line error names "
           "the cause); 130 interrupted by Ctrl-C and 143 by SIGTERM (every output written so far is "
           "kept).", ""]
    for name, sub in _subcommands(parser).items():
        sub.prog = f"fgslam {name}"
        out += [f"## fgslam {name}", "", cell(sub.description or ""), "", "```text",
                sub.format_usage().strip(), "```", "", "| argument | meaning | default |", "|---|---|---|"]
        out += [row for row in map(_option_row, sub._actions) if row]
        out += [""] + (["```text", sub.epilog.rstrip(), "```", ""] if sub.epilog else [])
    return "\n".join(out)


def cli_options() -> dict[str, set[str]]:
    """Command name -> the option strings its parser accepts (for checks of documented commands)."""
    return {name: {s for a in sub._actions for s in a.option_strings}
            for name, sub in _subcommands(build_parser()).items()}




def __getattr__(name: str):
    """``SphinxRoles``, the griffe extension (mkdocs.yml: mkdocstrings ``extensions``) that shows the
    docstrings' Sphinx roles as code; built on first use, since griffe comes with the docs extra only
    (the tests that read the generated pages run without it)."""
    if name != "SphinxRoles":
        raise AttributeError(name)
    import griffe  # deferred: the docs extra

    class SphinxRoles(griffe.Extension):
        def on_instance(self, *, obj, **kwargs) -> None:
            if obj.docstring is not None:
                obj.docstring.value = SPHINX_ROLE.sub(r"`\1`", obj.docstring.value)

    globals()["SphinxRoles"] = SphinxRoles
    return SphinxRoles


def on_files(files, config):  # MkDocs hook (mkdocs.yml: hooks)
    from mkdocs.structure.files import File

    for path, make in ((CONFIG_PAGE, config_page), (CLI_PAGE, cli_page)):
        files.append(File.generated(config, path, content=make()))
    return files


if __name__ == "__main__":  # pragma: no cover
    pages = {"config": config_page, "cli": cli_page}
    if len(sys.argv) != 2 or sys.argv[1] not in pages:
        sys.exit(f"usage: python tools/docs_reference.py {{{','.join(pages)}}}")
    sys.stdout.write(pages[sys.argv[1]]() + "\n")
