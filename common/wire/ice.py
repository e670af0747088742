"""Which STUN/TURN servers the two ends of a video call use (WebRTC's ICE servers).

Both ends need the same list: the robot's video server (aiortc) and the
operator's page (the browser, told by the dashboard). Empty, the default,
means host candidates only: no request leaves for a third-party server (aiortc
would otherwise ask Google's public STUN server), and the two machines must
reach each other over UDP (one LAN, or a VPN). Between sites that cannot, a
TURN server both ends can reach (for example on the relay host) carries the
media.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.config.typed import param
from common.errors import ConfigError

SCHEMES = ("stun:", "stuns:", "turn:", "turns:")


@dataclass
class IceConfig:
    servers: tuple[str, ...] = param(
        (),
        "STUN/TURN URLs, e.g. stun:relay.example.org:3478, turn:relay.example.org:3478; "
        "empty = host candidates only (the peers must reach each other over UDP)",
    )
    username: str = param("", "the TURN user name (TURN servers only)")
    credential_file: Path | None = param(
        None, "a file holding the TURN password (mode 0600); the page is given it too"
    )
    transport_policy: str = param(
        "all",
        "'relay': the page sends and takes media only through the TURN server (for a "
        "site whose policy forbids direct UDP, or to prove the TURN path); 'all' also "
        "tries direct paths. The robot's end (aiortc) always offers every path",
    )

    def __post_init__(self) -> None:
        if self.transport_policy not in ("all", "relay"):
            raise ValueError("ice.transport_policy must be 'all' or 'relay'")
        if self.transport_policy == "relay" and not any(
            u.startswith(("turn:", "turns:")) for u in self.servers
        ):
            raise ValueError("ice.transport_policy = 'relay' needs a TURN server in ice.servers")
        for url in self.servers:
            if not url.startswith(SCHEMES):
                raise ValueError(f"ICE server {url!r} must start with one of {SCHEMES}")
        if any(u.startswith(("turn:", "turns:")) for u in self.servers) and not (
            self.username and self.credential_file
        ):
            raise ValueError("a TURN server needs ice.username and ice.credential_file")

    def as_dicts(self) -> list[dict[str, Any]]:
        """The list in the form both WebRTC APIs take (``RTCIceServer`` fields)."""
        if not self.servers:
            return []
        server: dict[str, Any] = {"urls": list(self.servers)}
        if self.credential_file is not None:
            try:
                credential = Path(self.credential_file).read_text().strip()
            except OSError as e:
                raise ConfigError(
                    f"ice.credential_file {self.credential_file}: cannot read it: {e}"
                ) from None
            server.update(username=self.username, credential=credential)
        return [server]
