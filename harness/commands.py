"""The harness's ``deepxpalm`` subcommands, as the product's command finds them.

pyproject.toml names each one in the ``deepxpalm.commands`` entry-point group;
each is ``(module, one-line help)``, the shape of ``deploy.cli.SUBCOMMANDS``.
Loading this module imports nothing else, so listing the commands never pays
for the bench's numpy or pinned thread pools; only the chosen module is imported.
"""

from __future__ import annotations

BENCH = ("harness.bench.cli", "latency budget, run time against error: docs/benchmarks.md")
SOAK = ("harness.soak", "run the demo for a long time on a bad link and report how it aged")
