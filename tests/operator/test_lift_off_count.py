"""A lift-off is the palm leaving a fresh stimulus, not a first stimulus that came in stale."""

from __future__ import annotations

from test_heartbeat_confirms import CELLS, Rig, _stimulus


def test_only_leaving_a_fresh_stimulus_counts_as_a_lift_off():
    rig = Rig()
    node, clock = rig.node, rig.clock

    # the first stimulus is read only after it went stale (a node starved at its start):
    # the palm was never on, so nothing lifted
    rig.link.deliver(_stimulus(1, clock(), CELLS, keyframe=False), clock())
    node.receive()
    clock.advance(2 * rig.stale_ns)
    node.palm_step(clock(), rig.period)
    assert node.link_state == "stale"
    assert node.counters["lift_offs"] == 0

    # a fresh one puts the palm on; its silence past the staleness limit lifts it: one lift-off
    rig.deliver(_stimulus(2, clock(), CELLS, keyframe=False))
    assert node.link_state == "ok"
    clock.advance(rig.stale_ns + rig.period)
    node.palm_step(clock(), rig.period)
    assert node.link_state == "stale"
    assert node.counters["lift_offs"] == 1
