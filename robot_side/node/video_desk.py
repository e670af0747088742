"""Viewers' WebRTC signalling over the operator link, to the robot's local video server.

Offers come in with the operator messages (the command desk hands them
here); answers go out on the robot's stream. A robot that serves no video
answers an offer with "closed" and the reason, and a viewer that goes quiet
(no message from its key for ``video_viewer_timeout_s``) loses its session.
"""

from __future__ import annotations

import importlib.util
from collections import Counter
from collections.abc import Callable

from common.errors import ConfigError
from common.messages import VideoSignal
from common.transport import Sender
from robot_side.config import RobotLinkConfig
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
    return LinkSignalling(link.video_url, token_file=link.video_token_file)


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
    ) -> None:
        """``last_heard_ns(signer)``: when the viewer's key was last heard (peers.py)."""
        #: the bridge to the local video server (None: this robot serves no video)
        self.signalling = video
        self.timeout_ns = round(viewer_timeout_s * 1e9)
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
        self.signalling.on_signal(msg, signer)

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
            video.expire(self._viewer_heard)

    def _viewer_heard(self, signer: bytes | None) -> bool:
        """Called on the video thread: a stale read of these times is harmless."""
        return self.now() - self.last_heard_ns(signer) < self.timeout_ns

    def _publish(self, msg: VideoSignal) -> None:
        self._seq += 1
        msg.seq, msg.t_send_ns, msg.session = self._seq, self.now(), self.session
        self.pub.send(msg)
        self.counters[f"video_{msg.kind}s_sent"] += 1
