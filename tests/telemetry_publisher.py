"""A robot's telemetry at fixed rates on a real link, for the tests of what reads the wire.

``TelemetryPublisher`` sends stimuli, raw frames and heartbeats through any
sender with ``send(msg)`` (a bound ZeroMQ ``Publisher``, a ``FabricPublisher``)
from a thread of its own, each kind on its own grid of absolute deadlines (a
late turn catches up, so the rate over seconds holds on a loaded machine),
and keeps each message's seq and send time. The heartbeats carry the stats
``stats()`` gives (refusal counters, the arm's pose).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
import pytest

from common.clocks.clock import now_ns
from common.tactile.contract import FRAME_SHAPE
from common.wire.messages import Heartbeat, Stimulus, TactileFrame, new_run

#: the stimulus every message carries: one cell in each of two rows (the codec's rule)
CELLS = np.array([[0.0, 2.5, 0.0], [1.25, 0.0, 0.0], [0.0, 0.0, 0.0]], np.float32)


class TelemetryPublisher:
    """Sends ``rates`` (topic -> Hz) of stimulus, frame and heartbeat through ``sender``."""

    def __init__(
        self,
        sender,
        rates: dict[str, float],
        *,
        stats: Callable[[], dict[str, float]] = dict,
    ) -> None:
        self.sender = sender
        self.rates = dict(rates)
        self.stats = stats
        self.session = new_run()
        self.sent: dict[str, list[tuple[int, int]]] = {topic: [] for topic in rates}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="telemetry", daemon=True)

    def __enter__(self) -> TelemetryPublisher:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(10)

    def _message(self, topic: str, seq: int, t_send: int):
        if topic == "stimulus":
            return Stimulus(
                seq=seq,
                t_send_ns=t_send,
                t_capture_ns=t_send,
                frame_seq=seq,
                mode="mask",
                contact=True,
                stimulus=CELLS,
                pattern=4,
                confidence=0.93,
                grip_level=12,
                session=self.session,
            )
        if topic == "frame":
            frame = np.full(FRAME_SHAPE, 0.5, np.float32)
            return TactileFrame(
                seq=seq,
                t_send_ns=t_send,
                t_capture_ns=t_send,
                frame_seq=seq,
                frame=frame,
                session=self.session,
            )
        return Heartbeat(
            seq=seq,
            t_send_ns=t_send,
            node="robot",
            state="ok",
            stimulus_seq=len(self.sent.get("stimulus", ())),
            stats=self.stats(),
            session=self.session,
        )

    def _run(self) -> None:
        start = time.monotonic()
        due = dict.fromkeys(self.rates, start)
        seqs = dict.fromkeys(self.rates, 0)
        while not self._stop.is_set():
            topic = min(due, key=due.__getitem__)
            wait = due[topic] - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                return
            seqs[topic] += 1
            t_send = now_ns()
            self.sender.send(self._message(topic, seqs[topic], t_send))
            self.sent[topic].append((seqs[topic], t_send))
            # a late turn catches up, but never sends one topic's messages back to back: the
            # router lets a key pass only so often (its downsampling), as a robot's own pacing does
            period = 1.0 / self.rates[topic]
            due[topic] = max(due[topic] + period, time.monotonic() + period / 2)

    def sent_rate(self, topic: str, seq_first: int, seq_last: int) -> float:
        """What was sent of ``topic`` a second from ``seq_first`` to ``seq_last``, by the send
        times kept here."""
        sent = [t for seq, t in self.sent[topic] if seq_first <= seq <= seq_last]
        return (len(sent) - 1) * 1e9 / (sent[-1] - sent[0])


def check_rates(report: dict, telemetry: TelemetryPublisher) -> None:
    """A report's rates against what ``telemetry`` sent over the report's window.

    ``sent_hz`` (the messages' seq over their send times) is what the publisher sent over
    the span of seqs the report timed (the publisher catches up after a late turn, so its
    rate over any other span, the command's start-up included, may differ by more than 10 %
    on a loaded machine);
    ``rate_hz`` (over the receive times) is that less what was lost on the way (a loaded
    machine drops datagrams: the report counts them, so the arithmetic holds whatever
    the loss); and the publisher kept to at least half its rate.
    """
    for topic, hz in telemetry.rates.items():
        t = report[topic]
        said = f"{topic}: {t}"
        assert t["count"] > 1, said
        arrived = t["count"] / (t["count"] + t["lost"])
        assert t["rate_hz"] == pytest.approx(t["sent_hz"] * arrived, rel=0.10), said
        sent = telemetry.sent_rate(topic, t["seq_first"], t["seq_last"])
        assert t["sent_hz"] == pytest.approx(sent, rel=0.01), said
        assert t["sent_hz"] > hz / 2, said
