"""The goal packet the Feetech driver sends is byte for byte scservo_sdk's GroupSyncWrite."""

from __future__ import annotations

import numpy as np
import pytest
import scservo_sdk as sdk
from hypothesis import given
from hypothesis import strategies as st

from harness.bench.fixtures import CapturePort
from operator_side.servos.calibration import LinkGlideCalibration, ServoCalibration
from operator_side.servos.limits import GoalOutOfLimitsError, check_goals
from operator_side.servos.sts_registers import GOAL_POSITION
from operator_side.servos.sync_write import SyncWritePacket

pytestmark = pytest.mark.slow


def _sdk_packet(ids: list[int], values: list[int], protocol_end: int) -> bytes:
    port = CapturePort()
    handler = sdk.PacketHandler(protocol_end)
    try:
        group = sdk.GroupSyncWrite(port, handler, GOAL_POSITION.address, 2)
        for sid, value in zip(ids, values, strict=True):
            assert group.addParam(sid, [sdk.SCS_LOBYTE(value), sdk.SCS_HIBYTE(value)])
        assert group.txPacket() == sdk.COMM_SUCCESS
    finally:
        sdk.PacketHandler(0)  # the SDK's byte order is a global: leave it as STS
    return port.last_packet


@given(
    st.lists(st.integers(0, 253), min_size=1, max_size=12, unique=True).flatmap(
        lambda ids: st.tuples(
            st.just(ids), st.lists(st.integers(0, 0xFFFF), min_size=len(ids), max_size=len(ids))
        )
    ),
    st.sampled_from([0, 1]),
)
def test_packet_matches_the_sdk_for_any_ids_and_values(case, protocol_end) -> None:
    ids, values = case
    packet = SyncWritePacket(ids, GOAL_POSITION.address, big_endian=protocol_end == 1)
    assert bytes(packet.build(values)) == _sdk_packet(ids, values, protocol_end)
    # the buffer is reused: a second write with other values is right too
    other = [0xFFFF - v for v in values]
    assert bytes(packet.build(other)) == _sdk_packet(ids, other, protocol_end)


def test_bad_packets_are_refused_before_any_byte_changes() -> None:
    with pytest.raises(ValueError, match="distinct"):
        SyncWritePacket([1, 1], GOAL_POSITION.address)
    with pytest.raises(ValueError, match="distinct"):
        SyncWritePacket([254], GOAL_POSITION.address)
    packet = SyncWritePacket([1, 2], GOAL_POSITION.address)
    with pytest.raises(ValueError, match="2 servos"):
        packet.build([1])
    with pytest.raises(ValueError, match="2-byte"):
        packet.build([1, 70000])


_CAL = LinkGlideCalibration(
    servos=[ServoCalibration(id=i, min_counts=1000 + i, max_counts=3000 + i) for i in range(1, 7)]
)


@given(
    st.dictionaries(
        st.one_of(st.integers(-1, 8), st.integers(1, 6).map(np.int64)),
        st.one_of(
            st.integers(900, 3100),
            st.integers(900, 3100).map(float),
            st.floats(allow_nan=True),
            st.integers(900, 3100).map(np.int64),
            st.booleans(),
        ),
        max_size=7,
    )
)
def test_the_fast_check_agrees_with_the_full_one(goals) -> None:
    """check_goals' shortcut for plain in-range ints takes nothing the full check refuses."""
    by_id = {s.id: s for s in _CAL.servos}
    expect_ok = bool(goals) and all(
        int(k) in by_id
        and not isinstance(v, bool)
        and (isinstance(v, int | np.integer) or (isinstance(v, float) and v.is_integer()))
        and by_id[int(k)].min_counts <= int(v) <= by_id[int(k)].max_counts
        for k, v in goals.items()
    )
    if not expect_ok:
        with pytest.raises(GoalOutOfLimitsError):
            check_goals(_CAL, goals)
        return
    checked = check_goals(_CAL, goals)
    assert checked == {int(k): int(v) for k, v in goals.items()}
    assert all(type(k) is int and type(v) is int for k, v in checked.items())
