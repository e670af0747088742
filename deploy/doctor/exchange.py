"""A short heartbeat exchange with the other node: did its link answer, what did it say.

The doctor opens the node's own link for a moment, sends heartbeats and
reads the other node's: their counters (its links' health among them), its
state, what its socket monitors saw of the handshake, and enough round
trips for a clock estimate.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from typing import Any

from common.clocks.clock import now_ns
from common.clocks.clock_sync import ClockSync

HEARTBEAT_PERIOD_S = 0.05
#: Round trips enough for a clock estimate; the exchange stops early once it has them.
CLOCK_SAMPLES = 12


class _Monitor:
    """Handshake events of one socket, read without blocking."""

    def __init__(self, sock: Any) -> None:
        self.sock = sock.get_monitor_socket()
        self.events: list[str] = []

    def poll(self) -> None:
        import zmq
        from zmq.utils.monitor import recv_monitor_message

        while True:
            try:
                msg = recv_monitor_message(self.sock, zmq.NOBLOCK)
            except zmq.Again:
                return
            try:
                self.events.append(zmq.Event(msg["event"]).name)
            except ValueError:
                self.events.append(str(msg["event"]))

    def has(self, name: str) -> bool:
        return name in self.events

    def close(self) -> None:
        self.sock.close(0)


@dataclass
class Exchange:
    """What a short heartbeat exchange with the other node saw."""

    heartbeats: int = 0
    stimuli: int = 0
    rejected: int = 0
    peer_state: str | None = None
    #: the peer's newest heartbeat counters (its links' health among them)
    peer_stats: dict[str, float] = field(default_factory=dict)
    clock: ClockSync = field(default_factory=ClockSync)
    duration_s: float = 0.0
    sub_events: list[str] = field(default_factory=list)
    pub_events: list[str] = field(default_factory=list)
    denied_keys: list[str] = field(default_factory=list)


def heartbeat_exchange(
    ctx: Any,
    role: str,
    link: Any,
    timeout_s: float,
) -> Exchange:
    """Act as ``role``'s node for up to ``timeout_s``: send heartbeats, time the peer's.

    The robot side binds both ports with the node's own CURVE server options
    and allowlist; the operator side connects with its client options. Every
    heartbeat echoes the peer's newest one, so ``ClockSync`` gets NTP samples
    exactly as in the nodes. Raises ``zmq.ZMQError`` when a bind fails.
    """
    import zmq
    import zmq.auth  # common.keys.curve needs it loaded

    from common.keys.curve import Authenticator, client_options, server_options
    from common.wire.codec import MAX_MESSAGE_BYTES, DecodeError, decode, encode
    from common.wire.messages import Heartbeat, Stimulus, new_run

    out = Exchange()
    server = role == "robot"
    opts = server_options(link.security) if server else client_options(link.security)
    peer = "operator" if server else "robot"
    sockets: list[Any] = []
    monitors: list[_Monitor] = []
    with contextlib.ExitStack() as stack:
        if server:
            auth = Authenticator(ctx, link.security)
            stack.callback(auth.stop)
        pub = ctx.socket(zmq.PUB)
        sub = ctx.socket(zmq.SUB)
        for sock in (pub, sub):
            sockets.append(sock)
            sock.setsockopt(zmq.LINGER, 0)
            for opt, value in opts.items():
                sock.setsockopt(opt, value)
        stack.callback(lambda: [s.close(0) for s in sockets])
        sub.setsockopt(zmq.MAXMSGSIZE, MAX_MESSAGE_BYTES)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        pub_mon, sub_mon = _Monitor(pub), _Monitor(sub)
        monitors += [pub_mon, sub_mon]
        stack.callback(lambda: [m.close() for m in monitors])
        pub_ep = link.telemetry_endpoint if server else link.command_endpoint
        sub_ep = link.command_endpoint if server else link.telemetry_endpoint
        if server:
            pub.bind(pub_ep)
            sub.bind(sub_ep)
        else:
            sub.connect(sub_ep)
            pub.connect(pub_ep)
        poller = zmq.Poller()
        poller.register(sub, zmq.POLLIN)
        seq = 0
        # this exchange's run, and the peer's: a robot acts on an operator's heartbeat (and
        # answers it) only once it echoes the robot's current run (docs/protocol.md)
        run, peer_run = new_run(), None
        t0 = time.monotonic()
        next_hb = t0
        while time.monotonic() - t0 < timeout_s and out.clock.accepted < CLOCK_SAMPLES:
            now = time.monotonic()
            if now >= next_hb:
                seq += 1
                echo_send, echo_recv = out.clock.echo_fields()
                pub.send(
                    encode(
                        Heartbeat(
                            seq=seq,
                            t_send_ns=now_ns(),
                            node=role,
                            state="ok" if out.heartbeats else "down",
                            echo_t_send_ns=echo_send,
                            echo_t_recv_ns=echo_recv,
                            stats={"doctor": 1.0},
                            session=run,
                            echo_session=peer_run,
                        )
                    ),
                    zmq.NOBLOCK,
                )
                next_hb = now + HEARTBEAT_PERIOD_S
            if poller.poll(max(1, int((next_hb - time.monotonic()) * 1000))):
                while True:
                    try:
                        data = sub.recv(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    t_recv = now_ns()
                    try:
                        msg = decode(data)
                    except DecodeError:
                        out.rejected += 1
                        continue
                    if isinstance(msg, Heartbeat) and msg.node == peer:
                        out.heartbeats += 1
                        out.peer_state = msg.state
                        out.peer_stats = dict(msg.stats)
                        peer_run = msg.session if msg.session is not None else peer_run
                        out.clock.on_heartbeat(
                            msg.t_send_ns, msg.echo_t_send_ns, msg.echo_t_recv_ns, t_recv
                        )
                    elif isinstance(msg, Stimulus):
                        out.stimuli += 1
            for m in monitors:
                m.poll()
        out.duration_s = time.monotonic() - t0
        for m in monitors:
            m.poll()
        out.pub_events, out.sub_events = pub_mon.events, sub_mon.events
        out.denied_keys = auth.refused_keys if server else []
    return out
