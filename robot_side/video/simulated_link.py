"""A viewer's media through the link simulator: its only reachable candidate is the simulator.

With ``link_scenario`` set (``deepxpalm demo --scenario NAME`` sets it), each
viewer's session gets its own datagram relay (``common/netsim/datagram.py``)
in front of each of the video server's media ports, and the answer names the
relay's port instead of the server's. The offer's candidates are dropped, so
the server cannot reach the browser directly either: it learns the browser's
address from the checks that arrive through the relay (a peer-reflexive
candidate, as ``media_binding`` already relies on). Every SRTP, RTCP, DTLS
and STUN packet of that viewer then crosses the scenario, both ways, and
nothing else does. docs/netsim.md (Video through the simulator) says why
this rather than a TURN server behind the relay.
"""

from __future__ import annotations

import logging
import re

from common.errors import ConfigError
from common.netsim.datagram import DatagramForwarder
from common.netsim.impairments import Scenario
from common.netsim.scenario import load_scenario

log = logging.getLogger(__name__)

_CANDIDATE = re.compile(r"^(a=candidate:\S+ \d+ udp \d+ )(\S+) (\d+)( typ host.*)$", re.I)


def scenario_for(name_or_path: str) -> Scenario | None:
    """The scenario the media crosses, or None (direct) for an empty name.

    ``none`` is a relay without impairment: the simulator's own cost, nothing else.
    """
    if not name_or_path:
        return None
    try:
        return load_scenario(name_or_path)
    except ConfigError as e:
        raise ConfigError(f"video link_scenario: {e}") from None


def without_candidates(sdp: str) -> str:
    """The offer with no candidate: the browser is reached only through the relay.

    ``a=end-of-candidates`` goes too: with it and no candidate, aiortc declares
    ICE failed at once, before a check through the relay can arrive.
    """
    drop = ("a=candidate:", "a=end-of-candidates")
    return "\r\n".join(line for line in sdp.split("\r\n") if not line.startswith(drop))


class SimulatedMediaPath:
    """The relays of one viewer's session; ``route(answer)`` starts them, ``stop()`` ends them."""

    def __init__(self, scenario: Scenario, *, seed: int, start_ns: int) -> None:
        self.scenario = scenario
        self.seed = seed
        self.start_ns = start_ns
        self.relays: dict[tuple[str, int], DatagramForwarder] = {}

    def route(self, answer_sdp: str) -> str:
        """The answer with each host candidate's port replaced by its relay's."""
        out = []
        for line in answer_sdp.split("\r\n"):
            m = _CANDIDATE.match(line)
            if m:
                host, port = m.group(2), int(m.group(3))
                relay = self.relays.get((host, port))
                if relay is None:
                    relay = DatagramForwarder(
                        self.scenario,
                        target=(host, port),
                        listen=(host, 0),
                        seed=self.seed,
                        start_ns=self.start_ns,
                    )
                    relay.start()
                    self.relays[(host, port)] = relay
                assert relay.address is not None
                line = f"{m.group(1)}{host} {relay.address[1]}{m.group(4)}"
            out.append(line)
        if not self.relays:
            raise ConfigError("video: the answer has no host candidate to put the simulator before")
        sdp = "\r\n".join(out)
        for (_, port), relay in self.relays.items():  # the default candidate too
            assert relay.address is not None
            sdp = re.sub(rf"^(m=video ){port}\b", rf"\g<1>{relay.address[1]}", sdp, flags=re.M)
        log.info(
            "video: media through netsim %r: %s",
            self.scenario.name,
            ", ".join(f"{r.address[1]}->{p}" for (_, p), r in self.relays.items() if r.address),
        )
        return sdp

    def counters(self) -> dict[str, dict]:
        """Each relay's counters, by the server port it stands before."""
        return {f"{h}:{p}": r.counters() for (h, p), r in self.relays.items()}

    def stop(self) -> None:
        for relay in self.relays.values():
            relay.stop()
