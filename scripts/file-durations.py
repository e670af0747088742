"""Each test file's time (and each long test's), from pytest's JUnit reports, for the lanes' order.

    python scripts/file-durations.py REPORT.xml [REPORT.xml ...] > tests/file_durations.json

A report comes from a lane run with ``--junitxml=REPORT.xml`` (a test's time
there is its setup, call and teardown). The lanes hand whole files to their
workers; ``tests/conftest.py`` puts the longest files first, so that no worker
starts a long file while the others are running out of work (the longest
first, the shortest last: the lane ends close to its average). Files the
reports do not name keep their place after the known ones. A test of at
least ``LONG_TEST_S`` is named too, by its node id: the files whose tests
are handed out one by one (``EACH_TEST_ON_ITS_OWN`` in tests/conftest.py)
are ordered test by test. Times are wall seconds on the machine that ran
the reports; only their order matters.
"""

from __future__ import annotations

import json
import sys
import xml.etree.ElementTree as ET
from collections import defaultdict

#: a test this long (s) is named by its node id as well as counted in its file
LONG_TEST_S = 10.0


def node_id(case: ET.Element) -> str:
    """tests/x/test_y.py::Class::test_name[param] from a testcase (classname ``tests.x.test_y``,
    a class appended)."""
    parts = case.get("classname", "").split(".")
    classes = []
    while parts and not parts[-1].startswith("test_"):
        classes.insert(0, parts.pop())  # a test class's name
    return "::".join(["/".join(parts) + ".py", *classes, case.get("name", "")])


def file_of(case: ET.Element) -> str:
    """tests/x/test_y.py: the file part of the testcase's node id."""
    return node_id(case).split("::", 1)[0]


def main(paths: list[str]) -> int:
    if not paths:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    seconds: dict[str, float] = defaultdict(float)
    for path in paths:
        for case in ET.parse(path).getroot().iter("testcase"):
            took = float(case.get("time", 0.0))
            seconds[file_of(case)] += took
            if took >= LONG_TEST_S:
                seconds[node_id(case)] += took
    ordered = dict(sorted(((f, round(s, 1)) for f, s in seconds.items()), key=lambda fs: -fs[1]))
    json.dump(ordered, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
