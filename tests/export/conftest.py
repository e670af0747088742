"""The LeRobot interpreter the export tests load their datasets with."""

from __future__ import annotations

import pytest
from lerobot_env import LeRobot


@pytest.fixture(scope="session")
def lerobot(tmp_path_factory):
    """One LeRobot interpreter for every load a test process asks: importing LeRobot costs
    about 12 s of CPU, a load of a demo's dataset a second or two. Started at the first test
    that asks for it; a worker that runs no such test starts none."""
    with LeRobot(tmp_path_factory.mktemp("lerobot"), policies=True) as server:
        yield server
