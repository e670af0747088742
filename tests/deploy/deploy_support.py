"""Helpers the deploy tests share (conftest.py holds only fixtures: a module named
conftest is ambiguous when several test folders have one)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "deploy" / "config"
ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def cli(*args: str) -> list[str]:
    """The command line a systemd unit runs, through this interpreter."""
    return [sys.executable, "-m", "deploy.cli", *args]


def loopback(port: int) -> str:
    return f"tcp://127.0.0.1:{port}"
