"""The package's import graph: no module-level import cycle, and the converter importable
from a fresh interpreter in either order with the loaders (the old top-level `convert`
package and `rvggt_jax.weights.checkpoint` imported each other)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import PACKAGE


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _module_level_imports(path: Path, name: str, modules: set[str]) -> set[str]:
    """The package modules `path` imports when it is executed: imports at module level
    (inside `if`/`try` too), not those inside functions or classes, which run later."""
    is_package = path.name == "__init__.py"
    found: set[str] = set()

    def resolve(node: ast.ImportFrom) -> str:
        if not node.level:
            return node.module or ""
        base = name.split(".") if is_package else name.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        return ".".join(base + ([node.module] if node.module else []))

    def visit(stmts: list[ast.stmt]) -> None:
        for node in stmts:
            if isinstance(node, ast.Import):
                found.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                mod = resolve(node)
                found.add(mod)
                # `from pkg import sub` imports the submodule pkg.sub
                found.update(f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in modules)
            elif isinstance(node, (ast.If, ast.Try)):
                for field in ("body", "orelse", "finalbody"):
                    visit(getattr(node, field, []))
                for handler in getattr(node, "handlers", []):
                    visit(handler.body)

    visit(ast.parse(path.read_text()).body)
    # importing a.b.c runs a/b/__init__.py first
    found |= {".".join(m.split(".")[:i]) for m in found for i in range(1, m.count(".") + 1)}
    # A module's own parent packages are being imported already when it runs (Python
    # imports `a` and `a.b` before `a.b.c`): `from a.b import sibling` is not a cycle.
    ancestors = {".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 1)}
    return {m for m in found if m in modules and m != name and m not in ancestors}


def _import_graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    modules = set(files)
    return {name: _module_level_imports(path, name, modules) for name, path in files.items()}


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of `graph` as [a, b, ..., a], or None (iterative depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    for root in sorted(graph):
        if root in state:
            continue
        path, stack = [root], [iter(sorted(graph[root]))]
        state[root] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            elif nxt not in state:
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(sorted(graph[nxt])))
    return None


def test_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _find_cycle(graph) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b"}, "b": set()}) is None


def test_graph_sees_the_converter_imports():
    graph = _import_graph()
    assert "rvggt_jax.weights.errors" in graph["rvggt_jax.weights.checkpoint"]
    assert "rvggt_jax.weights.errors" in graph["rvggt_jax.weights.converter"]


def test_no_module_level_import_cycle():
    cycle = _find_cycle(_import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


@pytest.mark.parametrize("first, second", [("rvggt_jax.convert", "rvggt_jax.weights.checkpoint"),
                                           ("rvggt_jax.weights.checkpoint", "rvggt_jax.convert")])
def test_converter_and_loader_import_in_either_order(first, second):
    code = (f"import {first}, {second}; "
            "assert rvggt_jax.weights.checkpoint.CheckpointError is rvggt_jax.convert.CheckpointError")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def test_python_m_converter_runs():
    r = subprocess.run([sys.executable, "-m", "rvggt_jax.convert", "--help"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert "usage: python -m rvggt_jax.convert" in r.stdout
