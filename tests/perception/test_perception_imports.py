"""Every perception module imports on its own, and no two import each other."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.untimed]  # no timing checked

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "robot_side" / "perception"
MODULES = sorted(f"robot_side.perception.{p.stem}" for p in PACKAGE.glob("*.py"))
PROJECT = sorted(p.parent.name for p in ROOT.glob("*/__init__.py"))

#: One interpreter imports the third-party packages the modules need (torch alone is
#: seconds of CPU), then forks a child per module; the child, in which no project module
#: has been imported yet, imports the module and nothing else. A module that only imports
#: because another project module was imported before it still fails, as in a fresh
#: interpreter; one import of torch instead of one per module.
ZYGOTE = r"""
import importlib, json, os, sys, traceback
preload, project, modules = (json.loads(a) for a in sys.argv[1:4])
for name in preload:
    importlib.import_module(name)
leaked = sorted(m for m in sys.modules if m.partition(".")[0] in project)
assert not leaked, f"preloading imported project modules: {leaked}"
results = {}
for module in modules:
    r, w = os.pipe()
    sys.stdout.flush(); sys.stderr.flush()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        try:
            importlib.import_module(module)
            code = 0
        except BaseException:
            os.write(w, traceback.format_exc().encode())
            code = 1
        os._exit(code)
    os.close(w)
    with os.fdopen(r, "rb") as pipe:
        error = pipe.read().decode()
    _, status = os.waitpid(pid, 0)
    if os.waitstatus_to_exitcode(status) != 0 and not error:
        error = f"the child importing it ended with status {os.waitstatus_to_exitcode(status)}"
    results[module] = error or None
print(json.dumps(results))
"""


def _module_level_imports(path: Path) -> set[str]:
    """Modules ``path`` imports when it is imported: not in functions nor ``TYPE_CHECKING``."""
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            return
        if isinstance(node, ast.If) and ast.unparse(node.test).endswith("TYPE_CHECKING"):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text(), str(path)))
    return found


def _source(module: str) -> Path | None:
    base = ROOT.joinpath(*module.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def third_party_imports(modules: list[str]) -> list[str]:
    """Top-level third-party packages that importing ``modules`` imports, through the project.

    Only the packages themselves (``torch``, ``matplotlib``), never a submodule a module
    names (``matplotlib.pyplot``): each child imports those as a fresh interpreter would.
    """
    seen: set[str] = set()
    outside: set[str] = set()
    todo = list(modules)
    while todo:
        module = todo.pop()
        parts = module.split(".")
        for i in range(1, len(parts) + 1):  # a module's packages run their __init__ first
            name = ".".join(parts[:i])
            if name in seen:
                continue
            seen.add(name)
            top = parts[0]
            if top in PROJECT:
                source = _source(name)
                if source is not None:
                    todo.extend(_module_level_imports(source))
            elif top not in sys.stdlib_module_names and top != "__future__":
                outside.add(top)
    return sorted(outside)


@pytest.fixture(scope="module")
def imported_alone() -> dict[str, str | None]:
    """Each module's import error in a child of its own (None: it imported)."""
    preload = third_party_imports(MODULES)
    args = [json.dumps(preload), json.dumps(PROJECT), json.dumps(MODULES)]
    out = subprocess.run(
        [sys.executable, "-c", ZYGOTE, *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert out.returncode == 0, out.stderr[-4000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_the_shared_interpreter_preloads_the_heavy_packages_only() -> None:
    """What the children share is third-party; torch is among it (else nothing is saved)."""
    preload = third_party_imports(MODULES)
    assert "torch" in preload and "numpy" in preload
    assert not set(preload) & set(PROJECT)


@pytest.mark.parametrize("module", MODULES)
def test_module_imports_alone(module: str, imported_alone: dict[str, str | None]) -> None:
    assert imported_alone[module] is None, imported_alone[module]


def _perception_imports(path: Path) -> set[str]:
    """Perception modules ``path`` imports anywhere, at module level or inside functions."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.module == "robot_side.perception":
                found |= {f"robot_side.perception.{a.name}" for a in node.names}
            else:
                found.add(node.module)
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
    return {m for m in found if m in MODULES}


def test_no_import_cycle_between_perception_modules() -> None:
    graph = {
        f"robot_side.perception.{p.stem}": _perception_imports(p)
        for p in PACKAGE.glob("*.py")
        if p.stem != "__init__"
    }
    done: set[str] = set()

    def visit(module: str, path: tuple[str, ...]) -> None:
        if module in path:
            cycle = " -> ".join((*path[path.index(module) :], module))
            pytest.fail(f"import cycle: {cycle}")
        if module in done or module not in graph:
            return
        for dep in sorted(graph[module]):
            visit(dep, (*path, module))
        done.add(module)

    for module in sorted(graph):
        visit(module, ())
