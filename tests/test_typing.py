"""The typed public API: both packages ship py.typed, the lazy exports have `TYPE_CHECKING` imports that cover
`__all__` (type checkers see the real types, not `Any`), and mypy passes on the public modules."""

from __future__ import annotations

import ast
import importlib.util
import subprocess
import sys

import pytest
import tomllib

import segmentation
import u4d_aug
from tests.tiny_nets import REPO

PACKAGES = (u4d_aug, segmentation)


def lazy_exports(package) -> dict[str, str]:
    """The `_EXPORTS` literal of the package's __init__: public name -> the module that defines it."""
    tree = ast.parse((REPO / package.__name__ / "__init__.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.target.id == "_EXPORTS":
            return ast.literal_eval(node.value)
    raise AssertionError(f"{package.__name__}/__init__.py: no _EXPORTS")


def type_checking_imports(package) -> dict[str, tuple[str, str | None]]:
    """Name -> (module, `as` name) of each `from M import X as X` under `if TYPE_CHECKING:` in the __init__."""
    tree = ast.parse((REPO / package.__name__ / "__init__.py").read_text(encoding="utf-8"))
    found = {}
    for node in tree.body:
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            for statement in node.body:
                assert isinstance(statement, ast.ImportFrom), ast.unparse(statement)
                found.update({alias.name: (statement.module, alias.asname) for alias in statement.names})
    return found


@pytest.mark.parametrize("package", PACKAGES, ids=lambda p: p.__name__)
def test_type_checking_imports_cover_every_lazy_export(package):
    exports = lazy_exports(package)
    imports = type_checking_imports(package)
    assert set(package.__all__) - {"__version__"} == set(exports)
    assert sorted(set(exports) - set(imports)) == [], "lazy exports without a TYPE_CHECKING import"
    assert sorted(set(imports) - set(exports)) == [], "TYPE_CHECKING imports that are not exported"
    for name, (module, alias) in imports.items():
        assert module == exports[name], f"{name}: imported from {module}, exported from {exports[name]}"
        assert alias == name, f"{name}: `from {module} import {name} as {name}` marks it re-exported"


def test_the_lazy_imports_stay_lazy():
    """The `TYPE_CHECKING` imports never run: `import u4d_aug` loads none of the modules it exports from."""
    code = (
        "import sys, u4d_aug, segmentation\n"
        "print(sorted(m for m in sys.modules if m.startswith(('u4d_aug.', 'segmentation.'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO).stdout
    assert out.strip() == "[]"


def test_both_packages_ship_py_typed():
    package_data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    for package in PACKAGES:
        assert (REPO / package.__name__ / "py.typed").is_file()
        assert "py.typed" in package_data[package.__name__]


def test_mypy_checks_every_public_module():
    """[tool.mypy] files: both __init__ and every module they export from (a new export's module joins the list)."""
    files = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["mypy"]["files"]
    public = {f"{package.__name__}/__init__.py" for package in PACKAGES}
    public |= {module.replace(".", "/") + ".py" for package in PACKAGES for module in lazy_exports(package).values()}
    assert sorted(files) == sorted(public)


@pytest.mark.slow
def test_public_modules_pass_mypy():
    """mypy with the [tool.mypy] settings of pyproject.toml (the files it lists) finds nothing."""
    if importlib.util.find_spec("mypy") is None:
        pytest.skip("mypy is not installed (it comes with the dev extras: pip install -e '.[dev]')")
    result = subprocess.run([sys.executable, "-m", "mypy"], cwd=REPO, capture_output=True, text=True, timeout=1800)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert result.stdout.startswith("Success: no issues found"), result.stdout
