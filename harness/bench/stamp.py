"""What a measurement is stamped with: the commit it measured.

Every section that writes its own report (the runner's, the fault matrix's,
the task table's cells, the video-through-netsim rows) stamps the same way,
from this module, which imports none of them.
"""

from __future__ import annotations

import subprocess


def git_commit() -> str | None:
    """The checked-out commit (short hash), or None outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5
        )
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None
