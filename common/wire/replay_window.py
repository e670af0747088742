"""Once, and in order: the replay window that signed commands and signed telemetry share.

A sender picks a random ``session`` per run (a boot id) and numbers each of
its streams with ``seq`` and its send time ``t_send_ns``; all three are inside
the signature, so nobody on the path can change them. What is left to a
replayer is sending a signed message again, and this window refuses that:
per session and stream, a message is accepted once, and never after the
window has moved past it.

- A message above the highest accepted ``seq`` is new if its send time is
  later too (an honest sender's clock and counter rise together).
- With ``width`` > 0, a message up to ``width - 1`` below the highest is
  accepted once if it was not yet (a link that reorders, such as a datagram
  path): one bit per ``seq`` remembers which were. ``width`` = 0 accepts
  nothing below the highest (commands: a reordered command is refused).
- Anything else is a replay, including a duplicate the link made itself.

The operators' messages to a robot (commands, heartbeats, video signals)
use the window with ``by_time=False``: their ``seq`` alone orders them (it
is signed, and unique within a boot), so a send time that is unreadable or
wrong (a stop is acted on whatever its stamp says) cannot push the window
ahead of the sender's next messages. With ``retired`` > 0 the window also
remembers that many sessions it has forgotten, and refuses everything of
them: a boot pushed out by newer ones cannot be taken up again by a replay.

Deciding and recording are two calls, since a receiver may refuse a message
for another reason (too old) after it passed the window, and a refused
message must not move the window.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass


@dataclass(slots=True)
class _Stream:
    seq: int  # highest accepted
    t_send_ns: int  # its send time
    seen: int  # bit i set: seq - i was accepted (bit 0, seq itself, always is)


class ReplayWindow:
    """Per session and stream: which sequence numbers were accepted."""

    def __init__(
        self, width: int = 0, max_sessions: int = 16, *, by_time: bool = True, retired: int = 0
    ) -> None:
        if width < 0 or max_sessions < 1 or retired < 0:
            raise ValueError(
                f"width and retired must be >= 0 and max_sessions >= 1: {width}, {retired}, "
                f"{max_sessions}"
            )
        self.width = width
        self.max_sessions = max_sessions
        self.by_time = by_time
        self.max_retired = retired
        self._mask = (1 << max(width, 1)) - 1
        self._sessions: OrderedDict[int, dict[Hashable, _Stream]] = OrderedDict()
        self._retired: OrderedDict[int, None] = OrderedDict()

    def replayed(self, session: int, stream: Hashable, seq: int, t_send_ns: int) -> bool:
        """Whether accepting this message would accept something a second time (or too late)."""
        streams = self._sessions.get(session)
        if streams is None:
            return session in self._retired
        s = streams.get(stream)
        if s is None:
            return False
        if seq > s.seq:
            return self.by_time and t_send_ns <= s.t_send_ns
        behind = s.seq - seq
        return behind >= self.width or bool((s.seen >> behind) & 1)

    def accept(self, session: int, stream: Hashable, seq: int, t_send_ns: int) -> None:
        """Record an accepted message (one ``replayed`` said was not)."""
        streams = self._sessions.get(session)
        if streams is None:
            streams = self._sessions[session] = {}
            while len(self._sessions) > self.max_sessions:
                gone, _ = self._sessions.popitem(last=False)  # the least recently heard
                if self.max_retired:
                    self._retired[gone] = None
                    while len(self._retired) > self.max_retired:
                        self._retired.popitem(last=False)
        else:
            self._sessions.move_to_end(session)
        s = streams.get(stream)
        if s is None:
            streams[stream] = _Stream(seq, t_send_ns, 1)
        elif seq > s.seq:
            ahead = seq - s.seq
            s.seen = ((s.seen << ahead) | 1) & self._mask if ahead < self.width else 1
            s.seq, s.t_send_ns = seq, t_send_ns
        else:
            s.seen |= 1 << (s.seq - seq)

    def has(self, session: int, stream: Hashable) -> bool:
        """Whether this session's stream has an accepted message (its window is set)."""
        streams = self._sessions.get(session)
        return streams is not None and stream in streams

    def clear(self) -> None:
        self._sessions.clear()
        self._retired.clear()

    def __contains__(self, session: int) -> bool:
        return session in self._sessions
