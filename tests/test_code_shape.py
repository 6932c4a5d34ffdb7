"""The house rules a reader relies on: files under 400 lines, functions under 80 in the
library and the recipes, no module directly under ``pnp/`` but ``__init__.py``."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CODE = ("pnp", "envs", "transforms", "losses", "recipes", "tests")


def _python(folders):
    for folder in folders:
        yield from sorted((ROOT / folder).rglob("*.py"))


def test_files_are_under_400_lines():
    long = {str(p.relative_to(ROOT)): n for p in _python(CODE) if (n := len(p.read_text().splitlines())) > 400}
    assert not long, long


def test_functions_are_under_80_lines():
    long = {}
    for path in _python(("pnp", "envs", "transforms", "losses", "recipes")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno >= 80:
                long[f"{path.relative_to(ROOT)}:{node.name}"] = node.end_lineno - node.lineno + 1
    assert not long, long


def test_pnp_holds_subpackages_only():
    assert sorted(p.name for p in (ROOT / "pnp").glob("*.py")) == ["__init__.py"]


def test_tests_import_the_package_not_the_recipes():
    """Recipes are thin command lines; what a test checks lives in the package."""
    offenders = [str(p.relative_to(ROOT)) for p in _python(("tests",))
                 if "sys.path.insert(0, str(ROOT / \"recipes\"" in p.read_text()]
    assert not offenders, offenders


def test_readme_is_a_short_guide_beside_the_results_and_the_architecture():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 150, len(lines)
    assert not [n for n, line in enumerate(lines, 1) if len(line) > 120]
    assert (ROOT / "RESULTS.md").is_file() and (ROOT / "docs" / "guide" / "architecture.md").is_file()
