"""Imports point one way (docs/architecture.md, "Packages and the data path").

``common`` is at the bottom and imports no other package; ``robot_side``,
``operator_side`` and ``router_side`` import ``common`` and never each other;
``deploy`` is above them and may import all of them; ``harness`` (the bench,
the fault matrix, the fleet, the soak) sits above the whole product and
nothing in the product imports it. Every import counts,
at module level or inside a function (a lazy import still ties the packages
together), and so does ``importlib.import_module("...")`` with a literal name.

Within and across packages, no two modules import each other, directly or
round a longer circle: a circle means neither can be read, tested or moved
without the other. Nor do two folders (packages), round any loop: a folder is
a room, and one room importing another that imports it back (through any of
their modules) is two rooms that are one. A package's own top-level modules
count as its folder, so they are either below its folders (imported by them)
or above them (commands that import them), never both.
"""

from __future__ import annotations

import ast
import functools
import itertools
from collections import deque
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NODES = ("robot_side", "operator_side", "router_side")
#: package -> the project packages its modules may import
ALLOWED: dict[str, frozenset[str]] = {
    "common": frozenset({"common"}),
    **{node: frozenset({"common", node}) for node in NODES},
    "deploy": frozenset({"common", *NODES, "deploy"}),
    "harness": frozenset({"common", *NODES, "deploy", "harness"}),
}


#: circles known and being taken apart elsewhere; each entry names its modules. The
#: check fails when one is gone (delete its entry) as when a new one appears.
KNOWN_CIRCLES: dict[frozenset[str], str] = {}


@functools.cache
def _parsed(path: Path) -> ast.Module:
    """Each file parsed once for every check of this module."""
    return ast.parse(path.read_text(), str(path))


def _is_import_module(node: ast.AST) -> bool:
    return (
        isinstance(node, ast.Call)
        and isinstance(node.func, (ast.Attribute, ast.Name))
        and (getattr(node.func, "attr", None) or getattr(node.func, "id", None)) == "import_module"
        and bool(node.args)
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
    )


def _imported(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, module) for every absolute import in ``tree``, wherever it sits."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif _is_import_module(node):
            found.append((node.lineno, node.args[0].value))
    return found


def upward_imports(root: Path) -> list[str]:
    """``path:line: package -> module`` for every import ``ALLOWED`` does not allow."""
    wrong = []
    for package, allowed in ALLOWED.items():
        for path in sorted((root / package).rglob("*.py")):
            tree = _parsed(path)
            for line, module in _imported(tree):
                target = module.split(".")[0]
                if target in ALLOWED and target not in allowed:
                    wrong.append(f"{path.relative_to(root)}:{line}: {package} -> {module}")
    return wrong


def _modules(root: Path) -> dict[str, tuple[Path, bool]]:
    """dotted name -> (file, is a package's ``__init__``) for every module of the house."""
    modules = {}
    for package in ALLOWED:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            is_package = parts[-1] == "__init__"
            modules[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return modules


def import_graph(root: Path) -> dict[str, dict[str, int]]:
    """module -> {module it imports: first line} over the house's own modules.

    Every import counts, at module level or in a function, relative ones
    resolved, ``importlib.import_module`` with a literal name too. ``from p
    import x`` points at module ``p.x`` when there is one, else at ``p``; an
    import points at the one module it names, not at the packages above it.
    """
    modules = _modules(root)

    def known(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, dict[str, int]] = {name: {} for name in modules}
    for name, (path, is_package) in modules.items():
        here = name.split(".") if is_package else name.split(".")[:-1]
        for node in ast.walk(_parsed(path)):
            targets: list[str] = []
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(here[: len(here) - node.level + 1] + [base] * bool(base))
                targets = [
                    f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                    for a in node.names
                ]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif _is_import_module(node):
                targets = [node.args[0].value]
            for target in filter(None, map(known, targets)):
                if target != name:
                    graph[name].setdefault(target, node.lineno)
    return graph


def _strongly_connected(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """Tarjan's components of more than one module, iteratively (no recursion limit)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(graph[start]))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(graph[child])))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def _one_circle(graph: dict[str, dict[str, int]], members: list[str]) -> list[str]:
    """The shortest way round from the component's first module back to it."""
    inside = set(members)
    first = members[0]
    came_from: dict[str, str] = {}
    queue = deque([first])
    while queue:
        node = queue.popleft()
        for child in graph[node]:
            if child == first:
                path = [node]
                while path[-1] != first:
                    path.append(came_from[path[-1]])
                return [first, *reversed(path[:-1]), first]
            if child in inside and child not in came_from:
                came_from[child] = node
                queue.append(child)
    raise AssertionError(f"{members} is no circle")  # a component always has one


def import_circles(root: Path) -> dict[frozenset[str], str]:
    """Each set of modules that import each other -> one circle through them, with lines."""
    graph = import_graph(root)
    circles = {}
    for members in _strongly_connected(graph):
        way = _one_circle(graph, members)
        steps = [f"{a} (line {graph[a][b]}) -> {b}" for a, b in itertools.pairwise(way)]
        extra = sorted(set(members) - set(way))
        circles[frozenset(members)] = "; ".join(steps) + (f"; and through {extra}" if extra else "")
    return circles


def test_no_import_circle_in_the_house():
    circles = import_circles(ROOT)
    new = {m: way for m, way in circles.items() if m not in KNOWN_CIRCLES}
    gone = [name for m, name in KNOWN_CIRCLES.items() if m not in circles]
    assert not new, (
        "modules that import each other; move what both need into a module of its own, "
        "or make one of them stop calling the other:\n" + "\n".join(new.values())
    )
    assert not gone, f"no longer circles, delete them from KNOWN_CIRCLES: {gone}"


def _folder(name: str, modules: dict[str, tuple[Path, bool]]) -> str:
    """The folder (package) a module sits in; a package's ``__init__`` is its own folder's."""
    return name if modules[name][1] else name.rpartition(".")[0]


def folder_loops(root: Path) -> dict[frozenset[str], str]:
    """Each set of folders that import each other, round a loop -> the loop, with one import
    (module and line) for each step."""
    modules = _modules(root)
    graph = import_graph(root)
    #: folder -> {folder it imports: (module, line) of its first import there}
    folders: dict[str, dict[str, tuple[str, int]]] = {_folder(m, modules): {} for m in modules}
    for name, targets in graph.items():
        here = _folder(name, modules)
        for target, line in targets.items():
            there = _folder(target, modules)
            if there != here:
                folders[here].setdefault(there, (name, line))
    plain = {folder: dict.fromkeys(targets, 0) for folder, targets in folders.items()}
    loops = {}
    for members in _strongly_connected(plain):
        way = _one_circle(plain, members)
        steps = [
            f"{a} -> {b} ({folders[a][b][0]}, line {folders[a][b][1]})"
            for a, b in itertools.pairwise(way)
        ]
        extra = sorted(set(members) - set(way))
        loops[frozenset(members)] = "; ".join(steps) + (f"; and through {extra}" if extra else "")
    return loops


def test_no_loop_between_folders():
    loops = folder_loops(ROOT)
    assert not loops, (
        "folders that import each other round a loop; move what both need into the folder "
        "below (or a room of its own), or the importer up:\n" + "\n".join(loops.values())
    )


def test_a_loop_between_folders_fails_the_check(tmp_path):
    """Two rooms that import each other through different modules loop; a command at a
    package's top importing its rooms, while a room imports a module at that top, loops
    too; a room importing the one below it does not."""
    root = _tree(
        tmp_path,
        {
            "robot_side/camera/__init__.py": "",
            "robot_side/camera/pattern.py": "from robot_side.video.stamp import draw\n",
            "robot_side/video/__init__.py": "",
            "robot_side/video/stamp.py": "",
            "robot_side/video/config.py": "from robot_side.camera import pattern\n",
            "operator_side/node_cli.py": "from operator_side.node.loop import run\n",
            "operator_side/config.py": "",
            "operator_side/node/__init__.py": "",
            "operator_side/node/loop.py": "def run():\n    from operator_side.config import C\n",
            "common/wire/__init__.py": "",
            "common/wire/codec.py": "from common.clocks.clock import now\n",
            "common/clocks/__init__.py": "",
            "common/clocks/clock.py": "",
        },
    )
    assert folder_loops(root) == {
        frozenset({"robot_side.camera", "robot_side.video"}): "robot_side.camera -> "
        "robot_side.video (robot_side.camera.pattern, line 1); robot_side.video -> "
        "robot_side.camera (robot_side.video.config, line 1)",
        frozenset({"operator_side", "operator_side.node"}): "operator_side -> "
        "operator_side.node (operator_side.node_cli, line 1); operator_side.node -> "
        "operator_side (operator_side.node.loop, line 2)",
    }


def test_an_import_circle_fails_the_check(tmp_path):
    """A circle through a lazy, a relative and an ``import_module`` import is named; a
    diamond (two modules importing a third) is no circle."""
    root = _tree(
        tmp_path,
        {
            "harness/bench/__init__.py": "",
            "harness/bench/runner.py": "from harness.bench import sections\n",
            "harness/bench/sections.py": "from . import faults, stamp\n",
            "harness/bench/faults.py": "def run():\n    from .runner import git_commit\n",
            "harness/bench/stamp.py": "import subprocess\n",
            "harness/bench/task.py": "from harness.bench.stamp import git_commit\n",
            "deploy/a.py": "import importlib\nimportlib.import_module('deploy.b')\n",
            "deploy/b.py": "from deploy import a\n",
            "common/c.py": "from common import d\n",
            "common/d.py": "from common.e import x\n",
            "common/e.py": "from common.d import y\n",
        },
    )
    assert import_circles(root) == {
        frozenset({"deploy.a", "deploy.b"}): "deploy.a (line 2) -> deploy.b; "
        "deploy.b (line 1) -> deploy.a",
        frozenset({"common.d", "common.e"}): "common.d (line 1) -> common.e; "
        "common.e (line 1) -> common.d",
        frozenset(
            {"harness.bench.runner", "harness.bench.sections", "harness.bench.faults"}
        ): "harness.bench.faults (line 2) -> harness.bench.runner; "
        "harness.bench.runner (line 1) -> harness.bench.sections; "
        "harness.bench.sections (line 1) -> harness.bench.faults",
    }


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
            "router_side/router.py": "from robot_side import node\n",
            "deploy/cli.py": "import common, robot_side, operator_side, router_side, deploy\n",
            "deploy/demo.py": "def run():\n    from harness.fleet import Fleet\n",
            "deploy/plugins.py": "import importlib\nimportlib.import_module('harness.bench.cli')\n",
            "common/harnessed.py": "import harness\n",
            "harness/soak.py": "from deploy.demo import run\nfrom robot_side import node\n",
        },
    )
    assert upward_imports(root) == [
        "common/harnessed.py:1: common -> harness",
        "common/up.py:1: common -> robot_side.node",
        "robot_side/by_name.py:2: robot_side -> deploy.cli",
        "robot_side/lazy.py:2: robot_side -> deploy.scene",
        "robot_side/sideways.py:1: robot_side -> operator_side.node",
        "router_side/router.py:1: router_side -> robot_side",
        "deploy/demo.py:2: deploy -> harness.fleet",
        "deploy/plugins.py:2: deploy -> harness.bench.cli",
    ]
