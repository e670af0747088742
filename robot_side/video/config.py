"""The video server's settings, and the camera they name."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from common.config.typed import param
from common.wire.ice import IceConfig
from robot_side.camera import KINDS as CAMERA_KINDS
from robot_side.camera.base import Camera, build_camera
from robot_side.camera.config import LabCameraConfig, TestPatternConfig, V4L2Config


@dataclass
class VideoConfig:
    host: str = param(
        "127.0.0.1",
        "signalling address: loopback, where the robot node carries viewers' offers "
        "(its link.video_url); another only for dashboards connecting straight here",
    )
    port: int = param(8890, "signalling WebSocket port (media uses UDP ports ICE picks)")
    token_file: Path | None = param(
        None,
        "the file holding the secret a viewer's signalling must present (created, mode 0600, "
        "when missing; the robot node's link.video_token_file names the same file); "
        "unset: a fresh secret each run, in the URL printed at start",
    )
    media_interfaces: tuple[str, ...] = param(
        ("lo",),
        "network interfaces (e.g. eth0) or addresses the media's UDP sockets bind to: the one "
        "the operators' browsers reach this PC on; lo (loopback) only by default",
    )
    source: str = param(
        "test_pattern",
        f"which camera: one of {', '.join(CAMERA_KINDS)} (lab: a simulated lab's camera)",
    )
    max_viewers: int = param(
        4,
        "peer connections at once; each costs an encoder. When all are taken, a controller's "
        "offer (the robot node says whose) closes an observer's session to make room",
    )
    ice_timeout_s: float = param(
        10.0,
        "a viewer whose connection (ICE, then DTLS) has not completed this long after its "
        "answer gives its slot back: an offer that never connects holds no slot for longer",
    )
    ice: IceConfig = param(
        IceConfig(), "STUN/TURN servers; the operator's dashboard needs the same"
    )
    link_scenario: str = param(
        "",
        "a netsim scenario (name or .toml) each viewer's media crosses, through a datagram "
        "relay of its own (deepxpalm demo --scenario sets it); empty = straight to the viewer",
    )
    link_seed: int = param(0, "the media's impairment seed (with link_scenario)")
    test_pattern: TestPatternConfig = param(TestPatternConfig(), "the stamped test picture")
    v4l2: V4L2Config = param(V4L2Config(), "a USB camera on the robot PC")
    lab: LabCameraConfig = param(LabCameraConfig(), "a camera of a running simulated lab")
    record: Path | None = param(
        None,
        "record the camera into this MCAP file for as long as the server runs (beside the "
        "robot's recording: DIR/camera.mcap; deepxpalm demo --record sets it); unset: no recording",
    )
    record_fps: float = param(
        10.0, "frames a second recorded (at most the camera's own rate); JPEG, about 15-50 kB each"
    )

    def __post_init__(self) -> None:
        if not 0.1 <= self.record_fps <= 60:
            raise ValueError(f"video record_fps must be 0.1..60, not {self.record_fps}")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"video port must be 0..65535, not {self.port}")
        if self.max_viewers < 1:
            raise ValueError("video max_viewers must be at least 1")
        if not 0 < self.ice_timeout_s <= 120:
            raise ValueError(f"video ice_timeout_s must be in (0, 120], not {self.ice_timeout_s}")
        if not self.media_interfaces:
            raise ValueError("video media_interfaces must name at least one interface (e.g. lo)")


def camera_key(config: VideoConfig) -> str:
    """The camera's name in recordings and datasets (``observation.images.<key>``)."""
    return config.lab.camera if config.source == "lab" else config.source


def build_source(config: VideoConfig) -> Camera:
    """The camera ``config.source`` names, from its own section (``[video.<kind>]``)."""
    return build_camera(config.source, getattr(config, config.source, None))
