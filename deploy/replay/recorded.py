"""What a recording says of its node (which one, its config), and the replay's report."""

from __future__ import annotations

import collections
import logging
import tomllib
from pathlib import Path
from typing import Any

from common.config.typed import from_dict
from common.errors import ConfigError

log = logging.getLogger(__name__)

MAX_EXAMPLES = 10  # mismatches described in the report; all are counted


def recorded_config(metadata: dict[str, dict[str, str]], node: str) -> Any:
    """The node's effective config as the recording stored it (defaults if absent)."""
    if node == "robot":
        from robot_side.node.config import RobotConfig as cls
    else:
        from operator_side.node.config import OperatorConfig as cls
    text = metadata.get("deepxpalm.node", {}).get("config_toml")
    if text is None:
        log.warning("the recording holds no config; checking against today's defaults")
        return cls()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"the config stored in the recording does not parse: {e}") from None
    return from_dict(cls, data.get(node, data), where=node)


def node_of(path: Path, metadata: dict[str, dict[str, str]]) -> str:
    node = metadata.get("deepxpalm.node", {}).get("node")
    if node in ("robot", "operator"):
        return node
    from common.recording.mcap_recorder import read_recording

    for channel, _, _ in read_recording(path):
        prefix = channel.split("/", 1)[0]
        if prefix in ("robot", "operator"):
            return prefix
    raise ConfigError(f"{path} holds no robot/ or operator/ channel: is it a DeepXPalm recording?")


class Report:
    """Counts and the first few mismatches, per kind."""

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()
        self.examples: list[str] = []

    def ok(self, what: str) -> None:
        self.counts[what] += 1

    def mismatch(self, what: str, detail: str) -> None:
        self.counts[f"mismatch_{what}"] += 1
        if len(self.examples) < MAX_EXAMPLES:
            self.examples.append(f"{what}: {detail}")

    @property
    def mismatches(self) -> int:
        return sum(v for k, v in self.counts.items() if k.startswith("mismatch_"))
