"""The operator side stands alone: no robot-side code, no torch.

That no operator_side module imports robot_side is checked with every other
package direction in tests/test_import_directions.py; here, what loads.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


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


def test_the_palm_lift_runs_without_numpy_or_zeromq(tmp_path) -> None:
    """``deepxpalm palm lift`` to a failed open (every import on its path done): no NumPy, no
    ZeroMQ. Its start-up is the time a dead node's linkages stay on the palm; NumPy alone
    takes about half a second to import."""
    code = (
        "import sys\n"
        "from deploy.cli import main\n"
        "code = main(['palm', 'lift', '--set', 'servos.kind=\"feetech\"', "
        f"'--set', 'servos.port=\"{tmp_path / 'no-such-tty'}\"'])\n"
        "heavy = sorted({m.split('.')[0] for m in sys.modules} & {'numpy', 'zmq', 'torch'})\n"
        "print(code, heavy)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert out.stdout.split("\n")[0] == "1 []", out.stdout + out.stderr
    assert "no-such-tty" in out.stderr, out.stderr  # it got as far as opening the bus
