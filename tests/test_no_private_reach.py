"""No production or bench module reaches into another module's private names.

A name with a leading underscore belongs to the module that defines it. The
bench promises its report cannot drift from what runs: that holds only if it
drives the nodes, sensors and renderers through the names they publish, not
by swapping their internals. So: no ``from m import _x``, no ``obj._x``
(read or assigned) unless this module defines ``_x`` itself, and no
assignment into an imported module (``robot_side.node.now_ns = ...``).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.untimed]  # no timing checked

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = (
    "robot_side",
    "operator_side",
    "router_side",
    "common",
    "deploy",
    "harness",
)
#: underscore names that are public API elsewhere (namedtuple's, the interpreter's)
PUBLIC_UNDERSCORE = {"_replace", "_asdict", "_fields", "_make", "_exit", "_getframe"}


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _own_names(tree: ast.Module) -> set[str]:
    """Every name this module defines: functions, classes, assigned names and attributes."""
    own: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            own.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            own.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
                own.add(node.attr)
        elif isinstance(node, ast.arg):
            own.add(node.arg)
    return own


def violations(path: Path) -> list[str]:
    """``path:line what`` for each private name of another module used in ``path``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    own = _own_names(tree)
    modules = {
        (a.asname or a.name).split(".")[0]
        for node in ast.walk(tree)
        if isinstance(node, ast.Import)
        for a in node.names
    }
    where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module != "__future__":
            found += [
                f"{where}:{node.lineno} imports {a.name} from {node.module}"
                for a in node.names
                if _private(a.name)
            ]
        elif isinstance(node, ast.Import):
            found += [
                f"{where}:{node.lineno} imports {a.name}"
                for a in node.names
                if any(_private(part) for part in a.name.split("."))
            ]
        elif (
            isinstance(node, ast.Attribute)
            and isinstance(node.ctx, ast.Store)
            and isinstance(node.value, ast.Name)
            and node.value.id in modules
        ):
            found.append(f"{where}:{node.lineno} assigns into a module: {ast.unparse(node)}")
        elif isinstance(node, ast.Attribute) and _private(node.attr):
            base = node.value
            if isinstance(base, ast.Name) and base.id in ("self", "cls"):
                continue
            if isinstance(base, ast.Call) and getattr(base.func, "id", None) == "super":
                continue
            if node.attr in own or node.attr in PUBLIC_UNDERSCORE:
                continue
            verb = "assigns" if isinstance(node.ctx, ast.Store) else "reads"
            found.append(f"{where}:{node.lineno} {verb} {ast.unparse(node)}")
    return found


def _modules() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def test_no_module_reaches_into_another_modules_private_names() -> None:
    found = [v for path in _modules() for v in violations(path)]
    assert not found, "private names used across modules:\n" + "\n".join(found)


@pytest.mark.parametrize(
    "source",
    [
        "from robot_side.rendering import _WEIGHTS\n",
        "import robot_side.node as m\nm.now_ns = lambda: 0\n",
        "node.pub._sent = 3\n",
        "def f(sensor):\n    return sensor._parser\n",
    ],
)
def test_the_check_sees_a_reach(tmp_path: Path, source: str) -> None:
    path = tmp_path / "probe.py"
    path.write_text(source)
    assert violations(path)


def test_the_check_lets_a_module_use_its_own_private_names(tmp_path: Path) -> None:
    path = tmp_path / "probe.py"
    path.write_text(
        "class A:\n    def __init__(self):\n        self._x = 1\n\n"
        "def peek(a: A) -> int:\n    return a._x\n"
    )
    assert violations(path) == []
