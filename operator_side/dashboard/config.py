"""The dashboard's settings: a plain dataclass, so the node's config can hold it
without importing the web server (the robot PC never installs ``websockets``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from common.config.typed import param
from common.web.web_token import check_token
from common.wire.ice import IceConfig
from operator_side.dashboard.jog_config import JogConfig

#: ``video_url`` value: signalling rides the operator node's link to the robot
VIDEO_OVER_LINK = "link"
#: a fixed page token for scripted setups, when the config sets none
TOKEN_ENV = "DEEPXPALM_DASHBOARD_TOKEN"


@dataclass
class DashboardConfig:
    enabled: bool = param(False, "serve the live dashboard; off unless asked for")
    host: str = param(
        "127.0.0.1", "address to bind: loopback keeps it private (reach it through an SSH tunnel)"
    )
    port: int = param(8765, "HTTP and WebSocket port (one port, so one tunnel suffices)")
    token: str = param(
        "",
        "the secret the page's WebSocket (and a script's Authorization: Bearer) must prove; "
        f"the page takes it from the printed URL's ?token= and keeps it per tab; empty: "
        f"${TOKEN_ENV}, else a fresh random one each run. Any local process could otherwise "
        "steer the arm. Never shown again after start-up; a config file holding it must not "
        "be readable by other users",
        secret=True,
    )
    allowed_hosts: list[str] = param(
        [],
        "names the page may be opened under besides the bound address, 127.0.0.1, localhost "
        "and [::1] (e.g. a VPN name); any other Host is refused (DNS rebinding)",
    )
    max_rate_hz: float = param(
        60.0,
        "snapshots sampled per second at most, for the link history (its latency is the "
        "youngest stimulus age sampled each second); the stimulus rate is 60 Hz",
    )
    push_rate_hz: float = param(
        30.0,
        "states pushed to each page per second at most, each drawn by the page: its redraw "
        "rate (the camera's 30 fps); never more than max_rate_hz, and nothing while no page "
        "is open",
    )
    video_url: str = param(
        "",
        "where the robot's video is offered: 'link' = through this node's link to the robot "
        "(and its relay; the robot sets link.video_url), or the video server's WebSocket, "
        "e.g. ws://127.0.0.1:8890/?token=... (the URL deepxpalm video prints, token included); "
        "empty: no video panel",
    )
    ice: IceConfig = param(
        IceConfig(),
        "STUN/TURN servers for the page's video; the robot's video server uses the same",
    )
    video_stale_ms: float = param(
        500.0,
        "the video badge turns STALE, and the picture is greyed, once the picture on screen "
        "is older than this (from its capture stamp; unstamped sources: since the last frame)",
    )
    jog: JogConfig = param(
        JogConfig(), "jogging the arm from the page: keyboard, gamepad, 3D mouse"
    )

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must be 0..65535 (0: any free port), not {self.port}")
        if self.video_url not in ("", VIDEO_OVER_LINK) and not self.video_url.startswith(
            ("ws://", "wss://")
        ):
            raise ValueError(
                f"video_url must be 'link' or a ws:// or wss:// URL, not {self.video_url!r}"
            )
        if self.token:
            check_token(self.token, "dashboard.token")
        if not (math.isfinite(self.video_stale_ms) and self.video_stale_ms > 0):
            raise ValueError(f"video_stale_ms must be > 0, not {self.video_stale_ms}")
        if not (math.isfinite(self.max_rate_hz) and 0 < self.max_rate_hz <= 240):
            raise ValueError(f"max_rate_hz must be in (0, 240], not {self.max_rate_hz}")
        if not (math.isfinite(self.push_rate_hz) and 0 < self.push_rate_hz <= 240):
            raise ValueError(f"push_rate_hz must be in (0, 240], not {self.push_rate_hz}")
