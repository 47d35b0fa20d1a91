"""The documentation site (mkdocs.yml, docs/): it builds strictly, its links and anchors resolve, the
reference pages generated from the code cover every key, and what the pages and the README document
(commands, options, ``-o`` keys, dotted keys) exists in the code. The README stays short."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from fgslam.cli import COMMANDS
from fgslam.core.config import import_object
from fgslam.core.config_doc import config_keys, key_names
from fgslam.run.presets import PRESET_CLASSES, RUN_CONFIG_CLASS

from tool_support import load_tool

REPO = Path(__file__).resolve().parents[1]
#: the README's length limit: what it is, the two commands, the preset table, three examples, links
README_MAX_LINES = 260
#: config class of the keys that a command's ``-o KEY=VALUE`` sets
COMMAND_CONFIG = {
    "run": RUN_CONFIG_CLASS, "compare-colmap": RUN_CONFIG_CLASS, "localize": PRESET_CLASSES["localize"],
    "pgo": PRESET_CLASSES["pgo"], "eval": PRESET_CLASSES["eval"], "synth": PRESET_CLASSES["synth"],
    "demo": PRESET_CLASSES["demo"], "info": PRESET_CLASSES["dataset"],
}
#: options every command takes (before the command name) besides its own
GLOBAL_OPTIONS = {"-h", "--help", "-v", "--verbose", "-q", "--quiet", "--version"}
#: file name endings of names that look like dotted keys (``map.npz``, ``eval.yaml``) but are files
FILE_SUFFIXES = {"npz", "yaml", "yml", "json", "txt", "png", "ply", "rrd", "bin", "g2o", "csv", "py", "md", "pth",
                 "db3", "mcap", "bag", "jpg", "mp4", "avi", "html", "toml"}
CODE_BLOCK = re.compile(r"^```[^\n]*\n(.*?)^```", re.M | re.S)
CODE_SPAN = re.compile(r"`([^`\n]+)`")
DOTTED_KEY = re.compile(r"^([a-z_][a-z0-9_]*(?:\.[a-z_][a-z0-9_]*)+)(?:=.*)?$")
TOOL_SCRIPT = re.compile(r"\btools/([a-z0-9_]+\.py)\b")


def _mkdocs_available() -> None:
    pytest.importorskip("mkdocs", reason="the docs extra is not installed (pip install -e '.[docs]')")
    pytest.importorskip("mkdocstrings_handlers.python", reason="the docs extra is not installed")


def _build(config_file: Path, site: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(config_file),
                           "-d", str(site)], cwd=REPO, env=env, capture_output=True, text=True)


def documented_texts() -> dict[str, str]:
    """Repository-relative name -> text of the README and every page under docs/."""
    pages = {"README.md": (REPO / "README.md").read_text()}
    pages.update({str(p.relative_to(REPO)): p.read_text() for p in sorted((REPO / "docs").rglob("*.md"))})
    return pages


def _commands_in(code: str) -> list[list[str]]:
    """The ``fgslam ...`` command lines of a code block or span, as tokens (continuations joined)."""
    joined = re.sub(r"\\\n\s*", " ", code)
    found = []
    for line in joined.splitlines():
        for part in re.split(r"&&|\||;", line):
            try:
                tokens = shlex.split(part, comments=True)
            except ValueError:  # an unbalanced quote in a prose-like span: not a command line
                continue
            for i, tok in enumerate(tokens):
                if tok in ("fgslam", ".venv/bin/fgslam") or tok.endswith("/bin/fgslam"):
                    found.append(tokens[i + 1:])
                    break
    return found


def documentation_problems(text: str, where: str) -> list[str]:
    """What ``text`` documents that the code does not have: a command, an option of a command, a key of
    ``-o KEY=VALUE``, a dotted key of ``fgslam run``'s config in a code span, a ``tools/`` script."""
    tool = load_tool("docs_reference")
    options = tool.cli_options()
    keys = {cmd: key_names(import_object(target)) for cmd, target in COMMAND_CONFIG.items()}
    run_keys = keys["run"]
    sections = {k for k in run_keys if "." not in k}
    problems = []
    code = [m.group(1) for m in CODE_BLOCK.finditer(text)]
    prose = CODE_BLOCK.sub("", text)
    spans = [m.group(1) for m in CODE_SPAN.finditer(prose)]
    for chunk in code + spans:
        for tokens in _commands_in(chunk):
            if not tokens or tokens[0].startswith("-") or tokens[0].startswith("["):
                continue
            cmd = tokens[0]
            if cmd not in COMMANDS:
                if re.fullmatch(r"[a-z][a-z-]*", cmd):
                    problems.append(f"{where}: `fgslam {cmd}`: no such command")
                continue
            for i, tok in enumerate(tokens[1:], 1):
                flag = tok.split("=")[0]
                if re.fullmatch(r"--?[a-zA-Z][\w-]*", flag) and flag not in options[cmd] | GLOBAL_OPTIONS:
                    problems.append(f"{where}: `fgslam {cmd} {flag}`: no such option")
                if tok in ("-o", "--override") and i + 1 < len(tokens) and "=" in tokens[i + 1]:
                    key = tokens[i + 1].split("=")[0]
                    if cmd in keys and re.fullmatch(r"[a-z_][\w.]*", key) and key not in keys[cmd]:
                        problems.append(f"{where}: `fgslam {cmd} -o {key}=...`: no such key")
    for span in spans:
        m = DOTTED_KEY.match(span.strip())
        if m is None:
            continue
        key = m.group(1)
        head, last = key.split(".")[0], key.split(".")[-1]
        if head in sections and last not in FILE_SUFFIXES and key not in run_keys:
            problems.append(f"{where}: `{key}`: no such key of fgslam run's config")
    for name in TOOL_SCRIPT.findall(text):
        if not (REPO / "tools" / name).is_file():
            problems.append(f"{where}: tools/{name}: no such script")
    return problems


def test_the_site_builds_strictly(tmp_path):
    _mkdocs_available()
    result = _build(REPO / "mkdocs.yml", tmp_path / "site")
    assert result.returncode == 0, result.stderr[-4000:]
    for page in ("reference/config/index.html", "reference/cli/index.html", "reference/api/index.html",
                 "changelog/index.html"):
        assert (tmp_path / "site" / page).is_file(), page
    api = (tmp_path / "site" / "reference/api/index.html").read_text()
    assert all(f'id="fgslam.' in api and name in api for name in ("Slam", "Camera", "TrackResult", "open_dataset"))


def test_the_strict_build_fails_on_a_broken_link_or_anchor(tmp_path):
    """The site's own validation settings turn a link to a missing page, or to a missing heading, into
    a failed build."""
    _mkdocs_available()
    site = yaml.safe_load((REPO / "mkdocs.yml").read_text().replace("!!python", "#"))
    for case, link in (("page", "missing.md"), ("anchor", "other.md#no-such-heading")):
        docs = tmp_path / case / "docs"
        docs.mkdir(parents=True)
        (docs / "index.md").write_text(f"# Home\n\nSee [the other page]({link}).\n")
        (docs / "other.md").write_text("# Other\n\n## A heading\n")
        config = {"site_name": "t", "docs_dir": str(docs), "strict": True, "validation": site["validation"],
                  "nav": [{"Home": "index.md"}, {"Other": "other.md"}]}
        config_file = tmp_path / case / "mkdocs.yml"
        config_file.write_text(yaml.safe_dump(config))
        result = _build(config_file, tmp_path / case / "site")
        assert result.returncode != 0, case
        assert "no-such-heading" in result.stderr if case == "anchor" else "missing.md" in result.stderr
        (docs / "index.md").write_text("# Home\n\nSee [the other page](other.md#a-heading).\n")
        assert _build(config_file, tmp_path / case / "site").returncode == 0, case


def test_every_page_is_in_the_navigation():
    nav = yaml.safe_load((REPO / "mkdocs.yml").read_text().replace("!!python", "#"))["nav"]

    def leaves(items) -> set[str]:
        out: set[str] = set()
        for item in items:
            value = item if isinstance(item, str) else next(iter(item.values()))
            out |= leaves(value) if isinstance(value, list) else {value}
        return out

    tool = load_tool("docs_reference")
    pages = {str(p.relative_to(REPO / "docs")) for p in (REPO / "docs").rglob("*.md")}
    generated = {tool.CONFIG_PAGE, tool.CLI_PAGE}
    assert pages | generated == leaves(nav)


def test_the_documents_name_only_commands_options_and_keys_the_code_has():
    problems = [p for where, text in documented_texts().items() for p in documentation_problems(text, where)]
    assert not problems, "\n".join(problems)


def test_the_check_catches_what_the_code_does_not_have():
    text = ("```bash\nfgslam run handheld_rgbd --data D --out O -o dataset.nonsense=1 --no-such-flag \\\n"
            "  -o output.write_map=true\nfgslam frobnicate X\n```\n"
            "Set `map.no_such_key` or `dataset.end`; `map.npz` is a file; `tools/no_such_tool.py`.\n")
    problems = documentation_problems(text, "t.md")
    assert len(problems) == 5, problems
    for expected in ("-o dataset.nonsense", "--no-such-flag", "fgslam frobnicate", "`map.no_such_key`",
                     "tools/no_such_tool.py"):
        assert any(expected in p for p in problems), expected
    good = "```bash\nfgslam run handheld_rgbd --data D --out O -o dataset.end=10 --overwrite\n```\n`output.write_map`\n"
    assert documentation_problems(good, "t.md") == []


def test_the_config_reference_covers_every_key_with_its_meaning():
    """Every key of every documented config has a type and a one-line meaning (the field's comment),
    and the generated page lists it."""
    tool = load_tool("docs_reference")
    page = tool.config_page()
    targets = [RUN_CONFIG_CLASS] + [target for _, target, _ in tool.OTHER_CONFIGS]
    for target in targets:
        cls = import_object(target)
        for key in config_keys(cls):
            assert key.meaning, f"{target}: key '{key.key}' has no comment saying what it means"
            top_section = key.section and "." not in key.key and target == RUN_CONFIG_CLASS
            assert (f"### {key.key}\n" if top_section else f"| `{key.key}` |") in page, key.key


def test_the_documented_defaults_are_those_a_run_gets():
    """A section's defaults are what its parent builds (``SlamConfig()``), not the section class's own:
    every documented default, read back as YAML (a user copies it into a preset), is the value of the
    default config (``to_dict``), exactly."""
    from fgslam.core.config import to_dict

    for target in [RUN_CONFIG_CLASS, PRESET_CLASSES["localize"], PRESET_CLASSES["demo"]]:
        cls = import_object(target)
        values = to_dict(cls())
        for key in config_keys(cls):
            if key.section:
                continue
            value = values
            for part in key.key.split("."):
                value = value[part]
            shown = yaml.safe_load(key.default_text)
            expected = list(value) if isinstance(value, tuple) else value
            assert shown == expected and type(shown) is type(expected), (target, key.key, key.default_text, value)
    keys = {k.key: k for k in config_keys(import_object(RUN_CONFIG_CLASS))}
    assert keys["pointmap.source.kind"].default_text == '"auto"'  # the family's default, not the source class's


def test_the_cli_reference_lists_every_command_and_option():
    tool = load_tool("docs_reference")
    page = tool.cli_page()
    for name, flags in tool.cli_options().items():
        assert f"## fgslam {name}" in page
        for flag in flags - {"-h", "--help"}:
            assert re.search(rf"`[^`]*{re.escape(flag)}\b[^`]*`", page), (name, flag)


def test_the_readme_is_short_and_names_no_issue():
    readme = (REPO / "README.md").read_text()
    assert len(readme.splitlines()) <= README_MAX_LINES
    assert not re.search(r"\bissues? \d+", readme, re.I)
