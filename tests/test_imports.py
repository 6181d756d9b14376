"""The package's import graph: every import follows the layers of docs/architecture.md
(`IMPORT_RULES`), no import cycle, neither among the imports that run at
import time nor counting every import (inside functions too, and the uses of
`rvggt_jax`'s lazy names), and the converter importable from a fresh interpreter in
either order with the loaders (the old top-level `convert` package and
`rvggt_jax.weights.checkpoint` imported each other)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import PACKAGE


def _module_name(path: Path, package: Path = PACKAGE) -> str:
    parts = path.relative_to(package.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _named_modules(node: ast.Import | ast.ImportFrom, name: str, is_package: bool, modules: set[str]) -> list[str]:
    """The modules an import statement of module `name` names (`from pkg import sub`
    names the submodule pkg.sub too)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if node.level:
        base = name.split(".") if is_package else name.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        mod = ".".join(base + ([node.module] if node.module else []))
    else:
        mod = node.module or ""
    return [mod] + [f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in modules]


def _lazy_names() -> dict[str, str]:
    """`rvggt_jax`'s lazy public names (its `__getattr__` tables) -> the module that
    using the name imports."""
    import rvggt_jax

    return dict(rvggt_jax._LAZY)


def _lazy_uses(tree: ast.AST, lazy: dict[str, str], package: str = "rvggt_jax") -> dict[str, int]:
    """{module: line} of the uses of `package`'s lazy names in `tree`, anywhere:
    `from rvggt_jax import NAME` and `rvggt_jax.NAME`. The package's table itself is no
    edge of `rvggt_jax` (it maps names and imports on demand); a use imports the module
    behind the name, so it is an edge of the module that uses it."""
    found: dict[str, int] = {}
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.ImportFrom) and node.module == package and not node.level:
            names = [a.name for a in node.names]
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == package:
            names = [node.attr]
        for n in names:
            if n in lazy:
                found.setdefault(lazy[n], node.lineno)
    return found


def _imports(path: Path, name: str, modules: set[str], *, everywhere: bool = False,
             lazy: dict[str, str] | None = None) -> dict[str, int]:
    """{package module: line of its first import} of the modules `path` imports.

    everywhere=False: those imported when it is executed, imports at module level (inside
    `if`/`try` too), not those inside functions or classes, which run later.
    everywhere=True: every import statement, in functions and classes too, and every use
    of a lazy name of `lazy` (`_lazy_uses`)."""
    is_package = path.name == "__init__.py"
    tree = ast.parse(path.read_text())
    found: dict[str, int] = {}

    def visit(stmts: list[ast.stmt]) -> None:
        for node in stmts:
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for m in _named_modules(node, name, is_package, modules):
                    found.setdefault(m, node.lineno)
            elif isinstance(node, (ast.If, ast.Try)):
                for field in ("body", "orelse", "finalbody"):
                    visit(getattr(node, field, []))
                for handler in getattr(node, "handlers", []):
                    visit(handler.body)

    if everywhere:
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for m in _named_modules(node, name, is_package, modules):
                    found[m] = min(found.get(m, node.lineno), node.lineno)
        for m, line in _lazy_uses(tree, lazy or {}, name.split(".")[0]).items():
            found.setdefault(m, line)
    else:
        visit(tree.body)
    # importing a.b.c runs a/b/__init__.py first
    for m, line in list(found.items()):
        for i in range(1, m.count(".") + 1):
            parent = ".".join(m.split(".")[:i])
            found[parent] = min(found.get(parent, line), line)
    # A module's own parent packages are being imported already when it runs (Python
    # imports `a` and `a.b` before `a.b.c`): `from a.b import sibling` is not a cycle.
    ancestors = {".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 1)}
    return {m: line for m, line in found.items() if m in modules and m != name and m not in ancestors}


def _import_graph(*, everywhere: bool = False, package: Path = PACKAGE,
                  lazy: dict[str, str] | None = None) -> dict[str, dict[str, int]]:
    """{module: {module it imports: line}} over `package` (see `_imports`)."""
    files = {_module_name(p, package): p for p in package.rglob("*.py")}
    modules = set(files)
    if everywhere and lazy is None and package == PACKAGE:
        lazy = _lazy_names()
    return {name: _imports(path, name, modules, everywhere=everywhere, lazy=lazy) for name, path in files.items()}


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


def _cycles(graph: dict[str, dict[str, int]]) -> list[str]:
    """Every cycle `_find_cycle` meets, one a line, `a:LINE -> b:LINE -> ... -> a` (LINE:
    where that module imports the next): one is found, its last edge dropped, again."""
    graph = {a: dict(b) for a, b in graph.items()}
    found = []
    while (cycle := _find_cycle(graph)) is not None:
        found.append(" -> ".join(f"{a}:{graph[a][b]}" for a, b in zip(cycle, cycle[1:])) + f" -> {cycle[-1]}")
        del graph[cycle[-2]][cycle[-1]]
    return found


def test_all_imports_graph_sees_imports_in_functions_and_lazy_names(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from pkg.b import g\n    return g\n")
    (pkg / "b.py").write_text("import pkg\n\n\ndef g():\n    return pkg.lazy_a\n")
    assert _import_graph(package=pkg) == {"pkg": {}, "pkg.a": {}, "pkg.b": {}}
    graph = _import_graph(everywhere=True, package=pkg, lazy={"lazy_a": "pkg.a"})
    assert graph["pkg.a"] == {"pkg.b": 2} and graph["pkg.b"] == {"pkg.a": 5}
    assert _cycles(graph) == ["pkg.a:2 -> pkg.b:5 -> pkg.a"]
    full = _import_graph(everywhere=True)
    assert "rvggt_jax.weights.checkpoint" in full["rvggt_jax.weights.hub"]  # inside _convert_to
    assert "rvggt_jax.weights.pretrained" in full["rvggt_jax.train.loop"]  # rvggt_jax.load_pretrained(...)


def test_no_import_cycle_counting_every_import():
    """Imports inside functions too: a cycle there still ties the modules together (and
    breaks when one of them is imported first from the other's function)."""
    cycles = _cycles(_import_graph(everywhere=True))
    assert not cycles, "import cycles (module:line of each import):\n  " + "\n  ".join(cycles)


# Which part of the package may import which (docs/architecture.md): a part is a
# subpackage or a top-level module; each may import itself and the parts (or modules, as
# "model.params", with what is below them) listed here, and the packages above those (a
# package's __init__ runs before its modules: importing model.params runs model/__init__).
# "rvggt_jax" is the package's own __init__, whose lazy table is not an import edge.
IMPORT_RULES = {
    "rvggt_jax": {"config"},
    "config": {"compression.config", "compression.presets", "ops.kernels.names"},
    "geometry": set(),
    "errors": set(),
    "sequence": {"errors", "synthetic"},
    "ops": set(),
    "model": {"config", "errors", "ops", "compression"},
    "compression": {"config", "errors", "ops", "model"},
    "parallel": {"config", "ops", "model"},
    "weights": {"config", "model.params", "model.param_rules"},
    "planning": {"config", "errors", "ops", "compression", "model", "parallel", "weights"},
    "io": {"geometry"},
    "ba": {"geometry", "io"},
    "eval": {"geometry", "io", "model", "weights"},
    "train": {"config", "errors", "geometry", "eval", "model", "parallel", "synthetic", "weights"},
    "synthetic": {"config", "geometry", "eval", "model", "synthetic", "weights"},
    "examples_data": {"synthetic", "eval"},  # generate.py renders the demo scene (folder format)
    "diagnostics": {"config", "compression", "model", "planning"},
}
ANYTHING = ("app",)  # the command line


def _part(module: str) -> str:
    parts = module.split(".")
    return "rvggt_jax" if len(parts) == 1 else parts[1]


def rule_breaks(graph: dict[str, dict[str, int]], rules: dict[str, set[str]] = IMPORT_RULES,
                anything: tuple[str, ...] = ANYTHING) -> list[str]:
    """`a:LINE imports b` for every edge of `graph` that its part's rules do not allow (a
    part missing from `rules` and `anything` may import nothing outside itself)."""
    breaks = []
    for a, targets in sorted(graph.items()):
        pa = _part(a)
        if pa in anything:
            continue
        allowed = rules.get(pa, set())
        above = {e.rsplit(".", i)[0] for e in allowed for i in range(1, e.count(".") + 1)}
        for b, line in sorted(targets.items()):
            rel = b.split(".", 1)[1] if "." in b else b
            if _part(b) == pa or rel in above or any(rel == e or rel.startswith(e + ".") for e in allowed):
                continue
            breaks.append(f"{a}:{line} imports {b}")
    return breaks


def test_rule_checker_flags_planted_imports():
    graph = {"rvggt_jax.ops.attention": {"rvggt_jax.model.layers": 3, "rvggt_jax.ops.chunks": 4},
             "rvggt_jax.weights.converter": {"rvggt_jax.model.params": 7, "rvggt_jax.model.layers": 8},
             "rvggt_jax.app.cli": {"rvggt_jax.model.forward": 9}, "rvggt_jax.newpart.x": {"rvggt_jax.io.ply": 2}}
    assert rule_breaks(graph) == ["rvggt_jax.newpart.x:2 imports rvggt_jax.io.ply",
                                  "rvggt_jax.ops.attention:3 imports rvggt_jax.model.layers",
                                  "rvggt_jax.weights.converter:8 imports rvggt_jax.model.layers"]


def test_every_import_follows_the_layer_rules():
    """Every import (in functions too, and every use of a lazy name) goes from a part to a
    part its row of IMPORT_RULES names: the package's layers (docs/architecture.md)."""
    graph = _import_graph(everywhere=True)
    assert {_part(m) for m in graph} <= set(IMPORT_RULES) | set(ANYTHING), "a new part: give it a row"
    breaks = rule_breaks(graph)
    assert not breaks, "imports across the layers (docs/architecture.md):\n  " + "\n  ".join(breaks)


ENV_PROBE = """
import importlib, json, os, sys
import jax  # sets TF_CPP_MIN_LOG_LEVEL and TPU_SKIP_MDS_QUERY itself: the baseline is taken after it
before = dict(os.environ)
import rvggt_jax
for name in rvggt_jax.__all__:
    getattr(rvggt_jax, name)
for name in sys.argv[1:]:
    importlib.import_module(name)
after = dict(os.environ)
print(json.dumps({k: [before.get(k), after.get(k)] for k in sorted(set(before) | set(after))
                  if before.get(k) != after.get(k)}))
"""


def test_import_leaves_the_environment_alone():
    """Importing rvggt_jax, every lazy name of it and every module of the package changes
    no environment variable (XLA_FLAGS included: `prefer_threaded_convolutions` is called
    by the `rvggt` command, not by an import)."""
    import json
    import os

    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["PYTHONPATH"] = str(PACKAGE.parent)
    r = subprocess.run([sys.executable, "-c", ENV_PROBE, *sorted(_import_graph())], capture_output=True,
                       text=True, timeout=300, env=env, cwd=PACKAGE.parent)
    assert r.returncode == 0, r.stderr[-3000:]
    changed = json.loads(r.stdout.splitlines()[-1])
    assert changed == {}, f"environment variables changed by importing rvggt_jax (before, after): {changed}"


@pytest.mark.parametrize("first, second", [("rvggt_jax.app.convert_command", "rvggt_jax.weights.checkpoint"),
                                           ("rvggt_jax.weights.checkpoint", "rvggt_jax.app.convert_command")])
def test_converter_and_loader_import_in_either_order(first, second):
    code = (f"import {first}, {second}; import rvggt_jax.weights; "
            "assert rvggt_jax.weights.checkpoint.CheckpointError is rvggt_jax.weights.CheckpointError")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def test_retired_shims_are_gone():
    """0.1's aliases (`rvggt_jax.convert`, `rvggt_jax.nn`, the `rvggt_jax.train` attribute
    without an import) are retired (README, release notes): each is an error now."""
    code = ("import importlib, rvggt_jax\n"
            "for name in ('nn', 'train'):\n"
            "    try:\n        getattr(rvggt_jax, name)\n    except AttributeError:\n        pass\n"
            "    else:\n        raise SystemExit('rvggt_jax.' + name + ' still resolves')\n"
            "try:\n    importlib.import_module('rvggt_jax.convert')\nexcept ModuleNotFoundError:\n    pass\n"
            "else:\n    raise SystemExit('rvggt_jax.convert still imports')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


def test_convert_script_runs():
    """The design card's converter script (`convert/convert_checkpoint.py`) runs."""
    script = PACKAGE.parent / "convert" / "convert_checkpoint.py"
    r = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=120,
                       cwd=PACKAGE.parent)
    assert r.returncode == 0, r.stderr
    assert "usage: python convert/convert_checkpoint.py" in r.stdout
