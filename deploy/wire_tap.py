"""A robot's telemetry as a listener reads it: what ``deepxpalm topic`` and ``view`` stand on.

A tap reads what a robot sends (stimuli, raw frames, heartbeats, video
answers) with the user's own credentials, and sends nothing:

- **direct**: a ZeroMQ SUB to the robot's telemetry endpoint (``Subscriber``,
  common/wire/transport.py), a CURVE client with our key pair and the robot's
  public key, as an operator node connects; the robot must allow our key;
- **fabric**: a Zenoh session to the router with our certificate
  (``FabricSubscriber``, every message queued, none dropped for a newer one,
  as a recorder reads); the router's roster must let our name read the robot.

Every message passes the codec as a node's would (a bad one is counted by
class, never shown) and a signed one only if its signature verifies, so a
message's ``signer`` is the key that signed it. The settings come from an
operator's or a recorder's config (``--config``, read by the loaders the
nodes use) and the flags over it.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from common.config.typed import from_dict, load_toml
from common.errors import ConfigError
from common.fabric import keyexprs
from common.fabric.session import FabricConfig
from common.keys.curve import SecurityConfig
from common.wire.codec import name_prefix, split_name
from common.wire.messages import Message

#: topic name (the fabric's key chunk) -> message type, as a robot sends them
TOPICS: dict[str, type] = {kind: cls for cls, kind in keyexprs.ROBOT_KINDS.items()}
#: message type -> topic name
TOPIC_OF: dict[type, str] = dict(keyexprs.ROBOT_KINDS)
#: ``TapConfig.where`` of fabric settings given by flags
FLAGS = "fabric"


@dataclass
class TapConfig:
    """Where a tap reads from and with which credentials."""

    mode: Literal["direct", "fabric"] = "direct"
    telemetry_endpoint: str = "tcp://127.0.0.1:5555"
    security: SecurityConfig = field(default_factory=SecurityConfig)
    fabric: FabricConfig = field(default_factory=FabricConfig)
    #: robot names to read; empty = every robot a direct link carries (the fabric needs names)
    robots: list[str] = field(default_factory=list)
    #: the robot's public signing key (its NAME.sign), when known: messages it signed say so
    robot_key: bytes | None = None
    #: the table the fabric settings came from, for errors (``FLAGS``: the command line)
    where: str = "fabric"

    @property
    def source(self) -> str:
        """The endpoint or router read, as the user wrote it."""
        return self.fabric.router_endpoint if self.mode == "fabric" else self.telemetry_endpoint


def add_link_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags that say where to read and with which credentials (both commands')."""
    g = parser.add_argument_group(
        "where to read",
        "An operator's or a recorder's config gives the link, the keys and the robot; the "
        "flags below set or override them. Without either: the robot's telemetry on "
        "tcp://127.0.0.1:5555, plain (a robot on this PC).",
    )
    g.add_argument(
        "--config",
        type=Path,
        help="an operator's or a recorder's config (TOML, or a scene with [operator]): "
        "its link.mode, endpoints, CURVE keys, fabric certificate and robot",
    )
    g.add_argument("--endpoint", help="a robot's telemetry endpoint (direct link)")
    g.add_argument("--router", metavar="quic/HOST:PORT", help="read through this fabric router")
    g.add_argument(
        "--cert-dir", type=Path, help="fabric: our NAME.crt, NAME.key and the fabric's ca.crt"
    )
    g.add_argument("--name", help="fabric: our roster name (the certificate's common name)")
    g.add_argument(
        "--curve-key", type=Path, metavar="FILE", help="direct, CURVE: our NAME.key_secret"
    )
    g.add_argument(
        "--server-key", type=Path, metavar="FILE", help="direct, CURVE: the robot's NAME.key"
    )
    g.add_argument(
        "--allow-insecure",
        action="store_true",
        help="read plain TCP from another machine (anyone on the path reads it too)",
    )
    g.add_argument(
        "--robot",
        action="append",
        default=[],
        metavar="NAME",
        help="only this robot (repeatable); the fabric needs at least one",
    )
    g.add_argument(
        "--robot-key",
        type=Path,
        metavar="FILE",
        help="the robot's public signing key (NAME.sign): what it signed is marked so",
    )


def _operator_tap(section: dict[str, Any], where: str) -> TapConfig:
    from common.wire.signing import load_public_key
    from operator_side.node.config import OperatorLinkConfig

    link = from_dict(OperatorLinkConfig, section.get("link", {}), where=f"{where}.link")
    return TapConfig(
        mode=link.mode,
        telemetry_endpoint=link.telemetry_endpoint,
        security=link.security,
        fabric=link.fabric,
        robots=[link.robot_name] if link.robot_name else [],
        robot_key=load_public_key(link.robot_key_file) if link.robot_key_file else None,
        where=f"{where}.link.fabric",
    )


def _recorder_tap(section: dict[str, Any], where: str) -> TapConfig:
    from operator_side.record_cli import RecorderConfig

    rec = from_dict(RecorderConfig, section, where=where)
    return TapConfig(
        mode=rec.mode,
        telemetry_endpoint=rec.telemetry_endpoint,
        security=rec.security,
        fabric=rec.fabric,
        robots=list(rec.robots),
        where=f"{where}.fabric",
    )


def tap_from_file(path: Path) -> TapConfig:
    """The link settings of an operator's or a recorder's config file (or a scene's)."""
    data = load_toml(path)
    for section, reader in (("operator", _operator_tap), ("recorder", _recorder_tap)):
        if isinstance(data.get(section), dict):
            return reader(data[section], section)
    if isinstance(data.get("robot"), dict) or "publish_rate_hz" in data:
        raise ConfigError(
            f"{path} is a robot's config: the robot's own keys cannot read its stream. Give an "
            "operator's or a recorder's config (its key is in the robot's allowlist), or "
            "--endpoint for a plain link"
        )
    from operator_side.record_cli import RecorderConfig

    recorder_keys = {f.name for f in dataclasses.fields(RecorderConfig)}
    if data and set(data) <= recorder_keys and "link" not in data:
        return _recorder_tap(data, "recorder")
    return _operator_tap(data, "operator")


def tap_config(args: argparse.Namespace) -> TapConfig:
    """The config file's link settings (if any) with the flags over them."""
    from common.wire.signing import load_public_key

    cfg = tap_from_file(args.config) if args.config else TapConfig()
    if args.endpoint:
        cfg.mode, cfg.telemetry_endpoint = "direct", args.endpoint
    if args.router:
        cfg.mode = "fabric"
        cfg.fabric.router_endpoint = args.router
    if args.cert_dir:
        cfg.fabric.cert_dir = args.cert_dir
        cfg.where = FLAGS
    if args.name:
        cfg.fabric.name = args.name
    if args.curve_key or args.server_key:
        cfg.security.mode = "curve"
        cfg.security.secret_key_file = args.curve_key or cfg.security.secret_key_file
        cfg.security.server_public_key_file = args.server_key or cfg.security.server_public_key_file
    if args.allow_insecure:
        cfg.security.allow_insecure = True
    if args.robot:
        cfg.robots = list(args.robot)
    if args.robot_key:
        cfg.robot_key = load_public_key(args.robot_key)
    return cfg


def _warm_up() -> None:
    """Load what checking a signature needs before the first message: loaded on the first
    signed one, it held the reading of the messages behind it (their receive times late)."""
    from common.wire.signing import verify

    verify(bytes(32), bytes(64), b"")


@dataclass
class Received:
    """One message as the tap read it."""

    t_recv_ns: int  # this PC's monotonic clock
    robot: bytes  # the robot's name on the wire, b"" for an unnamed robot
    topic: str  # TOPICS' name
    msg: Message
    size: int  # bytes on the wire


class WireTap:
    """Reads ``topics`` of the robots ``config`` names; ``read`` hands out what passed the codec."""

    def __init__(
        self,
        config: TapConfig,
        topics: tuple[str, ...] = tuple(TOPICS),
        *,
        ctx: Any = None,
    ) -> None:
        from common.wire.codec import check_robot_name

        unknown = set(topics) - set(TOPICS)
        if unknown:
            raise ConfigError(f"unknown topic(s) {sorted(unknown)}; known: {sorted(TOPICS)}")
        self.config = config
        self.topics = topics
        self.session: Any = None
        self._ctx = None
        names = [check_robot_name(r) for r in config.robots]
        _warm_up()
        if config.mode == "fabric":
            self.inbox = self._open_fabric(config, names)
        else:
            self.inbox = self._open_direct(config, names, ctx)

    def _open_direct(self, config: TapConfig, names: list[bytes], ctx: Any) -> Any:
        import zmq

        from common.keys.curve import check_endpoint, client_options
        from common.wire.transport import Subscriber

        check_endpoint(config.telemetry_endpoint, config.security)
        options = client_options(config.security)
        if ctx is None:
            ctx = self._ctx = zmq.Context()
        prefixes = tuple(
            name_prefix(TOPICS[t].TOPIC, name) for t in self.topics for name in names or [b""]
        )
        return Subscriber(
            ctx,
            config.telemetry_endpoint,
            bind=False,
            rcvhwm=10_000,
            sock_opts=options,
            name="tap",
            topics=prefixes,
            reconnect=True,
            link_name="telemetry",
        )

    def _open_fabric(self, config: TapConfig, names: list[bytes]) -> Any:
        from common.fabric.link import FabricSubscriber
        from common.fabric.session import member_name, open_member_session

        if not names:
            raise ConfigError(
                "reading the fabric needs the robot's name (--robot NAME, or the config's "
                "robot_name / robots): the router grants exact keys, never a wildcard"
            )
        try:
            self.member = member_name(config.fabric, None, config.where)
            self.session = open_member_session(config.fabric, self.member, config.where, "tap")
        except ConfigError as e:
            if config.where != FLAGS:
                raise
            raise ConfigError(f"{e} (on the command line: --cert-dir DIR, --name NAME)") from None
        keys = tuple(keyexprs.robot_key(n, t) for n in names for t in self.topics)
        return FabricSubscriber(
            self.session, keys, expect_name=None, name="tap", queue=10_000, latest_value=False
        )

    def read(self, timeout_s: float) -> list[Received]:
        """What arrived within ``timeout_s`` (at once if something waits), oldest first."""
        if not self.inbox.poll(timeout_s):
            return []
        wires: list[bytes] = []
        got = self.inbox.drain(4096, wires)
        out = []
        for (msg, t_recv), data in zip(got, wires, strict=True):
            topic = TOPIC_OF.get(type(msg))
            if topic is None or topic not in self.topics:
                continue  # a prefix of ours matched another type (never, by the codec's topics)
            out.append(Received(t_recv, split_name(data)[0], topic, msg, len(data)))
        return out

    @property
    def rejected(self) -> Counter[str]:
        """Messages the codec refused, by error class (``SignatureError``: a forged one)."""
        return Counter(self.inbox.rejected)

    def connection(self) -> dict[str, Any]:
        """What the tap knows of its connection: whether it is up, and how often it was opened
        again (a direct link whose handshake failed, libzmq gave up on)."""
        if self.config.mode == "fabric":
            try:
                up = bool(list(self.session.info.routers_zid()))
            except Exception:  # a closed session
                up = False
            return {"up": up, "via": f"{self.config.source} as {self.member}"}
        health = self.inbox.health()
        return {
            "up": bool(health.get("link_telemetry_up", 0.0)),
            "reopened": int(health.get("link_telemetry_reopened", 0.0)),
            "via": self.config.source,
        }

    def why_nothing(self) -> str:
        """A hint for a tap that read nothing: what the connection says, and what to check."""
        state = self.connection()
        names = ", ".join(self.config.robots) or "any robot"
        if self.config.mode == "fabric":
            if not state["up"]:
                return (
                    f"no router reached at {state['via']}: is `deepxpalm router` running there, "
                    "UDP open to it, and our certificate signed by its CA?"
                )
            return (
                f"the router answers, but nothing of {names} came: is the robot connected to "
                "it (its name exact), and does the roster let us read it (role controller, "
                "observer or recorder)? `deepxpalm doctor --role router` on the router host"
            )
        if state["up"]:
            return (
                f"connected to {state['via']}, but {names} sent nothing on these topics: is the "
                "robot node running its loop (its journal), and is the robot name right?"
            )
        curve = self.config.security.mode == "curve"
        if state["reopened"] or curve:
            return (
                f"no connection to {state['via']}"
                + (
                    ": the CURVE handshake failed. Is our key in the robot's allowlist "
                    "(`deepxpalm keys allow`), and the robot's public key the one it holds?"
                    if state["reopened"]
                    else ": no robot answered, or the CURVE handshake was refused (our key not "
                    "in the robot's allowlist, or the wrong robot key)"
                )
                + " The robot's heartbeat counts refused keys (curve_refused)."
            )
        return (
            f"no connection to {state['via']}: is the robot node running, its port open "
            "(`nc -vz HOST 5555`), and its link plain? A CURVE robot needs --config or "
            "--curve-key and --server-key"
        )

    def close(self) -> None:
        self.inbox.close()
        if self.session is not None:
            from common.fabric.session import close_session

            close_session(self.session)
            self.session = None
        if self._ctx is not None:
            self._ctx.term()
            self._ctx = None
