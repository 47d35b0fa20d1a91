"""The package's layering (docs/architecture.md, "Layers"): the import-linter contracts of pyproject.toml
hold, the checker does fail on an upward import (a function-local one), no import cycle exists
between fgslam's modules, and every dataclass config name is unique across the package."""

import ast
import collections
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import grimp  # the `test` extra pins import-linter, and grimp with it
from tool_support import load_tool

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "fgslam"
SUCCESS = 0  # lint_imports' exit code when every contract is kept
FAILURE = 1
CONFIG_SUFFIXES = ("Config", "Options")
COUNTS = load_tool("structure_counts")  # dataclasses of the YAML sections and plugin options


#: the checker in a process of its own: import-linter configures logging (and disables the loggers
#: that exist), which would silence the rest of the suite's log checks
LINT = ("import sys; from importlinter.cli import lint_imports; "
        "sys.exit(lint_imports(config_filename=sys.argv[1], no_cache=True, no_logo=True))")


def _lint(config: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", LINT, str(config)], capture_output=True, text=True, cwd=ROOT)


def test_layer_contracts_hold():
    proc = _lint(ROOT / "pyproject.toml")
    assert proc.returncode == SUCCESS, proc.stdout + proc.stderr


def test_checker_fails_on_an_upward_function_local_import(tmp_path):
    # fgslam.run.batch imports fgslam.run.config inside check_cells() and run_cell() only (deferred: the run
    # package pulls torch): with the two layers swapped those function-local imports break the contract
    config = tmp_path / "swapped.toml"
    config.write_text(
        f'[tool.importlinter]\nroot_package = "{PACKAGE}"\n\n'
        '[[tool.importlinter.contracts]]\nname = "swapped"\ntype = "layers"\n'
        'layers = ["fgslam.run.config", "fgslam.run.batch"]\n'
    )
    proc = _lint(config)
    assert proc.returncode == FAILURE, proc.stdout + proc.stderr
    assert "fgslam.run.batch -> fgslam.run.config" in proc.stdout  # broken, not a config error


def _strongly_connected(graph: grimp.ImportGraph) -> list[list[str]]:
    """Import cycles of the whole graph (``tools/structure_counts.py``'s finder)."""
    return COUNTS.strongly_connected(graph, set(graph.modules))


def test_no_import_cycles():
    # function-local imports and those under ``if TYPE_CHECKING`` included: a collaborator that names
    # the frontend holding it is a circle even if only its annotations close it
    graph = grimp.build_graph(PACKAGE, cache_dir=None, exclude_type_checking_imports=False)
    assert _strongly_connected(graph) == []


def test_cycle_finder_finds_a_cycle():
    graph = grimp.ImportGraph()
    for module in ("toy", "toy.a", "toy.b", "toy.c"):
        graph.add_module(module)
    graph.add_import(importer="toy.a", imported="toy.b")
    graph.add_import(importer="toy.b", imported="toy.a")
    graph.add_import(importer="toy.c", imported="toy.a")
    assert _strongly_connected(graph) == [["toy.a", "toy.b"]]


def _is_dataclass(node: ast.ClassDef) -> bool:
    for decorator in node.decorator_list:
        target = decorator.func if isinstance(decorator, ast.Call) else decorator
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name == "dataclass":
            return True
    return False


def test_config_class_names_are_unique():
    where = collections.defaultdict(list)
    for path in sorted((ROOT / PACKAGE).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef) and node.name.endswith(CONFIG_SUFFIXES) and _is_dataclass(node):
                where[node.name].append(str(path.relative_to(ROOT)))
    assert {name: paths for name, paths in where.items() if len(paths) > 1} == {}


def test_every_layer_has_its_line_in_the_design_notes():
    """Each package of the top-level layers contract has a row in docs/architecture.md section 2 ("Layers"),
    in the contract's order: a layer added without its one-line purpose fails here."""
    contract = next(c for c in tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
                    if c["id"] == "layers")
    text = (ROOT / "docs" / "architecture.md").read_text()
    table = text[text.index("| layer | purpose |"):]
    table = table[:table.index("\n\n")]
    rows = [set(re.findall(r"`(fgslam[\w.]*)`", line)) for line in table.splitlines()[2:]]
    documented = [name for row in rows for name in sorted(row)]
    for layer in contract["layers"]:
        for name in (part.strip() for part in layer.split("|")):
            assert name in documented, f"{name}: no row in docs/architecture.md's layer table"
    order = [next(i for i, row in enumerate(rows) if name in row)
             for layer in contract["layers"] for name in (part.strip() for part in layer.split("|"))]
    assert order == sorted(order)


def test_no_collaborator_imports_its_frontend():
    """A family's collaborators receive its state object, never the frontend (docs/architecture.md section 2):
    inside each family only the package itself imports ``frontend.py``, annotations included."""
    graph = grimp.build_graph(PACKAGE, cache_dir=None, exclude_type_checking_imports=False)
    families = sorted(m.rsplit(".", 1)[0] for m in graph.modules
                      if m.startswith(f"{PACKAGE}.frontends.") and m.endswith(".frontend"))
    assert len(families) >= 3
    for family in families:
        importers = {m for m in graph.find_modules_that_directly_import(f"{family}.frontend") if m.startswith(family)}
        assert importers <= {family}, (family, sorted(importers))


def test_no_collaborator_reaches_into_its_frontend(tmp_path):
    """No file of a family but ``frontend.py`` touches an attribute through a name holding the frontend
    (``fe.x``, ``self.frontend.x``; ``tools/structure_counts.py``), and the counter does see one."""
    assert COUNTS.collaborator_accesses(ROOT / PACKAGE)["all"] == 0
    family = tmp_path / "pkg" / "frontends" / "toy"
    family.mkdir(parents=True)
    (family / "frontend.py").write_text("class Toy:\n    pass\n")
    (family / "helper.py").write_text("def step(fe):\n    return fe._times, fe.graph\n")
    assert COUNTS.collaborator_accesses(tmp_path / "pkg") == {
        "all": 2, "private": 1, "files": {"pkg/frontends/toy/helper.py": {"all": 2, "private": 1}}}
