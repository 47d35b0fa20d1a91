"""Documents that the code and the README cite exist in the repository.

Every ``docs/<file>`` named in fgslam/, tools/, README.md or docs/ must exist, a section cited as
``docs/<file>.md section N`` (or ``sections N and M``) must be a ``## N.`` heading of that file,
README and docs/ relative Markdown links must resolve, and nothing may point outside the
repository at the shared design notes (``../shared/DESIGN.md``): their content is docs/architecture.md.
"""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

SCANNED = ("fgslam", "tools", "docs", "README.md")
TEXT_SUFFIXES = {".py", ".md", ".yaml", ".txt", ".toml"}

#: docs/<file>, optionally followed (a Markdown link, a closing quote, a comment continuation) by
#: "section N" or "sections N, M and K".
DOC_REF = re.compile(
    r"docs/(?P<file>[A-Za-z0-9_.\-/]*[A-Za-z0-9_])"
    r"(?:[`'\"]*\]\([^)]*\))?[`'\"),]*"
    r"(?:[\s#]*sections?\s+(?P<sections>\d+(?:\s*(?:,|and|,\s*and)\s*\d+)*))?"
)
MD_LINK = re.compile(r"\]\((?P<target>[^)\s#]+)(?:#[^)]*)?\)")
SHARED_DESIGN = re.compile(r"shared/DESIGN|DESIGN\.md")
#: pages of the documentation site generated at build time (tools/docs_reference.py): links to them resolve
GENERATED_PAGES = ("docs/reference/config.md", "docs/reference/cli.md")


def _scanned_files() -> list[Path]:
    files: list[Path] = []
    for name in SCANNED:
        path = REPO / name
        if path.is_file():
            files.append(path)
        else:
            files.extend(p for p in sorted(path.rglob("*")) if p.is_file() and p.suffix in TEXT_SUFFIXES)
    return files


def doc_references(text: str) -> list[tuple[str, list[int]]]:
    """(file under docs/, cited section numbers) for every ``docs/...`` reference in ``text``."""
    refs = []
    for m in DOC_REF.finditer(text):
        sections = [int(n) for n in re.findall(r"\d+", m.group("sections") or "")]
        refs.append((m.group("file"), sections))
    return refs


def numbered_sections(markdown: str) -> set[int]:
    """Numbers of the ``## N. Title`` headings of a Markdown file."""
    return {int(n) for n in re.findall(r"^#{1,6}\s+(\d+)\.", markdown, flags=re.MULTILINE)}


def dangling_references(files: list[Path], root: Path = REPO) -> list[str]:
    """What is wrong with the references of ``files`` (of the repository at ``root``): one line each."""
    problems = []
    for path in files:
        where = path.relative_to(root)
        for lineno, line_text in enumerate(path.read_text().splitlines(), 1):
            if SHARED_DESIGN.search(line_text):
                problems.append(f"{where}:{lineno}: points at the shared design notes, not docs/architecture.md")
        text = path.read_text()
        for file, sections in doc_references(text):
            target = root / "docs" / file
            if f"docs/{file}" in GENERATED_PAGES:
                continue
            if not target.is_file():
                problems.append(f"{where}: cites docs/{file}, which does not exist")
                continue
            missing = sorted(set(sections) - numbered_sections(target.read_text())) if sections else []  # (a figure has none)
            if missing:
                problems.append(f"{where}: cites docs/{file} section(s) {missing}, which it does not have")
        if path.suffix == ".md":
            for m in MD_LINK.finditer(text):
                target = m.group("target")
                if "://" in target or target.startswith("mailto:"):
                    continue
                resolved = (path.parent / target).resolve()
                generated = any(resolved == (root / page).resolve() for page in GENERATED_PAGES)
                if not resolved.exists() and not generated:
                    problems.append(f"{where}: Markdown link to {target}, which does not exist")
    return problems


def test_cited_documents_and_sections_exist():
    files = _scanned_files()
    assert any(p.name == "README.md" for p in files) and any(p.suffix == ".py" for p in files)
    cited = [ref for p in files for ref in doc_references(p.read_text())]
    assert ("architecture.md", [5]) in cited and ("architecture.md", [4]) in cited  # the scan sees today's citations
    assert not dangling_references(files)


def test_the_scan_catches_dangling_references(tmp_path):
    """The checker fails on a missing document, a missing section, a broken link and the shared notes."""
    assert doc_references("see docs/design.md section 4.") == [("design.md", [4])]
    assert doc_references("([docs/design.md](docs/design.md) section 5)")[0] == ("design.md", [5])
    assert doc_references("(docs/design.md sections 5 and 6)") == [("design.md", [5, 6])]
    assert doc_references("# cites docs/design.md\n    # section 7 here") == [("design.md", [7])]
    assert doc_references("``docs/design.md``, section 2") == [("design.md", [2])]
    assert numbered_sections("# Title\n## 1. One\ntext\n## 10. Ten\n") == {1, 10}

    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "design.md").write_text("# Notes\n## 1. One\n## 2. Two\n")
    good = tmp_path / "good.md"
    good.write_text("see docs/design.md sections 1 and 2, [notes](docs/design.md)\n")
    assert dangling_references([good], tmp_path) == []
    bad = tmp_path / "bad.md"
    bad.write_text("see docs/nonexistent.md and docs/design.md section 99, [x](nowhere.md), ../shared/DESIGN.md\n")
    problems = dangling_references([bad], tmp_path)
    assert len(problems) == 4
    assert any("docs/nonexistent.md, which does not exist" in p for p in problems)
    assert any("section(s) [99]" in p for p in problems)
    assert any("link to nowhere.md" in p for p in problems)
    assert any("shared design notes" in p for p in problems)
