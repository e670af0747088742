"""Who may connect and what each operator key may do: one TOML file, read by router and robot.

```toml
[[operator]]
name = "alice"
role = "controller"        # controller (may hold a robot's control lease), observer, recorder
curve_key = "Z85..."       # her CURVE public key (NAME.key): a direct link lets it in
signing_key = "hex..."     # her Ed25519 public key (NAME.sign): the robot checks her signatures
video = true               # optional: an observer may watch the robot's camera too (below)

[[robot]]
name = "cell1"             # the name on the wire (docs/protocol.md, Robot names)
curve_key = "Z85..."       # the robot PC's CURVE public key
names = ["cell1", "cell1-cam"]  # optional: every name this key may use (default: [name])
```

The router (``deepxpalm router``) makes its access control from ``name``
and ``role`` (each member's certificate carries its name): a controller may
put commands, an observer only stops and heartbeats, a recorder nothing, and
a robot puts under its own names and reads only its inbox, so one robot's PC
cannot pose as another robot. A name belongs to one member. The robot reads
``signing_key`` and ``role`` (it acts only on commands signed by the key
that holds its lease); ``curve_key`` lets a member in on a direct link. The
robot trusts its own copy, never the router's: docs/security.md.

Video is a controller's: the robot answers a video offer only from a
controller's key, or from an observer whose entry says ``video = true``. A
recorder never gets video (``video = true`` on one is an error), and
``video = false`` keeps a controller from it.

A reload that would leave no robot or no controller where there were some
(an empty file, one cut short) is refused (``RosterLockoutError``) unless
the file says so at its top, before any entry::

    allow_lockout = true   # this roster may shut every robot or every controller out
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from common.errors import ConfigError
from common.wire.codec import DecodeError, check_robot_name
from common.wire.messages import ROLES
from common.wire.signing import parse_public_key


@dataclass(frozen=True)
class OperatorEntry:
    name: str
    role: str
    curve_key: bytes | None  # z85, as ZeroMQ's authenticator hands it over
    signing_key: bytes | None  # raw 32 bytes
    #: the roster's ``video``: None = the role's default (a controller's, nobody else's)
    video: bool | None = None

    @property
    def may_watch(self) -> bool:
        """Whether the robot answers this key's video offers (never a recorder's)."""
        if self.role == "recorder":
            return False
        return self.video if self.video is not None else self.role == "controller"


@dataclass(frozen=True)
class RobotEntry:
    name: str
    curve_key: bytes | None
    #: every name this key may publish and receive under (``name`` is always one of them)
    names: tuple[str, ...] = ()

    def wire_names(self) -> frozenset[bytes]:
        return frozenset(n.encode("ascii") for n in (self.name, *self.names))


class RosterLockoutError(ConfigError):
    """A roster that would shut every robot or every controller out, not marked as meant."""


@dataclass(frozen=True)
class Roster:
    operators: tuple[OperatorEntry, ...]
    robots: tuple[RobotEntry, ...] = ()
    #: the file says it may leave no robot or no controller (``allow_lockout = true``)
    allow_lockout: bool = False

    def by_signing_key(self) -> dict[bytes, OperatorEntry]:
        return {op.signing_key: op for op in self.operators if op.signing_key is not None}

    def by_curve_key(self) -> dict[bytes, OperatorEntry]:
        return {op.curve_key: op for op in self.operators if op.curve_key is not None}

    def robot_curve_keys(self) -> frozenset[bytes]:
        return frozenset(r.curve_key for r in self.robots if r.curve_key is not None)

    def robot_names_by_curve_key(self) -> dict[bytes, frozenset[bytes]]:
        """Each robot CURVE key (z85) and the wire names it may publish and receive under."""
        names: dict[bytes, frozenset[bytes]] = {}
        for r in self.robots:
            if r.curve_key is not None:
                names[r.curve_key] = names.get(r.curve_key, frozenset()) | r.wire_names()
        return names

    def controllers(self) -> tuple[str, ...]:
        return tuple(op.name for op in self.operators if op.role == "controller")

    def summary(self) -> str:
        """Who is in it, for a log line or the doctor: counts and names, by kind."""
        parts = []
        robots = [r.name + ("" if not r.names else f" (also {', '.join(r.names)})")
                  for r in self.robots]  # fmt: skip
        parts.append(f"{len(robots)} robots ({', '.join(robots) or 'none'})")
        for role in ROLES:
            names = [op.name for op in self.operators if op.role == role]
            parts.append(f"{len(names)} {role}s ({', '.join(names) or 'none'})")
        return ", ".join(parts)


def check_replacement(old: Roster, new: Roster, path: Path | str) -> None:
    """Refuse a new roster that would leave no robot or no controller where ``old`` had some.

    What an empty file or one cut at an entry boundary parses into: taken
    in, it would lock the whole fleet out (every robot refused at the router,
    no operator obeyed). The file's ``allow_lockout = true`` says it is meant.
    """
    if new.allow_lockout:
        return
    lost = []
    if old.robots and not new.robots:
        lost.append(f"every robot ({len(old.robots)})")
    if old.controllers() and not new.controllers():
        lost.append(f"every controller ({', '.join(old.controllers())})")
    if lost:
        raise RosterLockoutError(
            f"roster {path} would remove {' and '.join(lost)}: an empty or truncated file? "
            "Refused; if it is meant, put `allow_lockout = true` at the top of the file, "
            "before any entry"
        )


def _z85(text: object, where: str) -> bytes:
    if not isinstance(text, str) or len(text.strip()) != 40:
        raise ConfigError(f"{where}.curve_key must be a 40-character Z85 public key")
    return text.strip().encode("ascii")


def _str(entry: dict, key: str, where: str) -> str:
    value = entry.get(key)
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where}.{key} must be a non-empty string")
    return value


def load_roster(path: Path) -> Roster:
    """Read and check a roster file; ``ConfigError`` names the entry that is wrong."""
    try:
        text = Path(path).read_text()
    except OSError as e:
        raise ConfigError(f"cannot read roster {path}: {e}") from None
    return parse_roster(text, path)


def parse_roster(text: str, path: Path | str) -> Roster:
    """A roster from its text (``path`` names it in errors)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"cannot read roster {path}: {e}") from None
    unknown = set(data) - {"operator", "robot", "allow_lockout"}
    if unknown:
        raise ConfigError(f"roster {path}: unknown tables {sorted(unknown)}")
    operators = []
    seen: set[str] = set()
    for i, entry in enumerate(data.get("operator", [])):
        where = f"{path}: operator[{i}]"
        extra = set(entry) - {"name", "role", "curve_key", "signing_key", "video"}
        if extra:
            raise ConfigError(f"{where}: unknown keys {sorted(extra)}")
        name = _str(entry, "name", where)
        role = _str(entry, "role", where)
        if role not in ROLES:
            raise ConfigError(f"{where}.role = {role!r} is not one of {list(ROLES)}")
        if name in seen:
            raise ConfigError(f"{where}: operator {name!r} is listed twice")
        seen.add(name)
        curve = entry.get("curve_key")
        signing = entry.get("signing_key")
        video = entry.get("video")
        if video is not None and not isinstance(video, bool):
            raise ConfigError(f"{where}.video must be true or false")
        if video and role == "recorder":
            raise ConfigError(f"{where}: a recorder never gets video (video = true on {name!r})")
        operators.append(
            OperatorEntry(
                name=name,
                role=role,
                curve_key=None if curve is None else _z85(curve, where),
                signing_key=None
                if signing is None
                else parse_public_key(str(signing), f"{where}.signing_key"),
                video=video,
            )
        )
    robots = []
    owner: dict[str, tuple[str, bytes | None]] = {}  # wire name -> (entry name, its key)
    for i, entry in enumerate(data.get("robot", [])):
        where = f"{path}: robot[{i}]"
        extra = set(entry) - {"name", "curve_key", "names"}
        if extra:
            raise ConfigError(f"{where}: unknown keys {sorted(extra)}")
        name = _str(entry, "name", where)
        names = entry.get("names", [])
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ConfigError(f"{where}.names must be a list of robot names")
        curve = entry.get("curve_key")
        key = None if curve is None else _z85(curve, where)
        for n in dict.fromkeys((name, *names)):
            try:
                check_robot_name(n)
            except DecodeError as e:
                raise ConfigError(f"{where}: {e}") from None
            if n in owner and (owner[n][1] != key or n == name == owner[n][0]):
                raise ConfigError(
                    f"{where}: robot name {n!r} is already {owner[n][0]!r}'s: a name belongs "
                    "to one key, or any robot could pose as another"
                )
            owner[n] = (name, key)
        more = tuple(n for n in dict.fromkeys(names) if n != name)
        robots.append(RobotEntry(name, key, more))
    lockout = data.get("allow_lockout", False)
    if not isinstance(lockout, bool):
        raise ConfigError(f"roster {path}: allow_lockout must be true or false")
    return Roster(tuple(operators), tuple(robots), lockout)


def operator_entry(
    name: str, role: str, curve_key: bytes, signing_key: bytes, video: bool | None = None
) -> str:
    """An ``[[operator]]`` entry as TOML (``curve_key`` z85, ``signing_key`` raw 32 bytes);
    ``video``: the entry's video flag (None: the role's default, no line)."""
    if role not in ROLES:
        raise ConfigError(f"role {role!r} is not one of {list(ROLES)}")
    entry = (
        f'[[operator]]\nname = "{name}"\nrole = "{role}"\n'
        f'curve_key = "{curve_key.decode()}"\nsigning_key = "{signing_key.hex()}"\n'
    )
    return entry if video is None else entry + f"video = {str(video).lower()}\n"


def robot_entry(name: str, curve_key: bytes, names: tuple[str, ...] = ()) -> str:
    """A ``[[robot]]`` entry as TOML: the key, and every robot name it may use."""
    for n in (name, *names):
        try:
            check_robot_name(n)
        except DecodeError as e:
            raise ConfigError(str(e)) from None
    entry = f'[[robot]]\nname = "{name}"\ncurve_key = "{curve_key.decode()}"\n'
    more = [n for n in dict.fromkeys(names) if n != name]
    if more:
        entry += "names = [" + ", ".join(f'"{n}"' for n in [name, *more]) + "]\n"
    return entry
