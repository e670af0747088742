"""The bench's sections, in report order: the one table the runner, the report and the CLI read.

Each section is one module of ``harness/bench`` named as the section: its
sizes, the measuring code, ``measure``, ``markdown``, optional ``figure`` and
``verdicts``, ending in a ``SECTION``. Adding one is such a module and a line
below.
"""

from __future__ import annotations

from harness.bench import (
    across_sites,
    classifier,
    command_path,
    downsizing,
    e2e_inproc,
    e2e_tcp,
    faults,
    ik,
    keep_alive,
    netsim,
    node_cpu,
    scale,
    skipping,
    stages,
    stress,
    task,
    video,
    video_netsim,
)
from harness.bench.section import Section

SECTIONS: tuple[Section, ...] = (
    stages.SECTION,
    e2e_inproc.SECTION,
    e2e_tcp.SECTION,
    downsizing.SECTION,
    classifier.SECTION,
    ik.SECTION,
    skipping.SECTION,
    scale.SECTION,
    stress.SECTION,
    node_cpu.SECTION,
    keep_alive.SECTION,
    command_path.SECTION,
    video.SECTION,
    netsim.SECTION,
    video_netsim.SECTION,
    across_sites.SECTION,
    task.SECTION,
    faults.SECTION,
)
SECTION_NAMES: tuple[str, ...] = tuple(s.name for s in SECTIONS)
