"""The relay host installs the base package only: the relay loads no node, no torch, no crypto."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.untimed]  # no timing checked


def test_the_relay_loads_neither_node_nor_torch_nor_a_signing_library():
    probe = (
        "import sys\n"
        "import relay_side.cli, relay_side.relay\n"
        "heavy = sorted({m.split('.')[0] for m in sys.modules} & "
        "{'torch', 'numba', 'robot_side', 'operator_side', 'cryptography', 'nacl'})\n"
        "print('HEAVY', heavy)\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "HEAVY []" in out.stdout, out.stdout
