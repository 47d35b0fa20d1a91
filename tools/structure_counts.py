"""Structure counts of the fgslam package, for the closing notes of structure work; prints one JSON object.

Counts:

- ``collaborator_frontend_accesses``: in each frontend family's folder, attribute accesses through a
  name that holds the frontend (``fe.x``, ``frontend.x``, ``self.fe.x``, ``self._fe.x``,
  ``self.frontend.x``) in every file but the family's ``frontend.py``; ``private`` those to a
  ``_name``;
- ``folder_cycles``: import cycles (strongly connected components) among the modules of one folder,
  imports under ``if TYPE_CHECKING`` included;
- ``system_frontend_getattr``: ``getattr(<frontend>, ...)`` calls in the system module;
- ``getattr_forwarders``: classes that define ``__getattr__``;
- ``any_annotations``: annotations (arguments, returns, variables) that are ``Any`` (``bare``) or
  contain it (``containing``, e.g. ``dict[str, Any]``);
- ``function_local_imports``: ``import`` statements inside a function body (and in how many files);
- ``largest_class`` (by methods) and ``largest_module`` (by lines).

Usage: .venv/bin/python tools/structure_counts.py [--package fgslam]
"""

from __future__ import annotations

import argparse
import ast
import json
from pathlib import Path

import grimp

REPO = Path(__file__).resolve().parents[1]
FRONTEND_NAMES = {"fe", "frontend", "_fe", "_frontend"}
SYSTEM_MODULES = ("system.py", "run/system.py")


def _holder(node: ast.expr) -> bool:
    """Whether ``node`` names the frontend: ``fe``, ``frontend``, ``self.fe``, ``self._fe``, ..."""
    if isinstance(node, ast.Name):
        return node.id in FRONTEND_NAMES
    return isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "self" \
        and node.attr in FRONTEND_NAMES


def collaborator_accesses(package: Path) -> dict:
    total = private = 0
    per_file = {}
    for family in sorted((package / "frontends").iterdir()):
        if not (family / "frontend.py").is_file():
            continue
        for path in sorted(family.glob("*.py")):
            if path.name == "frontend.py":
                continue
            n = p = 0
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Attribute) and _holder(node.value):
                    n += 1
                    p += node.attr.startswith("_")
            if n:
                per_file[str(path.relative_to(package.parent))] = {"all": n, "private": p}
            total += n
            private += p
    return {"all": total, "private": private, "files": per_file}


def strongly_connected(graph: grimp.ImportGraph, modules: set[str]) -> list[list[str]]:
    """Import cycles: the strongly connected components (more than one module) of the import graph
    restricted to ``modules`` (Tarjan, iterative; tests/test_layers.py uses it too)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out = []

    def children(m: str) -> list[str]:
        return sorted(c for c in graph.find_modules_directly_imported_by(m) if c in modules)

    for start in sorted(modules):
        if start in index:
            continue
        work = [(start, iter(children(start)))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            module, it = work[-1]
            child = next(it, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(children(child))))
                elif child in on_stack:
                    low[module] = min(low[module], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[module])
            if low[module] == index[module]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == module:
                        break
                if len(component) > 1:
                    out.append(sorted(component))
    return out


def folder_cycles(name: str) -> list[list[str]]:
    graph = grimp.build_graph(name, cache_dir=None, exclude_type_checking_imports=False)
    folders: dict[str, set[str]] = {}
    for module in graph.modules:
        folders.setdefault(module.rsplit(".", 1)[0], set()).add(module)
    cycles = []
    for folder in sorted(folders):
        cycles += strongly_connected(graph, folders[folder])
    return cycles


def system_getattr(package: Path) -> int:
    n = 0
    for rel in SYSTEM_MODULES:
        path = package / rel
        if not path.is_file():
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "getattr" \
                    and node.args and (_holder(node.args[0]) or (isinstance(node.args[0], ast.Attribute)
                                                                   and node.args[0].attr == "frontend")):
                n += 1
    return n


def _bare_any(node: ast.expr | None) -> bool:
    return (isinstance(node, ast.Name) and node.id == "Any") or (isinstance(node, ast.Constant) and node.value == "Any")


def _mentions_any(node: ast.expr | None) -> bool:
    if node is None:
        return False
    return any(isinstance(n, ast.Name) and n.id == "Any" for n in ast.walk(node)) or (
        isinstance(node, ast.Constant) and isinstance(node.value, str) and "Any" in node.value)


def per_module(package: Path) -> dict:
    forwarders, any_count, bare, local_imports, local_files = [], 0, 0, 0, 0
    largest_class = ("", 0)
    largest_module = ("", 0)
    for path in sorted(package.rglob("*.py")):
        text = path.read_text()
        rel = str(path.relative_to(package.parent))
        lines = text.count("\n")
        if lines > largest_module[1]:
            largest_module = (rel, lines)
        tree = ast.parse(text, rel)
        file_local = 0
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                methods = [n for n in node.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
                if any(m.name == "__getattr__" for m in methods):
                    forwarders.append(f"{rel}:{node.name}")
                if len(methods) > largest_class[1]:
                    largest_class = (f"{rel}:{node.name}", len(methods))
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                args = node.args
                for a in args.posonlyargs + args.args + args.kwonlyargs + [args.vararg, args.kwarg]:
                    if a is not None and _mentions_any(a.annotation):
                        any_count += 1
                        bare += _bare_any(a.annotation)
                any_count += _mentions_any(node.returns)
                bare += _bare_any(node.returns)
                for inner in ast.walk(node):
                    if isinstance(inner, (ast.Import, ast.ImportFrom)):
                        file_local += 1
            elif isinstance(node, ast.AnnAssign) and _mentions_any(node.annotation):
                any_count += 1
                bare += _bare_any(node.annotation)
        # nested functions are walked twice above: count each import statement once
        seen = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for inner in ast.walk(node):
                    if isinstance(inner, (ast.Import, ast.ImportFrom)):
                        seen.add(id(inner))
        file_local = len(seen)
        local_imports += file_local
        local_files += file_local > 0
    return {"getattr_forwarders": forwarders, "any_annotations": {"bare": bare, "containing": any_count},
            "function_local_imports": {"imports": local_imports, "files": local_files},
            "largest_class": {"name": largest_class[0], "methods": largest_class[1]},
            "largest_module": {"name": largest_module[0], "lines": largest_module[1]}}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--package", default="fgslam")
    p.add_argument("--root", type=Path, default=REPO, help="the source tree holding the package")
    args = p.parse_args(argv)
    package = args.root / args.package
    modules = per_module(package)
    cycles = folder_cycles(args.package)
    report = {
        "collaborator_frontend_accesses": collaborator_accesses(package),
        "folder_cycles": {"count": len(cycles), "cycles": cycles},
        "system_frontend_getattr": system_getattr(package),
        **modules,
        "root_modules": sorted(p.name for p in package.glob("*.py")),
        "modules_over_600_lines": sorted(str(q.relative_to(package.parent)) for q in package.rglob("*.py")
                                         if q.read_text().count("\n") > 600),
    }
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
