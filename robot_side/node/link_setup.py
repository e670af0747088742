"""The robot's side of the operator link: its name, its signing key, its two sockets.

Checked when the node is built, so a config the link cannot honour fails
before any device moves, with the setting to change.
"""

from __future__ import annotations

import contextlib
import logging
from typing import TYPE_CHECKING

import zmq

from common.errors import ConfigError
from common.keys.curve import Authenticator, check_endpoint, server_options
from common.wire.codec import DecodeError, check_robot_name, name_prefix
from common.wire.messages import Command, Heartbeat, VideoSignal
from common.wire.transport import Publisher, Receiver, Sender, Subscriber
from robot_side.node.config import RobotConfig, RobotLinkConfig

if TYPE_CHECKING:  # cryptography only when signing
    from common.wire.signing import Signer

log = logging.getLogger(__name__)


def wire_name(name: str) -> bytes:
    """Our name on the wire (b"" = unnamed); ConfigError for a name the protocol forbids."""
    if not name:
        return b""
    try:
        return check_robot_name(name)
    except DecodeError as e:
        raise ConfigError(f"robot link.robot_name: {e}") from None


def stream_signer(link: RobotLinkConfig) -> Signer | None:
    """What signs everything we send (None: unsigned); operators holding our key drop the rest.

    Across sites (the fabric) the stream is signed unless ``link.unsigned_stream`` says
    otherwise.
    """
    if link.mode == "fabric" and link.signing_key_file is None:
        if not link.unsigned_stream:
            raise ConfigError(
                f"robot link.mode = {link.mode!r} signs its stream: set link.signing_key_file "
                "(`deepxpalm keys robot --name NAME` makes it), or link.unsigned_stream = "
                "true to let a compromised router forge what palms feel (docs/security.md)"
            )
        log.warning("link.unsigned_stream: this robot's stream is not signed")
    if link.signing_key_file is None:
        return None
    from common.wire.signing import load_signer  # cryptography only when signing

    return load_signer(link.signing_key_file)


def check_command_access(config: RobotConfig) -> None:
    """Refuse a bound, plain, unsigned command port in front of an arm, gripper or camera.

    Plain TCP is allowed on loopback, but a loopback port is open to every
    user and program on the PC: without CURVE (its allowlist) or a roster
    (signed commands) any of them could jog the arm, open the gripper,
    resume a latched stop or be sent the camera. ``deepxpalm robot`` checks
    this before any device is opened; ``link.allow_plain_commands`` says the
    risk is taken.
    """
    link_cfg = config.link
    if (
        link_cfg.mode != "bind"
        or link_cfg.security.mode == "curve"
        or link_cfg.roster_file is not None
    ):
        return
    actuators = [
        name
        for name, section in (("arm", config.arm), ("gripper", config.gripper))
        if section.get("kind", "none") != "none"
    ]
    if link_cfg.video_url:
        actuators.append("camera (link.video_url)")
    if not actuators:
        return
    if link_cfg.allow_plain_commands:
        log.warning(
            "link.allow_plain_commands: any process that reaches %s commands the %s",
            link_cfg.command_endpoint,
            " and ".join(actuators),
        )
        return
    raise ConfigError(
        f"robot link.command_endpoint {link_cfg.command_endpoint} is plain TCP with no roster: "
        f"any process that reaches it (on loopback, every user of this PC) could command the "
        f"{' and '.join(actuators)}. Set link.security.mode = 'curve' with keys from "
        "`deepxpalm keys` (or link.roster_file, for signed commands), or "
        "link.allow_plain_commands = true to take that risk"
    )


def open_link(
    stack: contextlib.ExitStack,
    ctx: zmq.Context,
    link: RobotLinkConfig,
    *,
    name: bytes,
    signer: Signer | None,
    serves_video: bool,
) -> tuple[Sender, Receiver, Authenticator | None]:
    """(the stream we publish, the operators' messages we read, the CURVE allowlist if bound).

    Fabric: both go through our Zenoh session to the router (``open_fabric``).

    Bound (a direct link): we are the CURVE server, and the operator connects to us.
    """
    if link.mode == "fabric":
        pub, sub = open_fabric(stack, link, name=name, signer=signer, serves_video=serves_video)
        return pub, sub, None
    for endpoint in (link.telemetry_endpoint, link.command_endpoint):
        check_endpoint(endpoint, link.security)
    auth = Authenticator(ctx, link.security)
    stack.callback(auth.stop)
    opts = server_options(link.security)
    pub = Publisher(
        ctx,
        link.telemetry_endpoint,
        bind=True,
        sock_opts=opts,
        name=name,
        signer=signer,
        link_name="telemetry",
    )
    stack.callback(pub.close)
    topics: tuple[bytes, ...] = (b"",)
    if name:
        wanted = [Command.TOPIC, Heartbeat.TOPIC]
        if serves_video:  # viewers' offers, only where a camera is served
            wanted.append(VideoSignal.TOPIC)
        topics = tuple(name_prefix(topic, name) for topic in wanted)
    sub = Subscriber(
        ctx,
        link.command_endpoint,
        bind=True,
        sock_opts=opts,
        name="robot commands",
        topics=topics,
        expect_name=name,
        link_name="commands",
    )
    stack.callback(sub.close)
    return pub, sub, auth


def open_fabric(
    stack: contextlib.ExitStack,
    link: RobotLinkConfig,
    *,
    name: bytes,
    signer: Signer | None,
    serves_video: bool,
) -> tuple[Sender, Receiver]:
    """Our Zenoh session to the router, our stream's publishers and our inbox.

    Our certificate is our roster name's, which is our name on the wire: the
    router lets us put under our own names only, and read only our inbox.
    """
    from common.fabric import keyexprs
    from common.fabric.link import FabricPublisher, FabricSubscriber
    from common.fabric.session import close_session, member_name, open_member_session

    if not name:
        raise ConfigError("robot link.mode = 'fabric' needs link.robot_name (our roster name)")
    where = "robot link.fabric"
    member = member_name(link.fabric, name.decode(), where)
    session = open_member_session(link.fabric, member, where, "robot node")
    stack.callback(close_session, session)
    endpoint = link.fabric.router_endpoint
    pub = FabricPublisher(session, robot=name, operator=None, signer=signer, endpoint=endpoint)
    stack.callback(pub.close)
    kinds = ["command", keyexprs.STOP, keyexprs.STOP_COPY, "heartbeat"]
    if serves_video:  # viewers' offers, only where a camera is served
        kinds.append("video")
    sub = FabricSubscriber(
        session,
        tuple(keyexprs.robot_inbox_for(name, kind) for kind in kinds),
        expect_name=name,
        name="robot commands",
        endpoint=endpoint,
    )
    stack.callback(sub.close)
    return pub, sub
