"""What happens to each message on one direction of the link.

Pure and seeded: ``DirectionImpairment.process`` takes a message and the
time it entered the link and returns when (and as what bytes) it leaves.
No sockets and no clock reads, so the statistics are tested in virtual time
and the proxy only schedules what this module decides.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from common.config import param
from common.errors import ConfigError

NS_PER_MS = 1_000_000

#: Direction names: telemetry flows robot -> operator, commands the other way.
DIRECTIONS: tuple[str, str] = ("to_operator", "to_robot")


@dataclass
class DirectionConfig:
    """Impairments of one direction."""

    delay_ms: float = param(0.0, "one-way delay added to every message")

    def __post_init__(self) -> None:
        if self.delay_ms < 0:
            raise ConfigError(f"delay_ms must be >= 0, not {self.delay_ms}")


@dataclass
class Scenario:
    """A named link: one impairment config per direction."""

    name: str = param("none", "shown in logs and reports")
    description: str = param("no impairment", "one line on what the link stands for")
    to_operator: DirectionConfig = param(DirectionConfig(), "robot -> operator (telemetry)")
    to_robot: DirectionConfig = param(DirectionConfig(), "operator -> robot (commands)")

    def direction(self, name: str) -> DirectionConfig:
        if name not in DIRECTIONS:
            raise ConfigError(f"unknown direction {name!r}; known: {list(DIRECTIONS)}")
        return getattr(self, name)

    def with_delay(self, name: str, delay_ms: float) -> Scenario:
        """A copy with one direction's base delay replaced (CLI overrides)."""
        d = dataclasses.replace(self.direction(name), delay_ms=delay_ms)
        return dataclasses.replace(self, **{name: d})


class DirectionImpairment:
    """The impairment state machine of one direction."""

    def __init__(
        self, config: DirectionConfig, *, seed: int = 0, name: str = "link", start_ns: int = 0
    ) -> None:
        self.config = config
        self.name = name
        self.seed = seed
        self.start_ns = start_ns
        self._delay_ns = round(config.delay_ms * NS_PER_MS)

    def process(self, now_ns: int, payload: bytes) -> list[tuple[int, bytes]]:
        """Deliveries ``(due_ns, bytes)`` for a message entering the link at ``now_ns``.

        An empty list is a loss; two entries a duplicate.
        """
        return [(now_ns + self._delay_ns, payload)]
