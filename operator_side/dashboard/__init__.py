"""The operator's live dashboard: a local web page fed over a WebSocket.

Only the config is imported eagerly: ``operator_side.node.config`` holds a
``DashboardConfig`` and must stay importable where ``websockets`` is not
installed. ``Dashboard`` loads the server on first use.
"""

from __future__ import annotations

from typing import Any

from operator_side.dashboard.config import DashboardConfig

__all__ = ["Dashboard", "DashboardConfig"]


def __getattr__(name: str) -> Any:
    if name == "Dashboard":
        from operator_side.dashboard.server import Dashboard

        return Dashboard
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
