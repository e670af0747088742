"""Signed telemetry is believed once, fresh, from the robot's current run (the palm's side).

The operator node is driven in virtual time through a capture link, with the
robot's real signing key: each case says what the palm does (servo goals).
"""

from __future__ import annotations

import numpy as np
import pytest

from common.clocks.clock import VirtualClock
from common.wire.codec import decode, encode
from common.wire.messages import Heartbeat, Stimulus, TactileFrame
from common.wire.signing import Signer, generate_key_files, load_signer
from common.wire.transport import CaptureLink
from operator_side.node import OperatorNode
from operator_side.node.config import OperatorConfig
from operator_side.node.telemetry_gate import (
    FROM_FUTURE,
    OLD_SESSION,
    REPLAYED,
    STALE,
    UNPROVEN,
    WITHOUT_SESSION,
    TelemetryGate,
)
from operator_side.servos.in_memory import InMemoryServoBus

MS = 1_000_000
RUN_A, RUN_B = 0xA11CE, 0xB0B


class Rig:
    """An operator node holding the robot's public key; the robot's signer beside it."""

    def __init__(self, tmp_path) -> None:
        public, secret = generate_key_files(tmp_path, "cell1")
        self.robot = load_signer(secret)
        self.clock = VirtualClock(t_ns=5_000 * MS)
        self.link = CaptureLink()
        self.bus = InMemoryServoBus()
        self.bus.connect()
        config = OperatorConfig()
        config.link.robot_key_file = public
        self.node = OperatorNode(config, self.bus, now=self.clock, link=self.link)
        self.period = round(1e9 / self.node.config.renderer.palm_step_rate_hz)
        self.seq = {RUN_A: 0, RUN_B: 0}

    def signed(self, msg, signer: Signer | None = None):
        """As the operator's socket hands it over: the bytes signed, verified, decoded."""
        return decode(encode(msg, b"cell1", signer or self.robot))

    def deliver(self, msg, late_ns: int = 0) -> None:
        self.link.deliver(msg, self.clock() + late_ns)
        self.node.receive()
        self.node.palm_step(self.clock(), self.period)

    def stimulus(self, session: int | None, cells=(5, 5, 5), seq: int | None = None):
        if seq is None:
            self.seq[session] = self.seq.get(session, 0) + 1
            seq = self.seq[session]
        t = self.clock()
        grid = np.zeros((3, 3), np.float32)
        for row, v in enumerate(cells):
            grid[row, 1] = v
        return self.signed(
            Stimulus(
                seq=seq,
                t_send_ns=t,
                t_capture_ns=t,
                frame_seq=seq,
                mode="direct",
                contact=True,
                stimulus=grid,
                session=session,
            )
        )

    def answer(self, session: int, seq: int = 1, echo: int | None = None):
        """A robot heartbeat of ``session`` answering our newest heartbeat (or ``echo``)."""
        if echo is None:
            self.node._send_heartbeat()
            echo = [m for m in self.link.messages if isinstance(m, Heartbeat)][-1].t_send_ns
            self.clock.advance(2 * MS)
        hb = Heartbeat(
            seq=seq,
            t_send_ns=self.clock() - MS,
            node="robot",
            state="ok",
            echo_t_send_ns=echo,
            echo_t_recv_ns=self.clock() - MS,
            session=session,
        )
        return self.signed(hb)

    def goals(self):
        return self.node.written_goals

    def count(self, name: str) -> int:
        return self.node.counters[name]


def test_an_unanswered_run_is_not_believed_and_an_answer_makes_the_palm_feel_it(tmp_path):
    rig = Rig(tmp_path)
    rig.deliver(rig.stimulus(RUN_A))
    assert rig.count(UNPROVEN) == 1 and rig.node.last_stimulus is None
    assert rig.goals() in (None, rig.node.renderer.retract_goals), "the palm stays free"
    rig.deliver(rig.answer(RUN_A))
    assert rig.count("telemetry_sessions") == 1
    rig.deliver(rig.stimulus(RUN_A))
    assert rig.node.last_stimulus is not None and rig.goals() != rig.node.renderer.retract_goals


def test_a_heartbeat_answering_an_old_or_foreign_heartbeat_proves_nothing(tmp_path):
    rig = Rig(tmp_path)
    rig.node._send_heartbeat()
    old = [m for m in rig.link.messages if isinstance(m, Heartbeat)][-1].t_send_ns
    rig.clock.advance(3_000 * MS)  # past the proof window: a recording made back then
    rig.deliver(rig.answer(RUN_A, echo=old))
    rig.deliver(rig.answer(RUN_A, seq=2, echo=rig.clock() - 5 * MS))  # not a time we sent
    assert rig.count(UNPROVEN) == 2 and rig.count("telemetry_sessions") == 0


def test_signed_telemetry_without_a_session_is_refused_by_name(tmp_path, caplog):
    rig = Rig(tmp_path)
    rig.deliver(rig.stimulus(None, seq=1))
    assert rig.count(WITHOUT_SESSION) == 1 and rig.node.last_stimulus is None
    assert "predates the replay window" in caplog.text


def test_a_replayed_stimulus_is_refused_counted_and_moves_nothing(tmp_path, caplog):
    rig = Rig(tmp_path)
    rig.deliver(rig.answer(RUN_A))
    captured = rig.stimulus(RUN_A, cells=(5, 0, 0))
    rig.deliver(captured)
    rig.clock.advance(20 * MS)
    rig.deliver(rig.stimulus(RUN_A, cells=(0, 0, 5)))
    targets = rig.count("targets_computed")
    rig.clock.advance(10 * MS)
    rig.deliver(captured)  # 30 ms later: younger than the age limit, so only the window stops it
    assert rig.count(REPLAYED) == 1
    assert rig.count("targets_computed") == targets, "the palm got no new goal from it"
    assert rig.node.last_stimulus.stimulus[2, 1] == 5
    assert "Stimulus telemetry_replayed: run 00000000000a11ce, seq 1" in caplog.text


def test_send_times_far_from_the_clock_estimate_are_refused(tmp_path):
    rig = Rig(tmp_path)
    rig.deliver(rig.answer(RUN_A))
    age = round(rig.node.config.link.max_telemetry_age_ms * MS)
    rig.deliver(rig.stimulus(RUN_A), late_ns=age + MS)  # held back on the path, then released
    assert rig.count(STALE) == 1
    rig.deliver(rig.stimulus(RUN_A), late_ns=-(age + MS))  # stamped in the future
    assert rig.count(FROM_FUTURE) == 1
    assert rig.node.last_stimulus is None
    rig.deliver(rig.stimulus(RUN_A), late_ns=age - MS)
    assert rig.node.last_stimulus is not None, "a slow link within the limit still renders"


def test_reordering_within_the_window_is_accepted_once_and_beyond_it_refused(tmp_path):
    rig = Rig(tmp_path)
    rig.deliver(rig.answer(RUN_A))
    width = TelemetryGate.WIDTH

    def frame(seq: int):
        t = rig.clock.advance(MS)  # an honest robot's send times rise with its seqs
        return rig.signed(
            TactileFrame(
                seq=seq,
                t_send_ns=t,
                t_capture_ns=t,
                frame_seq=seq,
                frame=np.zeros((2, 10, 10), np.float32),
                session=RUN_A,
            )
        )

    late = frame(1)
    skipped = frame(width)
    rig.deliver(frame(2))
    rig.deliver(late)  # overtaken by one: accepted
    rig.deliver(late)  # the same again: a replay
    assert rig.count(REPLAYED) == 1
    rig.deliver(frame(width + 1))
    rig.deliver(skipped)  # just inside: width - 1 behind
    rig.deliver(frame(3))  # width - 2 behind, never seen: inside too
    assert rig.count(REPLAYED) == 1
    rig.deliver(frame(1 + 1))  # width - 1 behind but already accepted
    rig.deliver(frame(1))  # width behind: outside the window
    assert rig.count(REPLAYED) == 3


def test_a_restarted_robot_is_believed_and_its_earlier_run_refused_after(tmp_path):
    rig = Rig(tmp_path)
    rig.deliver(rig.answer(RUN_A))
    for _ in range(30):  # the first run ran a while: its seqs are far above the new run's
        rig.clock.advance(10 * MS)
        rig.deliver(rig.stimulus(RUN_A))
    old = rig.stimulus(RUN_A, cells=(0, 9, 0))
    rig.clock.advance(10 * MS)
    rig.deliver(rig.stimulus(RUN_B))  # the new run speaks before it answered us
    assert rig.count(UNPROVEN) == 1
    rig.deliver(rig.answer(RUN_B))
    rig.deliver(rig.stimulus(RUN_B, cells=(0, 0, 3)))  # seq 2, far below the old run's 31
    assert rig.node.last_stimulus.session == RUN_B, "a restart is not mistaken for reordering"
    targets = rig.count("targets_computed")
    rig.deliver(old)  # a stimulus of the earlier run, however fresh it looks
    assert rig.count(OLD_SESSION) == 1
    assert rig.count("targets_computed") == targets and rig.node.last_stimulus.session == RUN_B
    assert rig.count("telemetry_sessions") == 2


def test_a_forged_answer_cannot_make_a_run_believed(tmp_path):
    rig = Rig(tmp_path)
    rig.node._send_heartbeat()
    echo = [m for m in rig.link.messages if isinstance(m, Heartbeat)][-1].t_send_ns
    forged = Heartbeat(
        seq=1, t_send_ns=1, node="robot", state="ok", echo_t_send_ns=echo, session=RUN_A
    )
    rig.deliver(rig.signed(forged, Signer.generate()))
    assert rig.count("telemetry_forged") == 1 and rig.count("telemetry_sessions") == 0


@pytest.mark.parametrize("max_age_ns", [0, -1])
def test_the_age_limit_must_be_positive(max_age_ns):
    from common.clocks.clock_sync import ClockSync

    with pytest.raises(ValueError):
        TelemetryGate(ClockSync(), max_age_ns)
