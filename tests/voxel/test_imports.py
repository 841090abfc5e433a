"""The grid's parts never import the grid back: no import cycle, no import inside a function."""

from __future__ import annotations

import ast
from pathlib import Path

import voxel

PACKAGE = Path(voxel.__file__).parent


def _runtime_imports(tree: ast.Module) -> list[tuple[str, int, bool]]:
    """(module, line, inside a function) of every import not guarded by `if TYPE_CHECKING`."""
    found: list[tuple[str, int, bool]] = []

    def walk(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                continue
            if isinstance(child, ast.ImportFrom) and child.module:
                found.append((child.module, child.lineno, in_function))
            elif isinstance(child, ast.Import):
                found.extend((alias.name, child.lineno, in_function) for alias in child.names)
            walk(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))

    walk(tree, False)
    return found


def test_no_part_of_the_grid_imports_it_and_voxel_imports_sit_at_the_top() -> None:
    for path in sorted(PACKAGE.glob("*.py")):
        for module, line, in_function in _runtime_imports(ast.parse(path.read_text())):
            where = f"{path.name}:{line}"
            if path.name not in ("grid.py", "__init__.py"):
                assert module != "voxel.grid", f"{where} imports voxel.grid"
            if module.startswith("voxel"):
                assert not in_function, f"{where} imports {module} inside a function"
