"""Who may connect and what each operator key may do: one TOML file, read by relay and robot.

```toml
[[operator]]
name = "alice"
role = "controller"        # controller (may hold a robot's control lease), observer, recorder
curve_key = "Z85..."       # her CURVE public key (NAME.key): the relay lets it in
signing_key = "hex..."     # her Ed25519 public key (NAME.sign): the robot checks her signatures

[[robot]]
name = "cell1"             # the name on the wire (docs/protocol.md, Robot names)
curve_key = "Z85..."       # the robot PC's CURVE public key: the relay lets it in
```

The relay reads ``curve_key`` and ``role`` (it drops commands from keys
that are not controllers); the robot reads ``signing_key`` and ``role`` (it
acts only on commands signed by the key that holds its lease). The robot
trusts its own copy, never the relay's: docs/security.md.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from common.codec import DecodeError, check_robot_name
from common.errors import ConfigError
from common.messages import ROLES
from common.signing import parse_public_key


@dataclass(frozen=True)
class OperatorEntry:
    name: str
    role: str
    curve_key: bytes | None  # z85, as ZeroMQ's authenticator hands it over
    signing_key: bytes | None  # raw 32 bytes


@dataclass(frozen=True)
class RobotEntry:
    name: str
    curve_key: bytes | None


@dataclass(frozen=True)
class Roster:
    operators: tuple[OperatorEntry, ...]
    robots: tuple[RobotEntry, ...] = ()

    def by_signing_key(self) -> dict[bytes, OperatorEntry]:
        return {op.signing_key: op for op in self.operators if op.signing_key is not None}

    def by_curve_key(self) -> dict[bytes, OperatorEntry]:
        return {op.curve_key: op for op in self.operators if op.curve_key is not None}

    def robot_curve_keys(self) -> frozenset[bytes]:
        return frozenset(r.curve_key for r in self.robots if r.curve_key is not None)


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
        data = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(f"cannot read roster {path}: {e}") from None
    unknown = set(data) - {"operator", "robot"}
    if unknown:
        raise ConfigError(f"roster {path}: unknown tables {sorted(unknown)}")
    operators = []
    seen: set[str] = set()
    for i, entry in enumerate(data.get("operator", [])):
        where = f"{path}: operator[{i}]"
        extra = set(entry) - {"name", "role", "curve_key", "signing_key"}
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
        operators.append(
            OperatorEntry(
                name=name,
                role=role,
                curve_key=None if curve is None else _z85(curve, where),
                signing_key=None
                if signing is None
                else parse_public_key(str(signing), f"{where}.signing_key"),
            )
        )
    robots = []
    for i, entry in enumerate(data.get("robot", [])):
        where = f"{path}: robot[{i}]"
        extra = set(entry) - {"name", "curve_key"}
        if extra:
            raise ConfigError(f"{where}: unknown keys {sorted(extra)}")
        name = _str(entry, "name", where)
        try:
            check_robot_name(name)
        except DecodeError as e:
            raise ConfigError(f"{where}.name: {e}") from None
        curve = entry.get("curve_key")
        robots.append(RobotEntry(name, None if curve is None else _z85(curve, where)))
    return Roster(tuple(operators), tuple(robots))
