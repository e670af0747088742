"""The fleet recorder says what went missing: gaps in each sender's sequence numbers."""

from __future__ import annotations

import zmq
from tests_support import stimulus

from common.wire.codec import encode
from operator_side.record_cli import RecorderConfig, StreamRecorder


def _take(recorder: StreamRecorder, robot: bytes, seqs: list[int]) -> None:
    for s in seqs:
        recorder.take(encode(stimulus(seq=s), robot), 0)


def test_gaps_count_per_robot_and_a_restart_is_not_a_loss():
    ctx = zmq.Context()
    recorder = StreamRecorder(RecorderConfig(robots=["cell1", "cell2"]), ctx)
    try:
        _take(recorder, b"cell1", [1, 2, 5, 6])  # 3 and 4 lost
        _take(recorder, b"cell2", [7, 8, 9])  # joined mid-stream: nothing lost
        _take(recorder, b"cell2", [1, 2])  # cell2 restarted: its seq starts again
        _take(recorder, b"cell1", [7, 300_000])  # a jump past the restart gap: a restart
        stats = recorder.stats()
        assert stats["cell1_STIM"] == 6 and stats["cell1_STIM_lost"] == 2
        assert stats["cell2_STIM"] == 5 and "cell2_STIM_lost" not in stats
    finally:
        recorder.close()
        ctx.term()
