"""The palm probe sees every goal the servos were given, not only the goals on each panel."""

from __future__ import annotations

import json

from harness.faults.probes import PalmProbe

RETRACT = [3783, 2361, 3783, 2361, 3783, 2361]
PRESSED = [3000, 3000, 3000, 3000, 3000, 3000]


def _panel(path, t_ns: int, goals: list[int], log: list[list[int]]) -> None:
    path.write_text(
        json.dumps(
            {"t_ns": t_ns, "goals": {str(i + 1): g for i, g in enumerate(goals)}, "goal_log": log}
        )
    )


def test_a_lift_between_two_panels_is_seen_at_the_bus_time(tmp_path):
    """The palm pressed on both panels; between them it lifted off for 30 ms."""
    status = tmp_path / "servos.json"
    probe = PalmProbe(status, RETRACT)
    _panel(status, 1_000_000_000, PRESSED, [[990_000_000, i + 1, 3000] for i in range(6)])
    assert probe.read() > 0
    lift = [[1_005_000_000, i + 1, RETRACT[i]] for i in range(6)]
    press = [[1_035_000_000, i + 1, 3000] for i in range(6)]
    _panel(status, 1_060_000_000, PRESSED, lift + press)
    assert probe.read() > 0  # the panel itself shows the palm pressed again
    replayed = [(s.t_s, s.value) for s in probe.samples]
    off = [t for t, v in replayed if v == 0]
    assert off == [1.005], replayed  # all six retracted at the bus's time of the last write
    assert [t for t, _ in replayed] == sorted(t for t, _ in replayed)


def test_a_probe_started_after_a_nodes_first_writes_still_sees_its_retract(tmp_path):
    """The first panel a late probe reads already shows the palm pressed; its log still holds
    the node's retract before the press (a half-written pose before it is no sample)."""
    status = tmp_path / "servos.json"
    probe = PalmProbe(status, RETRACT)
    partial = [[900_000_000, 1, 3000]]
    retract = [[950_000_000 + i, i + 1, RETRACT[i]] for i in range(6)]
    press = [[990_000_000 + i, i + 1, 3000] for i in range(6)]
    _panel(status, 1_000_000_000, PRESSED, partial + retract + press)
    assert probe.read() > 0
    replayed = [(round(s.t_s, 3), s.value) for s in probe.samples]
    assert replayed[0] == (0.95, 0.0), replayed  # nothing before the pose was whole
    assert replayed[-1] == (0.99, 783.0) and len(replayed) == 7, replayed  # then each write
