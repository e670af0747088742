"""Imports point one way (docs/architecture.md, "Packages and the data path").

``common`` is at the bottom and imports no other package; ``robot_side``,
``operator_side`` and ``relay_side`` import ``common`` and never each other;
``deploy`` is above them and may import all of them; ``harness`` (the bench,
the fault matrix, the fleet, the soak) sits above the whole product and
nothing in the product imports it. Every import counts,
at module level or inside a function (a lazy import still ties the packages
together), and so does ``importlib.import_module("...")`` with a literal name.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NODES = ("robot_side", "operator_side", "relay_side")
#: package -> the project packages its modules may import
ALLOWED: dict[str, frozenset[str]] = {
    "common": frozenset({"common"}),
    **{node: frozenset({"common", node}) for node in NODES},
    "deploy": frozenset({"common", *NODES, "deploy"}),
    "harness": frozenset({"common", *NODES, "deploy", "harness"}),
}


def _imported(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, module) for every absolute import in ``tree``, wherever it sits."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, (ast.Attribute, ast.Name))
            and (getattr(node.func, "attr", None) or getattr(node.func, "id", None))
            == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            found.append((node.lineno, node.args[0].value))
    return found


def upward_imports(root: Path) -> list[str]:
    """``path:line: package -> module`` for every import ``ALLOWED`` does not allow."""
    wrong = []
    for package, allowed in ALLOWED.items():
        for path in sorted((root / package).rglob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            for line, module in _imported(tree):
                target = module.split(".")[0]
                if target in ALLOWED and target not in allowed:
                    wrong.append(f"{path.relative_to(root)}:{line}: {package} -> {module}")
    return wrong


def test_the_tree_imports_only_downward():
    wrong = upward_imports(ROOT)
    assert not wrong, (
        "these imports run against docs/architecture.md's directions (common at the bottom, "
        "deploy at the top, the three sides beside each other); move the code they need "
        "down, or the importer up:\n" + "\n".join(wrong)
    )


def test_every_package_is_scanned():
    """A package the table does not know would escape the check."""
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"tests"}
    assert packages == set(ALLOWED), f"add {packages - set(ALLOWED)} to ALLOWED (and the docs)"
    without_init = [
        str(d.relative_to(ROOT))
        for package in ALLOWED
        for d in (ROOT / package).rglob("*")
        if d.is_dir() and any(d.glob("*.py")) and not (d / "__init__.py").exists()
    ]
    assert not without_init, f"folders of modules without an __init__.py: {without_init}"


def _tree(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    for package in ALLOWED:
        (root / package).mkdir(exist_ok=True)
        (root / package / "__init__.py").touch()
    return root


def test_an_upward_import_fails_the_check(tmp_path):
    """Each way of reaching up is caught; sideways within a package and downward are not."""
    root = _tree(
        tmp_path,
        {
            "common/clock.py": "import numpy\nfrom common import config\n",
            "common/up.py": "from robot_side.node import RobotNode\n",
            "robot_side/node.py": "from common.clock import now_ns\n",
            "robot_side/lazy.py": "def run():\n    from deploy.scene import Scene\n",
            "robot_side/by_name.py": "import importlib\nimportlib.import_module('deploy.cli')\n",
            "robot_side/sideways.py": "import operator_side.node\n",
            "operator_side/node.py": "from . import config\nfrom common import codec\n",
            "relay_side/relay.py": "from robot_side import node\n",
            "deploy/cli.py": "import common, robot_side, operator_side, relay_side, deploy\n",
        },
    )
    assert upward_imports(root) == [
        "common/up.py:1: common -> robot_side.node",
        "robot_side/by_name.py:2: robot_side -> deploy.cli",
        "robot_side/lazy.py:2: robot_side -> deploy.scene",
        "robot_side/sideways.py:1: robot_side -> operator_side.node",
        "relay_side/relay.py:1: relay_side -> robot_side",
    ]
