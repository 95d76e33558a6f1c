"""Layout of the packages (DESIGN.md §4): no function longer than 80 lines, and every module with its test file at the
mirrored path (u4d_aug/data/scan.py -> tests/u4d_aug/data/test_scan.py)."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

from tests.tiny_nets import REPO

PACKAGES = ("u4d_aug", "segmentation")
MAX_FUNCTION_LINES = 80


def modules() -> list[Path]:
    """Every module of the packages but their __init__.py, relative to the repository."""
    found = [path for package in PACKAGES for path in (REPO / package).rglob("*.py") if path.name != "__init__.py"]
    return sorted(path.relative_to(REPO) for path in found)


def functions(node: ast.AST, prefix: str = "") -> Iterator[tuple[str, ast.FunctionDef | ast.AsyncFunctionDef]]:
    """(qualified name, node) of every function and method under `node`, nested ones too."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
            yield prefix + child.name, child
            yield from functions(child, f"{prefix}{child.name}.")
        elif isinstance(child, ast.ClassDef):
            yield from functions(child, f"{prefix}{child.name}.")
        else:
            yield from functions(child, prefix)


def long_functions(module: Path) -> list[str]:
    """'FILE:LINE NAME: N lines' of each function of `module` longer than MAX_FUNCTION_LINES (def to last line)."""
    tree = ast.parse((REPO / module).read_text(encoding="utf-8"), filename=str(module))
    found = []
    for name, node in functions(tree):
        length = node.end_lineno - node.lineno + 1
        if length > MAX_FUNCTION_LINES:
            found.append(f"{module}:{node.lineno} {name}: {length} lines")
    return found


def mirrored_test(module: Path) -> Path:
    """tests/PACKAGE/.../test_NAME.py of PACKAGE/.../NAME.py."""
    return Path("tests") / module.parent / f"test_{module.name}"


def test_the_rules_see_every_module_and_function():
    found = modules()
    assert Path("u4d_aug/data/sim/world.py") in found and Path("segmentation/losses.py") in found
    assert not [path for path in found if path.name == "__init__.py"]
    assert mirrored_test(Path("u4d_aug/data/scan.py")) == Path("tests/u4d_aug/data/test_scan.py")
    tree = ast.parse(
        "class A:\n    def f(self):\n        def g():\n            pass\nif True:\n    async def h():\n        pass\n"
    )
    assert [name for name, _ in functions(tree)] == ["A.f", "A.f.g", "h"]


def test_no_function_is_longer_than_80_lines():
    found = [entry for module in modules() for entry in long_functions(module)]
    assert not found, f"functions longer than {MAX_FUNCTION_LINES} lines (split them):\n" + "\n".join(found)


def test_every_module_has_its_mirrored_test_file():
    missing = [
        f"{module} -> {mirrored_test(module)}" for module in modules() if not (REPO / mirrored_test(module)).is_file()
    ]
    assert not missing, "modules without their test file (tests/README.md):\n" + "\n".join(missing)
