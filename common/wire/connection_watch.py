"""A connecting ZeroMQ socket's connection as its monitor tells it, and whether libzmq gave up.

libzmq never reconnects after a protocol error (an oversized or malformed
frame from the peer, a handshake in a language it does not speak); its
monitor says so by a disconnect or a failed handshake that no retry follows.
"""

from __future__ import annotations

import contextlib

import zmq

# Plain ints: pyzmq's constants are IntFlag members, and ``int & flag`` runs
# the enum's Python-level __rand__, which builds a new member on every call.
_EVENTS, _POLLIN, _NOBLOCK = int(zmq.EVENTS), int(zmq.POLLIN), int(zmq.NOBLOCK)

_WATCHED_EVENTS = (
    zmq.EVENT_CONNECTED
    | zmq.EVENT_CONNECT_DELAYED
    | zmq.EVENT_CONNECT_RETRIED
    | zmq.EVENT_DISCONNECTED
    | zmq.EVENT_HANDSHAKE_SUCCEEDED
    | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
    | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
    | zmq.EVENT_HANDSHAKE_FAILED_AUTH
)
#: libzmq retries at once after an ordinary disconnect (CONNECT_RETRIED); without that word
#: for this long after a disconnect or a failed handshake, it has given up on the connection
RECONNECT_GRACE_S = 0.25
#: the wait before opening again doubles while the new socket fails too, up to this
RECONNECT_MAX_S = 0.5


class ConnectionWatch:
    """A connecting socket's connection as its monitor tells it, and whether libzmq gave up.

    ``poll`` reads the queued events without waiting; it answers True when the
    connection ended (disconnect or failed handshake) and libzmq has not
    announced a retry within the grace time: the caller then opens the socket
    again. A live or retrying connection is left alone.
    """

    def __init__(self, sock: zmq.Socket, what: str, reopens: int = 0, wait_s: float = 0.0):
        self.what = what
        self.monitor = sock.get_monitor_socket(_WATCHED_EVENTS)
        self.up = False
        self.reopens = reopens
        #: when libzmq stopped trying (a disconnect or failed handshake not followed by a retry)
        self._ended_ns: int | None = None
        self.ended_how = ""
        self.wait_s = wait_s  # before reopening: grows while reopened sockets fail too
        self.closed = False  # the socket's owner closed it: nothing to watch any more

    def poll(self, now: int) -> bool:
        from zmq.utils.monitor import recv_monitor_message

        mon = self.monitor
        while mon.get(_EVENTS) & _POLLIN:
            try:
                event = recv_monitor_message(mon, _NOBLOCK)["event"]
            except zmq.Again:
                break
            if event == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self.up, self._ended_ns, self.wait_s = True, None, 0.0
            elif event in (zmq.EVENT_CONNECT_RETRIED, zmq.EVENT_CONNECT_DELAYED):
                self._ended_ns = None  # libzmq carries on by itself
            elif event != zmq.EVENT_CONNECTED:  # a disconnect, or a handshake that failed
                self.up = False
                self._ended_ns = now
                self.ended_how = "closed" if event == zmq.EVENT_DISCONNECTED else "refused"
        if self._ended_ns is None:
            return False
        return now - self._ended_ns >= (RECONNECT_GRACE_S + self.wait_s) * 1e9

    def close(self, sock: zmq.Socket) -> None:
        with contextlib.suppress(zmq.ZMQError):  # already closed
            sock.disable_monitor()
        self.monitor.close(0)
