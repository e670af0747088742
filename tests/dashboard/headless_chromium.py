"""The browser driver the dashboard tests use; it lives in ``deploy/headless_chromium.py``
(the video benchmark drives the same browser). Also runnable: ``python
tests/dashboard/headless_chromium.py URL OUT.png`` screenshots a page."""

from __future__ import annotations

import sys

from deploy.headless_chromium import BrowserError, Chromium, chromium_path, main

__all__ = ["BrowserError", "Chromium", "chromium_path", "main"]

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
