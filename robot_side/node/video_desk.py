"""Viewers' WebRTC signalling over the operator link, to the robot's local video server.

Offers come in with the operator messages (the command desk hands them
here); answers go out on the robot's stream. A robot that serves no video
answers an offer with "closed" and the reason, and a viewer that goes quiet
(no message from its key for ``video_viewer_timeout_s``) loses its session.

Video is a controller's: an offer is answered only from a key whose roster
entry may watch (``OperatorEntry.may_watch``: a controller, or an observer
with ``video = true``; a recorder never). Each key makes at most
``video_offers_per_s`` offers a second (as many at once); the rest are
refused. A refusal is counted and the viewer told why in a "closed" signal,
at most ``REFUSAL_REPLIES_PER_S`` a second per key, so a flood of offers
cannot turn into a flood on the robot's stream. The slots themselves are the
bridge's (link_signalling.py): a controller's offer may close an observer's
session when all are taken.
"""

from __future__ import annotations

import importlib.util
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from common.errors import ConfigError
from common.keys.roster import OperatorEntry
from common.wire.messages import VideoSignal
from common.wire.transport import Sender
from robot_side.node.config import RobotLinkConfig
from robot_side.video.link_signalling import LinkSignalling


def video_signalling(link: RobotLinkConfig) -> LinkSignalling | None:
    """The signalling bridge ``link.video_url`` names (None: no video on this robot)."""
    if not link.video_url:
        return None
    if importlib.util.find_spec("websockets") is None:
        raise ConfigError(
            "robot link.video_url is set but websockets is not installed: "
            "pip install 'deepxpalm[video]' on the robot PC"
        )
    return LinkSignalling(
        link.video_url,
        token_file=link.video_token_file,
        max_sessions=link.video_max_sessions,
        per_key=link.video_sessions_per_key,
    )


#: "closed" replies to refused offers one key gets a second at most (the rest only counted)
REFUSAL_REPLIES_PER_S = 5.0
#: keys whose offer rate is tracked at once (a stale one is dropped: its bucket is full again)
MAX_TRACKED_KEYS = 256


@dataclass
class _Bucket:
    """A token bucket: ``rate`` a second, at most ``rate`` (at least 1) held."""

    rate: float
    tokens: float
    at_ns: int

    def take(self, now_ns: int) -> bool:
        burst = max(1.0, self.rate)
        self.tokens = min(burst, self.tokens + (now_ns - self.at_ns) * 1e-9 * self.rate)
        self.at_ns = now_ns
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


class _PerKey:
    """One token bucket per key, bounded in number (the oldest untouched goes first)."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self._buckets: dict[bytes | None, _Bucket] = {}

    def take(self, key: bytes | None, now_ns: int) -> bool:
        bucket = self._buckets.pop(key, None)
        if bucket is None:
            bucket = _Bucket(self.rate, max(1.0, self.rate), now_ns)
            if len(self._buckets) >= MAX_TRACKED_KEYS:
                del self._buckets[next(iter(self._buckets))]
        self._buckets[key] = bucket  # the most recently used last
        return bucket.take(now_ns)


class VideoDesk:
    """Carries signals both ways and ends the sessions of quiet viewers."""

    def __init__(
        self,
        video: LinkSignalling | None,
        viewer_timeout_s: float,
        *,
        counters: Counter[str],
        now: Callable[[], int],
        session: int,
        last_heard_ns: Callable[[bytes | None], int],
        who: Callable[[bytes | None], OperatorEntry | None],
        offers_per_s: float = 2.0,
    ) -> None:
        """``last_heard_ns(signer)``: when the viewer's key was last heard (peers.py);
        ``who(signer)``: its roster entry now (None: not in the roster any more)."""
        #: the bridge to the local video server (None: this robot serves no video)
        self.signalling = video
        self.timeout_ns = round(viewer_timeout_s * 1e9)
        self.who = who
        self._offers = _PerKey(offers_per_s)
        self._replies = _PerKey(REFUSAL_REPLIES_PER_S)
        self.counters = counters
        self.now = now
        self.session = session
        self.last_heard_ns = last_heard_ns
        self.pub: Sender | None = None  # set by the node once its link is open
        self._next_expiry_ns = 0
        self._seq = 0

    def on_signal(self, msg: VideoSignal, signer: bytes | None) -> None:
        self.counters["video_signals_received"] += 1
        if self.signalling is None:
            self.counters["video_signals_unserved"] += 1
            if msg.kind == "offer":
                self._publish(
                    VideoSignal(
                        seq=0,
                        t_send_ns=0,
                        kind="closed",
                        viewer=msg.viewer,
                        reason="this robot serves no video (its link.video_url is empty)",
                    )
                )
            return
        if msg.kind != "offer":
            self.signalling.on_signal(msg, signer)  # a bye ends only the signer's own session
            return
        entry = self.who(signer)
        now = self.now()
        if entry is None or not entry.may_watch:
            self._refuse(msg, signer, now, "video_offers_refused_role", _not_yours(entry))
        elif not self._offers.take(signer, now):
            rate = self._offers.rate
            self._refuse(
                msg,
                signer,
                now,
                "video_offers_refused_rate",
                f"too many video offers from {entry.name}: at most {rate:g} a second",
            )
        else:
            self.signalling.on_signal(msg, signer, controller=entry.role == "controller")

    def _refuse(
        self, msg: VideoSignal, signer: bytes | None, now: int, counter: str, reason: str
    ) -> None:
        self.counters["video_offers_refused"] += 1
        self.counters[counter] += 1
        if not self._replies.take(signer, now):
            self.counters["video_refusals_not_told"] += 1
            return
        self._publish(
            VideoSignal(seq=0, t_send_ns=0, kind="closed", viewer=msg.viewer, reason=reason)
        )

    def serve(self, now: int) -> None:
        """Publish the answers the video sessions produced; end the sessions of quiet viewers."""
        video = self.signalling
        if video is None:
            return
        if video.outgoing:
            for msg in video.take_outgoing():
                self._publish(msg)
        if now < self._next_expiry_ns:
            return
        self._next_expiry_ns = now + 1_000_000_000
        if video.sessions:
            video.expire(self._viewer_heard, self._may_watch)

    def _viewer_heard(self, signer: bytes | None) -> bool:
        """Called on the video thread: a stale read of these times is harmless."""
        return self.now() - self.last_heard_ns(signer) < self.timeout_ns

    def _may_watch(self, signer: bytes | None) -> bool:
        """Called on the video thread: the roster's entry now (a reload may take it away)."""
        entry = self.who(signer)
        return entry is not None and entry.may_watch

    def _publish(self, msg: VideoSignal) -> None:
        self._seq += 1
        msg.seq, msg.t_send_ns, msg.session = self._seq, self.now(), self.session
        self.pub.send(msg)
        self.counters[f"video_{msg.kind}s_sent"] += 1


def _not_yours(entry: OperatorEntry | None) -> str:
    """Why a key may not watch, as its page shows it."""
    if entry is None:
        return "video refused: this key is not in the robot's roster"
    if entry.role == "recorder":
        return f"video refused: {entry.name} is a recorder, and recorders never get video"
    if entry.role == "controller":
        return f"video refused: the robot's roster says video = false for {entry.name}"
    return (
        f"video refused: video is for controllers; {entry.name} is an {entry.role} "
        "without video = true in the robot's roster"
    )
