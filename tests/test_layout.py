"""The layout rules of issue 23 ("done when"): at most 8 modules directly in rvggt_jax/, no
function over 100 lines, no module over 450 lines, the design card's converter script
runs; and the test tree's own rules (folders that name the package's subpackages, no
test module importing another). Each checker is also run on a planted case it must flag."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

from tests.helpers import PACKAGE, REPO

MAX_TOP_LEVEL_MODULES = 8
MAX_FUNCTION_LINES = 100
MAX_MODULE_LINES = 450
CONVERT_SCRIPT = REPO / "convert" / "convert_checkpoint.py"
TESTS = REPO / "tests"


def top_level_modules(package: Path) -> list[str]:
    """The .py modules directly in `package` (not __init__.py, not subpackages)."""
    return sorted(p.name for p in package.glob("*.py") if p.name != "__init__.py")


def long_functions(source: str, limit: int = MAX_FUNCTION_LINES) -> list[tuple[str, int]]:
    """(qualified name, lines) of every def in `source` (functions, methods, nested ones)
    longer than `limit` lines, counted from the `def` line to its last line."""
    found = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = prefix + child.name
                lines = child.end_lineno - child.lineno + 1
                if lines > limit:
                    found.append((name, lines))
                visit(child, name + ".<locals>.")
            elif isinstance(child, ast.ClassDef):
                visit(child, prefix + child.name + ".")
            else:
                visit(child, prefix)

    visit(ast.parse(source), "")
    return found


def long_modules(package: Path, limit: int = MAX_MODULE_LINES) -> list[tuple[str, int]]:
    """(path relative to `package`'s parent, lines) of every .py file under `package`
    longer than `limit` lines."""
    out = []
    for p in sorted(package.rglob("*.py")):
        n = len(p.read_text().splitlines())
        if n > limit:
            out.append((str(p.relative_to(package.parent)), n))
    return out


def package_long_functions(package: Path) -> list[str]:
    return [f"{p.relative_to(package.parent)}: {name} ({lines} lines)"
            for p in sorted(package.rglob("*.py")) for name, lines in long_functions(p.read_text())]


def script_help(script: Path) -> tuple[int, str | None, str]:
    """Run `python SCRIPT --help` from the repository: (return code, its usage line or None,
    stderr)."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, cwd=REPO, env=env,
                       timeout=120)
    usage = next((ln for ln in r.stdout.splitlines() if ln.startswith("usage: ")), None)
    return r.returncode, usage, r.stderr


def imported_test_modules(source: str) -> list[str]:
    """The test modules (test_*, conftest) that `source` imports."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [node.module or ""] + [f"{node.module or ''}.{a.name}" for a in node.names]
        else:
            continue
        found += [n for n in names if n.split(".")[-1].startswith("test_") or n.split(".")[-1] == "conftest"]
    return found


# ---- the rules, on the package and on the tests ---------------------------------------------


def test_at_most_8_modules_directly_in_the_package():
    modules = top_level_modules(PACKAGE)
    assert modules, "no module found: is PACKAGE the package?"
    assert len(modules) <= MAX_TOP_LEVEL_MODULES, modules


def test_no_function_over_100_lines():
    assert len(list(PACKAGE.rglob("*.py"))) > 20  # the walk sees the subpackages
    long = package_long_functions(PACKAGE)
    assert not long, "functions over 100 lines:\n" + "\n".join(long)


def test_no_module_over_450_lines():
    long = long_modules(PACKAGE)
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_convert_script_prints_its_usage():
    code, usage, err = script_help(CONVERT_SCRIPT)
    assert code == 0, err[-3000:]
    assert usage is not None and "convert_checkpoint.py" in usage, usage


def test_test_folders_name_subpackages():
    subpackages = {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    folders = {p.name for p in TESTS.iterdir() if p.is_dir() and any(p.glob("test_*.py"))}
    assert folders and folders <= subpackages, folders - subpackages
    for f in folders | {"helpers"}:
        assert (TESTS / f / "__init__.py").is_file(), f  # package-style test modules (tests.model.test_forward)


def test_no_test_module_imports_another():
    bad = {str(p.relative_to(REPO)): imported_test_modules(p.read_text()) for p in sorted(TESTS.rglob("*.py"))}
    bad = {k: v for k, v in bad.items() if v}
    assert not bad, bad


# ---- the checkers flag planted cases ----------------------------------------------------------


def _def(name: str, lines: int, indent: str = "", body: str = "") -> str:
    """A def of exactly `lines` lines (its `def` line included), `body` first."""
    inner = indent + "    "
    text = [f"{indent}def {name}():"] + [inner + ln for ln in body.splitlines()]
    text += [f"{inner}x = {i}" for i in range(lines - len(text))]
    return "\n".join(text) + "\n"


def test_function_checker_flags_planted_functions():
    source = ("import math\n\n" + _def("short", 5) + _def("exactly_at_the_limit", 100)
              + "class Model:\n" + _def("long_method", 101, indent="    ")
              + _def("outer", 103, body=_def("inner", 101)))
    found = dict(long_functions(source))
    assert found == {"Model.long_method": 101, "outer": 103, "outer.<locals>.inner": 101}, found
    assert long_functions(_def("f", 100)) == [] and long_functions(_def("f", 101)) == [("f", 101)]
    assert long_functions("async " + _def("g", 101)) == [("g", 101)]


def test_module_checkers_flag_planted_packages(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    for i in range(MAX_TOP_LEVEL_MODULES):
        (pkg / f"m{i}.py").write_text("x = 1\n" * MAX_MODULE_LINES)
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "deep.py").write_text("y = 2\n" * (MAX_MODULE_LINES + 1))
    assert len(top_level_modules(pkg)) == MAX_TOP_LEVEL_MODULES  # __init__ and sub/ do not count
    assert long_modules(pkg) == [(str(Path("pkg") / "sub" / "deep.py"), MAX_MODULE_LINES + 1)]
    (pkg / "one_more.py").write_text(_def("f", 101))
    assert len(top_level_modules(pkg)) == MAX_TOP_LEVEL_MODULES + 1
    assert package_long_functions(pkg) == [f"{Path('pkg') / 'one_more.py'}: f (101 lines)"]


def test_script_checker_flags_planted_scripts(tmp_path):
    failing = tmp_path / "failing.py"
    failing.write_text("import sys\nprint('usage: failing.py')\nsys.exit(2)\n")
    silent = tmp_path / "silent.py"
    silent.write_text("print('help text without a usage line')\n")
    assert script_help(failing)[:2] == (2, "usage: failing.py")
    assert script_help(silent)[:2] == (0, None)


def test_import_checker_flags_planted_imports():
    source = ("import numpy\nfrom conftest import rel_err\nfrom tests.model.test_layers import _reference\n"
              "import tests.weights.test_hub\nfrom tests.helpers import rel_err\n"
              "def f():\n    from test_track_head import FINAL_ITER_RTOL\n")
    assert sorted(imported_test_modules(source)) == sorted(["conftest", "tests.model.test_layers", "tests.weights.test_hub",
                                                   "test_track_head"])
