"""The package's layering (docs/design.md, "Layers"): the import-linter contracts of pyproject.toml
hold, the checker does fail on an upward import (a function-local one), no import cycle exists
between fgslam's modules, and every dataclass config name is unique across the package."""

import ast
import collections
import subprocess
import sys
from pathlib import Path

import grimp  # the `test` extra pins import-linter, and grimp with it

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "fgslam"
SUCCESS = 0  # lint_imports' exit code when every contract is kept
FAILURE = 1
CONFIG_SUFFIXES = ("Config", "Options")  # dataclasses of the YAML sections and plugin options


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
    # fgslam.batch imports fgslam.run.config inside check_cells() and run_cell() only (deferred: the run
    # package pulls torch): with the two layers swapped those function-local imports break the contract
    config = tmp_path / "swapped.toml"
    config.write_text(
        f'[tool.importlinter]\nroot_package = "{PACKAGE}"\n\n'
        '[[tool.importlinter.contracts]]\nname = "swapped"\ntype = "layers"\n'
        'layers = ["fgslam.run.config", "fgslam.batch"]\n'
    )
    proc = _lint(config)
    assert proc.returncode == FAILURE, proc.stdout + proc.stderr
    assert "fgslam.batch -> fgslam.run.config" in proc.stdout  # broken, not a config error


def _strongly_connected(graph: grimp.ImportGraph) -> list[list[str]]:
    """Import cycles: the strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []
    for start in sorted(graph.modules):
        if start in index:
            continue
        work = [(start, iter(sorted(graph.find_modules_directly_imported_by(start))))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            module, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.find_modules_directly_imported_by(child)))))
                elif child in on_stack:
                    low[module] = min(low[module], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[module])
            if low[module] == index[module]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == module:
                        break
                if len(component) > 1:
                    cycles.append(sorted(component))
    return cycles


def test_no_import_cycles():
    # function-local imports included; annotations only (a collaborator naming the frontend class
    # that holds it, under ``if TYPE_CHECKING``) are not imports at run time
    graph = grimp.build_graph(PACKAGE, cache_dir=None, exclude_type_checking_imports=True)
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
