"""Size limits of the source: no class over 500 lines, no function over 120 lines.

Compiled numba kernels (a ``@numba.njit`` / ``@njit`` / ``@numba.jit`` decorator) are exempt: one
long kernel can beat several small ones where inlining pays (their docstrings say so).

The limits are checked in :data:`CHECKED_PACKAGES` (folders relative to the repository root): every
package. ``python tests/test_code_size.py`` lists what exceeds them anywhere in :data:`ROOTS`.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ROOTS = ("protocol", "mapper", "clients", "govnesf")
"""Where the report looks."""
CHECKED_PACKAGES = ROOTS
"""Where the limits are enforced."""
MAX_CLASS_LINES = 500
MAX_FUNCTION_LINES = 120


def is_compiled_kernel(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    """True when a decorator of ``node`` is numba's (``njit``, ``jit``, ``numba.*``, called or not)."""
    for decorator in node.decorator_list:
        target = decorator.func if isinstance(decorator, ast.Call) else decorator
        names = []
        while isinstance(target, ast.Attribute):
            names.append(target.attr)
            target = target.value
        if isinstance(target, ast.Name):
            names.append(target.id)
        if "numba" in names or (names and names[0] in ("njit", "jit")):
            return True
    return False


def oversized(path: Path) -> list[str]:
    """``"path:line kind name (N lines)"`` for each class over :data:`MAX_CLASS_LINES` and each
    function (methods and nested functions too) over :data:`MAX_FUNCTION_LINES` in ``path``;
    numba kernels are left out. A definition's lines run from its ``def`` / ``class`` line to its
    last line (decorators not counted)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ClassDef):
            kind, limit = "class", MAX_CLASS_LINES
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not is_compiled_kernel(node):
            kind, limit = "function", MAX_FUNCTION_LINES
        else:
            continue
        assert node.end_lineno is not None
        lines = node.end_lineno - node.lineno + 1
        if lines > limit:
            where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
            found.append(f"{where}:{node.lineno} {kind} {node.name} ({lines} lines > {limit})")
    return found


def python_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*.py") if "__pycache__" not in p.parts)


def test_checked_packages_keep_the_size_limits() -> None:
    found = [item for pkg in CHECKED_PACKAGES for path in python_files(ROOT / pkg)
             for item in oversized(path)]
    assert not found, "split these (docs/concepts/architecture.md):\n" + "\n".join(found)


def test_checked_packages_are_source_folders() -> None:
    for pkg in CHECKED_PACKAGES:
        assert (ROOT / pkg).is_dir() and pkg.split("/")[0] in ROOTS, pkg
        assert python_files(ROOT / pkg), f"{pkg} holds no Python file"


def test_the_check_finds_long_classes_and_functions_but_not_kernels(tmp_path: Path) -> None:
    def function(name: str, body_lines: int, decorator: str = "") -> str:
        return decorator + f"def {name}():\n" + "    x = 1\n" * (body_lines - 1) + "    return x\n"

    source = (
        "import numba\nfrom numba import njit\n\n"
        + function("short", 120)  # 121 lines with its def: too long
        + function("fits", 119)  # 120 lines: fits
        + function("kernel", 300, "@numba.njit(cache=True)\n")
        + function("bare_kernel", 300, "@njit\n")
        + function("decorated", 200, "@staticmethod\n")
        + "class Big:\n" + "    a = 1\n" * 500  # 501 lines
        + "class Small:\n" + "    a = 1\n" * 499
    )
    path = tmp_path / "module.py"
    path.write_text(source)
    found = {line.split(" ")[2] for line in oversized(path)}
    assert found == {"short", "decorated", "Big"}


if __name__ == "__main__":  # the report over every package, checked or not
    report = [item for pkg in ROOTS for path in python_files(ROOT / pkg) for item in oversized(path)]
    print("\n".join(report) or "nothing exceeds the limits")
    sys.exit(0)
