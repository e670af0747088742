"""InMemoryServoBus: the in-process bus the operator node is tested on."""

from __future__ import annotations

import pytest

from common.devices.lifecycle import build_device
from common.errors import ConfigError, DeviceNotConnectedError
from operator_side.servos import KINDS
from operator_side.servos.calibration import (
    LinkGlideCalibration,
    ServoCalibration,
    save_calibration,
)
from operator_side.servos.in_memory import InMemoryServoBus, InMemoryServoBusConfig
from operator_side.servos.limits import GoalOutOfLimitsError


def _goals(value: int) -> dict[int, int]:
    return {i: value for i in range(1, 7)}


def test_records_each_write_with_time_and_positions_follow() -> None:
    with InMemoryServoBus() as bus:
        bus.write_goals(_goals(2000))
        bus.write_goals({1: 2100, 2: 2200})
        recs = bus.records
        assert [r.goals for r in recs] == [_goals(2000), {1: 2100, 2: 2200}]
        assert recs[0].t_ns <= recs[1].t_ns
        pos = bus.read_positions()
        assert pos[1] == 2100 and pos[2] == 2200 and pos[3] == 2000


@pytest.mark.parametrize("bad", [1023, 3801, -1, 5000])
def test_out_of_limit_counts_are_refused_and_not_recorded(bad: int) -> None:
    with InMemoryServoBus() as bus:
        bus.write_goals(_goals(2048))
        goals = _goals(2048)
        goals[4] = bad
        with pytest.raises(GoalOutOfLimitsError, match="servo 4"):
            bus.write_goals(goals)
        assert len(bus.records) == 1
        assert bus.read_positions()[4] == 2048
        assert bus.status()["refused"] == 1


def test_unknown_id_and_non_integer_refused() -> None:
    with InMemoryServoBus() as bus:
        with pytest.raises(GoalOutOfLimitsError, match="id 7"):
            bus.write_goals({7: 2048})
        with pytest.raises(GoalOutOfLimitsError, match="not an integer"):
            bus.write_goals({1: 2048.5})
        assert bus.records == []


def test_bounded_records() -> None:
    with InMemoryServoBus(InMemoryServoBusConfig(max_records=3)) as bus:
        for v in range(2000, 2010):
            bus.write_goals(_goals(v))
        assert [r.goals[1] for r in bus.records] == [2007, 2008, 2009]


def test_not_connected() -> None:
    bus = InMemoryServoBus()
    with pytest.raises(DeviceNotConnectedError, match="connect"):
        bus.write_goals(_goals(2048))


def test_built_from_scene_section_with_calibration_file(tmp_path) -> None:
    servos = [ServoCalibration(id=i, min_counts=1500, max_counts=2500) for i in range(1, 7)]
    path = tmp_path / "cal.toml"
    save_calibration(LinkGlideCalibration(servos=servos), path)
    bus = build_device(KINDS, {"kind": "in_memory", "calibration_file": str(path)}, "servos")
    with bus:
        bus.write_goals(_goals(2400))
        with pytest.raises(GoalOutOfLimitsError):
            bus.write_goals(_goals(2600))


def test_inline_calibration_from_scene_section() -> None:
    section = {
        "kind": "in_memory",
        "max_records": 5,
        "calibration": {
            "servos": [{"id": i, "min_counts": 100, "max_counts": 200} for i in range(1, 7)]
        },
    }
    bus = build_device(KINDS, section, "servos")
    with bus:
        bus.write_goals(_goals(150))
        with pytest.raises(GoalOutOfLimitsError):
            bus.write_goals(_goals(201))
    with pytest.raises(ConfigError, match="max_records"):
        build_device(KINDS, {"kind": "in_memory", "max_records": 0}, "servos")


def test_every_bus_checks_limits_itself_and_returns_what_it_sent() -> None:
    """The check is ServoBus's: a bus that only puts bytes on the wire cannot skip it."""
    from operator_side.servos.base import ServoBus

    class WireOnlyBus(ServoBus):
        Config = dict
        calibration = LinkGlideCalibration()
        is_connected = True

        def __init__(self) -> None:
            self.sent: list[dict[int, int]] = []

        def connect(self) -> None: ...

        def disconnect(self) -> None: ...

        def _write_goals(self, goals: dict[int, int]) -> None:
            self.sent.append(goals)

        def read_positions(self) -> dict[int, int]:
            return {}

        def set_torque(self, enabled: bool) -> None: ...

    bus = WireOnlyBus()
    assert bus.write_goals({1: 2048.0}) == {1: 2048}
    with pytest.raises(GoalOutOfLimitsError, match="servo 2"):
        bus.write_goals({1: 2048, 2: 5000})
    assert bus.sent == [{1: 2048}] and bus.refused_writes == 1


def test_the_old_kind_name_is_refused_with_the_new_one() -> None:
    """``recording`` servos recorded nothing; a config still naming them is told the new name."""
    with pytest.raises(ConfigError, match=r"servos\.kind = 'recording' has been renamed: "):
        build_device(KINDS, {"kind": "recording"}, "operator.servos")
    with pytest.raises(ConfigError, match="write kind = 'in_memory'"):
        build_device(KINDS, {"kind": "recording"}, "operator.servos")
