"""The operator node's link: whom it listens to, with which keys, and its two sockets.

- ``LinkKeys``: the robot's name on the wire, our signing key (commands the
  robot obeys only from the lease holder), and the robot's public key:
  telemetry signed by anyone else is dropped. Across sites (the fabric) the
  robot's stream must be signed, unless ``link.unsigned_stream`` says the
  risk of what a compromised router could forge is taken;
- ``telemetry_gate_for``: with the robot's key, its signed telemetry is
  believed once, fresh and from its current run (telemetry_gate.py);
- ``Sockets``: the subscriber and publisher, opened again after a long
  silence (libzmq never reconnects a socket after a protocol error).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zmq

from common.clocks.clock_sync import ClockSync
from common.errors import ConfigError
from common.keys.curve import client_options
from common.wire.codec import DecodeError, check_robot_name, name_prefix
from common.wire.messages import Heartbeat, Stimulus, TactileFrame, VideoSignal
from common.wire.transport import Link, Publisher, Receiver, Sender, Subscriber
from operator_side.node.config import OperatorLinkConfig
from operator_side.node.telemetry_gate import TelemetryGate

log = logging.getLogger(__name__)


@dataclass
class LinkKeys:
    """The robot's name (b"" = unnamed), our signer and the robot's public key, if any."""

    robot_name: bytes
    signer: Any
    robot_key: bytes | None

    @classmethod
    def load(cls, link: OperatorLinkConfig) -> LinkKeys:
        """ConfigError for a name the protocol forbids, or the fabric with no robot key."""
        try:
            robot_name = check_robot_name(link.robot_name) if link.robot_name else b""
        except DecodeError as e:
            raise ConfigError(f"operator link.robot_name: {e}") from None
        signer = None
        if link.signing_key_file is not None:
            from common.wire.signing import load_signer  # cryptography only when signing

            signer = load_signer(link.signing_key_file)
        if link.mode == "fabric" and link.robot_key_file is None and not link.unsigned_stream:
            raise ConfigError(
                "operator link.mode = 'fabric' takes the robot's stream across sites, so it must "
                "be signed: set link.robot_key_file to the robot's NAME.sign (`deepxpalm keys "
                "robot`), or link.unsigned_stream = true to accept what a compromised router "
                "could forge"
            )
        robot_key = None
        if link.robot_key_file is not None:
            from common.wire.signing import load_public_key

            robot_key = load_public_key(link.robot_key_file)
        return cls(robot_name, signer, robot_key)


def telemetry_gate_for(
    keys: LinkKeys, clock: ClockSync, link: OperatorLinkConfig
) -> TelemetryGate | None:
    """With the robot's key: the gate its signed telemetry passes (None: no key, no gate)."""
    if keys.robot_key is None:
        return None
    return TelemetryGate(
        clock,
        round(link.max_telemetry_age_ms * 1e6),
        keys.signer.public if keys.signer is not None else None,
    )


def topics(robot_name: bytes, frames: bool, video: bool) -> tuple[bytes, ...]:
    """What we subscribe to: one robot's stimuli and heartbeats, and frames and video signals
    if wanted; an unnamed robot (a direct link): everything it sends, so that whatever
    arrives is read and judged (the fuzz tests send it anything)."""
    if not robot_name:
        return (b"",)
    wanted = [name_prefix(Stimulus.TOPIC, robot_name), name_prefix(Heartbeat.TOPIC, robot_name)]
    if frames:
        wanted.append(name_prefix(TactileFrame.TOPIC, robot_name))
    if video:
        wanted.append(name_prefix(VideoSignal.TOPIC, robot_name))
    return tuple(wanted)


class Sockets:
    """The node's subscriber and publisher (or the link it was handed)."""

    def __init__(
        self,
        link: Link | None,
        config: OperatorLinkConfig,
        keys: LinkKeys,
        *,
        counters: Counter[str],
        now: Callable[[], int],
    ) -> None:
        self.config = config
        self.keys = keys
        self.counters = counters
        self.now = now
        self.pub: Sender | None = link.pub if link is not None else None
        self.sub: Receiver | None = link.sub if link is not None else None
        self.opened_ns = 0
        #: when the newest message the node believed arrived (local clock)
        self.last_rx_ns = 0
        self.rejected_before = 0  # rejections counted by sockets since reopened
        self.session: Any = None  # mode fabric: our Zenoh session, opened once

    def describe(self) -> str:
        link = self.config
        if link.mode == "fabric":
            return f"fabric through {link.fabric.router_endpoint} as {self._member()!r}"
        return f"telemetry {link.telemetry_endpoint}, commands {link.command_endpoint}"

    def _member(self) -> str:
        from common.fabric.session import member_name

        return member_name(self.config.fabric, None, "operator link.fabric")

    def open(self, ctx: zmq.Context, topics: tuple[bytes, ...], wake_fd: int) -> None:
        """Connect both sockets; ``wake_fd`` wakes the subscriber's poll (queued commands)."""
        if self.config.mode == "fabric":
            self._open_fabric(topics, wake_fd)
            return
        link = self.config
        opts = client_options(link.security)
        self.sub = Subscriber(
            ctx,
            link.telemetry_endpoint,
            bind=False,
            sock_opts=opts,
            name="operator telemetry",
            topics=topics,
            expect_name=self.keys.robot_name,
            reconnect=True,  # opened again at once if libzmq gives up (a protocol error)
            link_name="telemetry",
        )
        self.pub = Publisher(
            ctx,
            link.command_endpoint,
            bind=False,
            sock_opts=opts,
            name=self.keys.robot_name,
            signer=self.keys.signer,
            reconnect=True,
            link_name="commands",
        )
        self.sub.poller.register(wake_fd, zmq.POLLIN)
        self.opened_ns = self.now()

    def _open_fabric(self, topics: tuple[bytes, ...], wake_fd: int) -> None:
        """Our Zenoh session (opened once), the robot's keys we read, our keys we put on.

        The session reconnects to the router by itself, so it is never reopened.
        """
        from common.fabric import keyexprs
        from common.fabric.link import FabricPublisher, FabricSubscriber
        from common.fabric.session import open_member_session

        link = self.config
        robot = self.keys.robot_name
        if not robot:
            raise ConfigError("operator link.mode = 'fabric' needs link.robot_name")
        member = self._member()
        keyexprs.check_operator_name(member)
        if self.session is None:
            where = "operator link.fabric"
            self.session = open_member_session(link.fabric, member, where, "operator node")
        kinds = {t[: len(Stimulus.TOPIC)] for t in topics}
        by_topic = {
            Stimulus.TOPIC: "stimulus",
            Heartbeat.TOPIC: "heartbeat",
            TactileFrame.TOPIC: "frame",
            VideoSignal.TOPIC: "video",
        }
        keys = tuple(keyexprs.robot_key(robot, by_topic[t]) for t in sorted(kinds) if t in by_topic)
        endpoint = link.fabric.router_endpoint
        self.sub = FabricSubscriber(
            self.session, keys, expect_name=robot, name="operator telemetry", endpoint=endpoint
        )
        self.pub = FabricPublisher(
            self.session, robot=robot, operator=member, signer=self.keys.signer, endpoint=endpoint
        )
        self.sub.poller.register(wake_fd, zmq.POLLIN)
        self.opened_ns = self.now()

    def reopen_if_silent(
        self, now: int, ctx: zmq.Context, topics: tuple[bytes, ...], wake_fd: int
    ) -> None:
        """Open both sockets again after a long silence.

        libzmq never reconnects a connecting socket after a protocol error (an
        oversized or malformed frame from the peer), so a link that went silent
        may be dead on our side only; a fresh socket costs nothing if it was not.
        """
        if self.config.mode == "fabric":
            return  # the Zenoh session reconnects to its router by itself
        quiet_since = max(self.last_rx_ns, self.opened_ns)
        if (now - quiet_since) / 1e6 < self.config.reopen_after_ms:
            return
        log.info("no telemetry for %.1f s: opening the sockets again", (now - quiet_since) / 1e9)
        rejected = self.sub.rejected_total
        self.close()
        self.open(ctx, topics, wake_fd)
        self.rejected_before += rejected
        self.counters["sockets_reopened"] += 1

    @property
    def decode_errors(self) -> int:
        """Frames refused by the subscriber, over every socket it has had."""
        return self.rejected_before + self.sub.rejected_total

    def close(self) -> None:
        if self.sub is not None:
            self.sub.close()
        if self.pub is not None:
            self.pub.close()
        if self.session is not None:
            from common.fabric.session import close_session

            close_session(self.session)
            self.session = None
