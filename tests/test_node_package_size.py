"""Both nodes stay packages of small parts: no module over 400 lines, no class over 300.

The robot node was one 1,044-line module whose class held the frame
pipeline, two copies of command admission, the lease, video, deadman,
heartbeats and workers; the operator node one 940-line module mixing link
setup, what arrives, the lease view, the palm, the outbox and recording.
This keeps the next concern from growing back into one class.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import operator_side.node
import robot_side.node

PACKAGES = [Path(p.__file__).parent for p in (robot_side.node, operator_side.node)]
MAX_MODULE_LINES = 400
MAX_CLASS_LINES = 300


def _sizes(source: str) -> tuple[int, dict[str, int]]:
    """(lines in the module, lines of each class, decorators and docstring included)."""
    tree = ast.parse(source)
    classes = {
        node.name: node.end_lineno
        - min([node.lineno, *(d.lineno for d in node.decorator_list)])
        + 1
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef)
    }
    return len(source.splitlines()), classes


@pytest.mark.parametrize("package", PACKAGES, ids=lambda p: f"{p.parent.name}.{p.name}")
def test_no_module_or_class_of_a_node_package_is_too_long(package: Path) -> None:
    modules = sorted(package.glob("*.py"))
    assert len(modules) > 5, f"{package} is not a node package"
    too_long = []
    for path in modules:
        lines, classes = _sizes(path.read_text())
        if lines >= MAX_MODULE_LINES:
            too_long.append(f"{path.name}: {lines} lines (limit {MAX_MODULE_LINES})")
        too_long += [
            f"{path.name}: class {name}: {n} lines (limit {MAX_CLASS_LINES})"
            for name, n in classes.items()
            if n >= MAX_CLASS_LINES
        ]
    assert not too_long, "split by concern: " + "; ".join(too_long)


def test_the_size_check_sees_a_long_class() -> None:
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_CLASS_LINES))
    lines, classes = _sizes(f"class Big:\n{body}\n")
    assert classes == {"Big": MAX_CLASS_LINES + 1} and lines == MAX_CLASS_LINES + 1
