"""What the wheel ships: the package and its configs, never the test doubles (lanevil_dev/) or the tests, and no
module of the package imports either (an installed package has neither)."""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "lanevil_train"
DEV_ONLY = ("tests", "lanevil_dev")  # top-level packages of the source checkout only

_RUN_MODULE = re.compile(r"-m\s+(tests|lanevil_dev)\b")
_MODULE_PATH = re.compile(r"lanevil_dev(\.\w+)*(:\w+)?|tests(\.\w+)+(:\w+)?")
_TARGET = re.compile(r"^\s*_target_:\s*['\"]?(tests|lanevil_dev)\b", re.M)


def _dev_only(module: str | None) -> bool:
    return module is not None and module.split(".")[0] in DEV_ONLY


def _docstrings(tree: ast.AST) -> set[int]:
    """ids of the module's, classes' and functions' docstring nodes (prose may name a test file)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                found.add(id(first.value))
    return found


def dev_only_uses(source: str, name: str = "<source>") -> list[str]:
    """'line: what' for each use of tests/lanevil_dev in python `source`: imports, import_module/__import__ of a
    string, a `python -m` of one (in a string or as "-m", "<module>" in a command list), a dotted module path."""
    tree = ast.parse(source, name)
    docstrings = _docstrings(tree)
    uses = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            uses += [f"{node.lineno}: import {a.name}" for a in node.names if _dev_only(a.name)]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and _dev_only(node.module):
            uses.append(f"{node.lineno}: from {node.module} import ...")
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if func in ("import_module", "__import__") and _dev_only(str(node.args[0].value)):
                uses.append(f"{node.lineno}: {func}({node.args[0].value!r})")
        elif isinstance(node, (ast.List, ast.Tuple)):
            items = [e.value if isinstance(e, ast.Constant) else None for e in node.elts]
            uses += [f"{node.lineno}: '-m', {b!r}" for a, b in zip(items, items[1:])
                     if a == "-m" and isinstance(b, str) and _dev_only(b)]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
            if _RUN_MODULE.search(node.value) or _MODULE_PATH.fullmatch(node.value):
                uses.append(f"{node.lineno}: {node.value[:80]!r}")
    return uses


def test_no_module_of_the_package_uses_the_tests_or_the_test_doubles():
    """Every .py under lanevil_train/ (and every config's _target_) is free of `tests` and `lanevil_dev`."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        found += [f"{path.relative_to(ROOT)}:{use}" for use in dev_only_uses(path.read_text(), str(path))]
    for path in sorted(PACKAGE.rglob("*.yaml")):
        found += [f"{path.relative_to(ROOT)}: _target_ {m.group(1)}" for m in _TARGET.finditer(path.read_text())]
    assert not found, "the package uses what the wheel does not ship:\n" + "\n".join(found)


@pytest.mark.parametrize("source", [
    "import lanevil_dev", "import tests.vlm.conftest as c", "from lanevil_dev.fake_server import FakeServer",
    "from tests.tasks import cli_helpers", "def f():\n    from lanevil_dev import tiny_vlm",
    "importlib.import_module('lanevil_dev.tiny_vlm')", "cmd = [sys.executable, '-m', 'lanevil_dev.fake_server']",
    "cmd = 'python -m tests.vlm.helper --port 0'", "TARGET = 'tests.tasks.failing_defense:FailingDefense'",
])
def test_the_check_catches_each_kind_of_use(source):
    assert dev_only_uses(source)


@pytest.mark.parametrize("source", [
    "from . import tests", "import lanevil_train.tests_helpers", "from lanevil_train.vlm.tokenizer import qwen_ids",
    "'''Checked by tests/test_packaging.py and lanevil_dev.tiny_vlm.'''", "names = ['tests', '-m']",
    "cmd = [sys.executable, '-m', 'lanevil_train']",
])
def test_the_check_passes_what_is_not_a_use(source):
    assert not dev_only_uses(source)


def test_the_wheel_ships_the_package_and_its_configs_only(tmp_path):
    """pip builds the wheel offline (no build isolation: the venv's setuptools) from a copy of the checkout, so that
    no build/ or *.egg-info lands in it; the copy has lanevil_dev/ and tests/ too, to be left out."""
    source = tmp_path / "src"
    junk = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "build", "dist", "outputs", "multirun")
    for name in ("lanevil_train", "lanevil_dev", "tests", "benchmarks"):
        shutil.copytree(ROOT / name, source / name, ignore=junk)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                            "--disable-pip-version-check", "-q", "-w", str(tmp_path / "dist"), str(source)],
                           capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stdout[-3000:] + built.stderr[-3000:]
    wheels = list((tmp_path / "dist").glob("lanevil_train-*.whl"))
    assert len(wheels) == 1, wheels
    names = set(zipfile.ZipFile(wheels[0]).namelist())

    assert "lanevil_train/__init__.py" in names and "lanevil_train/conf/config.yaml" in names
    package_files = {path.relative_to(ROOT).as_posix() for pattern in ("*.py", "*.yaml")
                     for path in PACKAGE.rglob(pattern) if "__pycache__" not in path.parts}
    assert not package_files - names, "left out of the wheel: " + ", ".join(sorted(package_files - names))
    assert {name.split("/")[0] for name in names if ".dist-info/" not in name} == {"lanevil_train"}
    doubles = re.compile(r"(^|/)(lanevil_dev|tests)/|fake_server|tiny_vlm|vlm/tiny\.py")
    assert not [name for name in names if doubles.search(name)]
