"""The operator side stands alone: no robot-side code, no torch."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports, at module level or inside functions."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
    return found


def test_operator_side_never_imports_robot_side() -> None:
    offenders = {
        f"{path.relative_to(ROOT)}: {module}"
        for path in sorted((ROOT / "operator_side").rglob("*.py"))
        for module in _imported_modules(path)
        if module == "robot_side" or module.startswith("robot_side.")
    }
    assert not offenders, f"operator_side imports robot_side: {sorted(offenders)}"


def test_operator_node_and_study_load_without_torch_or_robot_side() -> None:
    code = (
        "import sys\n"
        "import operator_side.node, operator_side.node_cli\n"
        "import operator_side.study.cli, operator_side.study.display, operator_side.study.runner\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
        "robot = sorted(m for m in sys.modules if m.split('.')[0] == 'robot_side')\n"
        "assert not robot, f'robot-side modules were imported: {robot}'\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert out.returncode == 0, out.stderr
