"""The robot's control lease as its newest heartbeat states it, seen from this operator.

With a signing key the robot obeys our commands only while we hold its lease
(robot_side/node/commands/lease.py). The heartbeat names the holder and the key waiting;
from that follow whether we control, what the dashboard shows, how often we
send heartbeats (an observer sends them at ``observer_heartbeat_rate_hz``)
and, with ``request_control``, when we ask for the lease.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from typing import Any

from common.wire.messages import Heartbeat
from operator_side.node.config import OperatorLinkConfig

log = logging.getLogger(__name__)

#: how often ``request_control`` asks while nobody holds the lease
LEASE_REQUEST_EVERY_NS = 250_000_000


class LeaseView:
    """Who holds the robot's lease, and what we do about it."""

    def __init__(self, link_cfg: OperatorLinkConfig, own_key: bytes | None, counters: Counter[str]):
        """``own_key``: our signing key's public half (None: unsigned, no lease)."""
        self.link_cfg = link_cfg
        self.own_key = own_key
        self.counters = counters
        #: the key holding the robot's control lease, as its newest heartbeat says
        self.holder: bytes | None = None
        #: the key waiting for the lease, as the robot's newest heartbeat says
        self.pending: bytes | None = None
        self._turn = 0
        self._next_request_ns = 0

    @property
    def ours(self) -> bool:
        """Whether the robot's newest heartbeat names our key as the lease holder."""
        return self.own_key is not None and self.holder == self.own_key

    def on_heartbeat(self, msg: Heartbeat) -> None:
        was = self.ours
        self.holder, self.pending = msg.lease_holder, msg.lease_pending
        if self.ours != was:
            self.counters["lease_gained" if not was else "lease_lost"] += 1
            log.info("control lease %s", "ours" if not was else "no longer ours")

    def heartbeat_wanted(self) -> bool:
        """Every due heartbeat, unless we are a signed observer (``observer_heartbeat_rate_hz``)."""
        link_cfg = self.link_cfg
        self._turn += 1
        if self.own_key is None or self.ours or link_cfg.request_control:
            return True
        if self.pending == self.own_key:
            return True  # asked: the robot's deadman will count from us as soon as it grants
        every = max(
            1, round(link_cfg.heartbeat_rate_hz / max(link_cfg.observer_heartbeat_rate_hz, 1e-3))
        )
        return self._turn % every == 0

    def request_if_free(self, now: int, ask: Callable[[str], None]) -> None:
        """``request_control``: ask while nobody holds the lease (refused until clocks sync)."""
        if not self.link_cfg.request_control or self.own_key is None:
            return
        if self.holder is not None or now < self._next_request_ns:
            return
        self._next_request_ns = now + LEASE_REQUEST_EVERY_NS
        self.counters["lease_requests_sent"] += 1
        ask("lease_request")

    def view(self) -> dict[str, Any] | None:
        """The control lease as the robot's newest heartbeat states it (None when unsigned)."""
        own = self.own_key
        if own is None:
            return None
        holder, pending = self.holder, self.pending
        return {
            "ours": holder == own,
            "holder": None if holder is None else holder.hex()[:12],
            "pending": None if pending is None else pending.hex()[:12],
            "asked": pending == own,
            "key": own.hex()[:12],
        }
