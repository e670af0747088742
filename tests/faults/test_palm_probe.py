"""The palm probe sees every goal the servos were given, not only the goals on each panel,
each at the bus's own time."""

from __future__ import annotations

import json

from harness.faults.probes import PalmProbe, Sample

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
    assert probe.read() is None  # its sample is at the panel's time, not returned for now
    assert probe.samples[-1] == Sample(1.0, 783.0)
    lift = [[1_005_000_000, i + 1, RETRACT[i]] for i in range(6)]
    press = [[1_035_000_000, i + 1, 3000] for i in range(6)]
    _panel(status, 1_060_000_000, PRESSED, lift + press)
    probe.read()
    assert probe.samples[-1] == Sample(1.06, 783.0)  # the panel itself shows the palm pressed
    replayed = [(s.t_s, s.value) for s in probe.samples]
    off = [t for t, v in replayed if v == 0]
    assert off == [1.005], replayed  # all six retracted at the bus's time of the last write
    assert [t for t, _ in replayed] == sorted(t for t, _ in replayed)


def test_a_panel_read_late_stands_at_its_own_time_before_later_writes(tmp_path):
    """Each panel's sample stands at the time the panel was written: read late (a starved
    probe), a panel stamped when read could stand after writes it does not hold."""
    status = tmp_path / "servos.json"
    probe = PalmProbe(status, RETRACT)
    _panel(status, 1_000_000_000, PRESSED, [[990_000_000, i + 1, 3000] for i in range(6)])
    probe.read()
    lift = [[1_020_000_000 + i, i + 1, RETRACT[i]] for i in range(6)]
    _panel(status, 1_040_000_000, RETRACT, lift)
    probe.read()
    _panel(status, 1_060_000_000, RETRACT, lift)
    probe.read()
    assert Sample(1.04, 0.0) in probe.samples and Sample(1.06, 0.0) in probe.samples
    times = [s.t_s for s in probe.samples]
    assert times == sorted(times), probe.samples
    after_lift = [s.value for s in probe.samples if s.t_s >= 1.025]
    assert set(after_lift) == {0.0}, probe.samples


def test_a_probe_started_after_a_nodes_first_writes_still_sees_its_retract(tmp_path):
    """The first panel a late probe reads already shows the palm pressed; its log still holds
    the node's retract before the press (a half-written pose before it is no sample)."""
    status = tmp_path / "servos.json"
    probe = PalmProbe(status, RETRACT)
    partial = [[900_000_000, 1, 3000]]
    retract = [[950_000_000 + i, i + 1, RETRACT[i]] for i in range(6)]
    press = [[990_000_000 + i, i + 1, 3000] for i in range(6)]
    _panel(status, 1_000_000_000, PRESSED, partial + retract + press)
    probe.read()
    replayed = [(round(s.t_s, 3), s.value) for s in probe.samples]
    assert replayed[0] == (0.95, 0.0), replayed  # nothing before the pose was whole
    assert replayed[-2] == (0.99, 783.0) and len(replayed) == 8, replayed  # then each write
    assert replayed[-1] == (1.0, 783.0), replayed  # and the panel, at its own time
