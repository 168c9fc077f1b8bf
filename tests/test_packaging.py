"""Packaging: what pyproject.toml declares matches what the code imports, on every Python we accept."""

from __future__ import annotations

import glob
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def _requirements() -> dict[str, Requirement]:
    return {Requirement(text).name: Requirement(text) for text in PROJECT["dependencies"]}


def test_tomli_is_declared_exactly_where_config_imports_it():
    tomli = _requirements().get("tomli")
    assert tomli is not None, "config.py imports tomli on Python < 3.11"
    assert tomli.marker is not None
    assert tomli.marker.evaluate({"python_version": "3.10"})
    assert not tomli.marker.evaluate({"python_version": "3.11"})
    assert "sys.version_info >= (3, 11)" in (ROOT / "taichi_gs" / "config.py").read_text()


def test_every_third_party_import_of_the_package_is_a_declared_dependency():
    import ast

    declared = set(_requirements()) | {"opencv-python-headless"}
    # an optional extra's package (the viewer's viser) only where a function imports it, when it is used
    optional = {Requirement(text).name for text in PROJECT["optional-dependencies"]["viewer"]}
    import_names = {"cv2": "opencv-python-headless", "skimage": "scikit-image", "yaml": "pyyaml"}
    stdlib = set(sys.stdlib_module_names) | {"tomllib", "tomli", "taichi_gs"}
    missing = set()
    for path in (ROOT / "taichi_gs").rglob("*.py"):
        tree = ast.parse(path.read_text())
        in_functions = {id(node) for function in ast.walk(tree) if isinstance(function, ast.FunctionDef)
                        for node in ast.walk(function)}
        for node in ast.walk(tree):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else [])
            allowed = declared | optional if id(node) in in_functions else declared
            for name in names:
                top = name.split(".")[0]
                if top not in stdlib and import_names.get(top, top) not in allowed:
                    missing.add(f"{top} ({path.name})")
    assert not missing, f"imported but not in pyproject dependencies (or, optional ones, outside a function): {sorted(missing)}"


def test_every_name_a_module_exports_exists():
    """``from taichi_gs.<module> import *`` works: each name in a module's ``__all__`` is defined there."""
    import ast
    import importlib

    missing = []
    for path in (ROOT / "taichi_gs").rglob("*.py"):
        listed = [node for node in ast.parse(path.read_text()).body if isinstance(node, ast.Assign)
                  and any(isinstance(target, ast.Name) and target.id == "__all__" for target in node.targets)]
        if not listed:
            continue
        parts = path.relative_to(ROOT).with_suffix("").parts
        module = importlib.import_module(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
        missing += [f"{module.__name__}.{name}" for name in module.__all__ if not hasattr(module, name)]
    assert not missing, f"listed in __all__ but not defined: {missing}"


def test_license_is_an_spdx_expression():
    assert PROJECT["license"] == "Apache-2.0"


def _python310() -> str | None:
    candidates = [shutil.which("python3.10"), *sorted(glob.glob(str(Path.home() / ".pyenv/versions/3.10*/bin/python3.10")))]
    for candidate in filter(None, candidates):
        try:
            out = subprocess.run([candidate, "-c", "import sys; print(sys.version_info[:2])"], capture_output=True,
                                 text=True, timeout=30)
        except OSError:
            continue
        if out.returncode == 0 and out.stdout.strip() == "(3, 10)":
            return candidate
    return None


def test_sources_compile_on_python_3_10():
    python = _python310()
    if python is None:
        pytest.skip("no Python 3.10 interpreter here; the metadata test above covers tomli")
    result = subprocess.run([python, "-m", "compileall", "-q", "-f", "-d", "x", str(ROOT / "taichi_gs")],
                            capture_output=True, text=True, timeout=120, env={"PYTHONPYCACHEPREFIX": "/tmp/pycache310"})
    assert result.returncode == 0, result.stdout + result.stderr
