"""The browser driver the dashboard tests use; it lives in ``deploy/headless_chromium.py``
(the video benchmark drives the same browser). Also runnable: ``python
tests/dashboard/headless_chromium.py URL OUT.png`` screenshots a page."""

from __future__ import annotations

import os
import sys

import pytest

from deploy.headless_chromium import BrowserError, Chromium, chromium_path, main

# Browser tests skip without chromium, except in CI, where they must run.
needs_chromium = pytest.mark.skipif(
    chromium_path() is None and not os.environ.get("CI"),
    reason="chromium is not installed: run scripts/install-test-system-packages.sh "
    "(required in CI)",
)

__all__ = ["BrowserError", "Chromium", "chromium_path", "main", "needs_chromium"]

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
