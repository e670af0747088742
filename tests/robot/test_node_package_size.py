"""The robot node stays a package of small parts: no module over 400 lines, no class over 300.

It was one 1,044-line module whose class held the frame pipeline, two
copies of command admission, the lease, video, deadman, heartbeats and
workers; this keeps the next concern from growing back into one class.
"""

from __future__ import annotations

import ast
from pathlib import Path

import robot_side.node

PACKAGE = Path(robot_side.node.__file__).parent
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


def test_no_module_or_class_of_the_robot_node_is_too_long() -> None:
    modules = sorted(PACKAGE.glob("*.py"))
    assert len(modules) > 5, f"{PACKAGE} is not the robot node package"
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
