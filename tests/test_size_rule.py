"""The product stays made of small parts: no module of 400 lines or more, no class of 300.

Both node packages were split by concern once (the robot node was one
1,044-line module whose class held the frame pipeline, two copies of command
admission, the lease, video, deadman, heartbeats and workers); elsewhere
classes kept growing (the UR driver 735 lines, its simulator 815). This holds
every product package (``common``, ``robot_side``, ``operator_side``,
``router_side``, ``deploy``; not the harness, not the tests) to the rule.

What is still over it is in ``ALLOWED``, each entry with the size it had when
it was listed as its cap and the reason it is still one piece (the list
started with 32 entries and is empty now). The list only shrinks: an entry
that grows past its cap fails, so does a new module or class over the limit,
and so does an entry no longer over the limit (take it out, so it cannot
grow back). Split along concerns, not by one-line
pass-through members that forward to a part: let callers talk to the part.

Sizes count every line of a module, and a class from its first decorator to
its last line (docstring included).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("common", "robot_side", "operator_side", "router_side", "deploy")
MAX_MODULE_LINES = 400
MAX_CLASS_LINES = 300
#: the node packages were split first and stay without exceptions
NO_EXCEPTIONS = ("robot_side/node/", "operator_side/node/")

#: "path" (a module) or "path::Class" -> (its size when listed: the cap, why it is still one piece).
#: Empty: the 32 modules and classes listed when the rule came to the whole product have all
#: been split. An entry added here must say why the piece cannot be split yet, and it only
#: ever shrinks from there.
ALLOWED: dict[str, tuple[int, str]] = {}


def sizes(source: str) -> tuple[int, dict[str, int]]:
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


def over_the_limit(root: Path = ROOT) -> dict[str, int]:
    """Every product module and class at or over its limit, by its ``ALLOWED`` key."""
    found = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            where = path.relative_to(root).as_posix()
            lines, classes = sizes(path.read_text())
            if lines >= MAX_MODULE_LINES:
                found[where] = lines
            found |= {f"{where}::{c}": n for c, n in classes.items() if n >= MAX_CLASS_LINES}
    return found


def test_nothing_grows_past_the_limit_or_its_cap() -> None:
    problems = []
    for key, n in sorted(over_the_limit().items()):
        limit = MAX_CLASS_LINES if "::" in key else MAX_MODULE_LINES
        if key not in ALLOWED:
            problems.append(f"{key}: {n} lines (limit {limit}): split it along its concerns")
        elif n > ALLOWED[key][0]:
            problems.append(
                f"{key}: {n} lines, grew past its cap of {ALLOWED[key][0]}: split it, "
                "or move what you added into a part of its own"
            )
    assert not problems, "\n".join(problems)


def test_every_allowlist_entry_is_still_needed() -> None:
    over = over_the_limit()
    gone = [f"{key}: now under the limit or gone" for key in ALLOWED if key not in over]
    assert not gone, "take these out of ALLOWED (it only shrinks):\n" + "\n".join(gone)


def test_the_node_packages_have_no_exceptions() -> None:
    assert not [key for key in ALLOWED if key.startswith(NO_EXCEPTIONS)]


def test_the_size_check_sees_a_long_class_and_module(tmp_path: Path) -> None:
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_CLASS_LINES))
    lines, classes = sizes(f"@dataclass\nclass Big:\n{body}\n")
    assert classes == {"Big": MAX_CLASS_LINES + 2} and lines == MAX_CLASS_LINES + 2
    (tmp_path / "common").mkdir()
    (tmp_path / "common" / "big.py").write_text(f"class Big:\n{body}\n" + "\n" * MAX_MODULE_LINES)
    assert over_the_limit(tmp_path) == {
        "common/big.py": MAX_CLASS_LINES + 1 + MAX_MODULE_LINES,
        "common/big.py::Big": MAX_CLASS_LINES + 1,
    }
