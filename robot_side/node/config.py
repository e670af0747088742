"""The robot node's configuration: every default in one place, printed by --help."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from common.config.typed import param
from common.fabric.session import FabricConfig
from common.keys.curve import SecurityConfig


@dataclass
class RenderConfig:
    mode: Literal["direct", "mask", "mask_ground_truth"] = param(
        "mask",
        "direct: no mask (the paper's baseline); mask: the CNN's pattern; "
        "mask_ground_truth: a simulator's true pattern (simulation only)",
    )
    method: Literal["antialiased", "plain", "area"] = param(
        "antialiased", "10x10 -> 3x3 downsizing; antialiased bicubic lets every taxel count"
    )
    order: Literal["peak_then_mask", "mask_then_peak"] = param(
        "mask_then_peak",
        "mask first: the paper's order loses 0-deg patterns (8-29% match vs 100%, docs/tactile.md)",
    )
    contact_threshold_n: float = param(1.0, "largest taxel below this = no contact (sensor floor)")
    compiled_step: bool = param(
        True,
        "mask mode on the numba classifier: sanitize, classify and render a frame in one "
        "compiled call (robot_side/node/compiled_step.py); false = the plain path",
    )
    deadband_n: float = param(
        0.05, "a stimulus cell must change by more than this to be resent (0.04 mm of depth)"
    )
    keyframe_interval_ms: float | None = param(
        None,
        "resend an unchanged stimulus this often, so a lost change cannot persist; unset = "
        "500 on a direct link (TCP loses nothing), 25 on the fabric, where a stimulus is a "
        "datagram and a lost change must be made good within the operator's staleness "
        "(150 ms) less the path's delay",
    )


@dataclass
class ClassifierConfig:
    path: Path | None = param(None, "model file; unset = the model shipped in the package")
    backend: str | None = param(None, "inference backend; unset = the fastest exact one")


@dataclass
class RobotLinkConfig:
    telemetry_endpoint: str = param(
        "tcp://127.0.0.1:5555", "PUB bound here: stimuli, frames, heartbeats"
    )
    command_endpoint: str = param(
        "tcp://127.0.0.1:5556", "SUB bound here: operator commands and heartbeats"
    )
    heartbeat_rate_hz: float = param(
        20.0,
        "heartbeats confirm an unchanged stimulus is still current and carry the clock and "
        "the lease, on either link (on the fabric the 25 ms keyframes confirm it too, and "
        "what goes beside them must fit QUIC's smallest window: docs/fabric.md)",
    )
    heartbeat_stats_period_ms: float | None = param(
        None,
        "how often a heartbeat carries the node's counters (about 1.8 kB; the heartbeat "
        "itself about 250 B); unset = every heartbeat on a direct link, every 1000 ms "
        "on the fabric, where a heartbeat must fit one datagram to travel as a latest value",
    )
    heartbeat_early_ms: float = param(
        20.0, "a heartbeat due within this long goes out with a frame's work, not on its own"
    )
    frame_display_rate_hz: float | None = param(
        None,
        "raw frames for the operator's heatmaps (about 1 kB each); 0 = never; unset = 15 on "
        "a direct link, none on the fabric, where a frame takes half of QUIC's smallest "
        "congestion window and the stimuli wait behind it (docs/fabric.md)",
    )
    deadman_ms: float = param(
        250.0,
        "this long after the operator sent its newest fresh message (its clock, mapped to "
        "ours), the arm stops and the gripper holds; must exceed the link's one-way delay",
    )
    max_command_age_ms: float = param(
        250.0,
        "a command sent longer ago than this (the operator's send time on our clock) is "
        "refused, so a backlog ages out instead of moving the arm late; must exceed the "
        "link's one-way delay (raise both on a satellite link)",
    )
    max_messages_per_wake: int = param(
        32, "operator messages read per loop turn at most: a flood cannot take the frame loop"
    )
    command_backlog_pause_ms: float = param(
        8.0,
        "after a full batch, commands wait this long for the next turn while frames go on; "
        "what waits only ages (stale commands are refused)",
    )
    mode: Literal["bind", "fabric"] = param(
        "bind",
        "bind: the operator connects to our two endpoints (one site opens a port); fabric: we "
        "connect out to a Zenoh router across sites (deepxpalm router, the [link.fabric] "
        "table), nobody connects in",
    )
    robot_name: str = param(
        "",
        "our name on the wire, after every topic (docs/protocol.md) and our roster name; "
        "needed on the fabric, which carries several robots; empty = unnamed (direct link "
        "only)",
    )
    roster_file: Path | None = param(
        None,
        "operators and their roles (common/keys/roster.py): commands must then be signed, and "
        "only the holder of the control lease is obeyed; needed on the fabric. SIGHUP "
        "(systemctl reload) reads it again",
    )
    lease_request_timeout_ms: float = param(
        2000.0, "a lease request the holder neither grants nor answers lapses after this"
    )
    signing_key_file: Path | None = param(
        None,
        "our Ed25519 key (NAME.sign_secret, `deepxpalm keys generate-signing`): everything we "
        "send is signed, and operators holding our public key drop telemetry that is not, so "
        "a compromised router cannot forge what a palm feels; needed with mode fabric unless "
        "unsigned_stream; unset = unsigned",
    )
    unsigned_stream: bool = param(
        False,
        "with mode fabric, run without signing_key_file: anyone who can inject into the "
        "router (a compromised router host) can then make operators' palms feel what did "
        "not happen",
    )
    allow_plain_commands: bool = param(
        False,
        "bound with security.mode = 'plain' and no roster_file: take commands from any "
        "process that reaches the command port (on loopback: every user and program on this "
        "PC) although an arm, gripper or camera is configured; false = refuse to start so",
    )
    video_url: str = param(
        "",
        "the video server on this PC (deepxpalm video, e.g. ws://127.0.0.1:8890/): viewers' "
        "offers reach it through this link, so video opens no port; empty = no video here",
    )
    video_token_file: Path | None = param(
        None,
        "the video server's token_file (its signalling secret; deepxpalm video creates it); "
        "unset: video_url must carry the token (?token=), as deepxpalm video prints it",
    )
    video_viewer_timeout_s: float = param(
        5.0, "a viewer whose node has not been heard for this long loses its video session"
    )
    video_max_sessions: int = param(
        4,
        "video sessions at once through this link (as the video server's max_viewers); when "
        "full, a controller's offer closes an observer's session to make room",
    )
    video_sessions_per_key: int = param(
        2, "video sessions one operator key holds at once; a newer one closes its oldest"
    )
    video_offers_per_s: float = param(
        2.0,
        "video offers a second one key may make (as many at once); more are refused, "
        "counted and told why; a page that reconnects makes one every few seconds",
    )
    security: SecurityConfig = param(
        SecurityConfig(),
        "CURVE keys and the operator allowlist (mode bind)",
    )
    fabric: FabricConfig = param(
        FabricConfig(),
        "mode fabric: the router and our certificate (our roster name is robot_name); the "
        "endpoints and CURVE settings above are then unused",
    )

    def __post_init__(self) -> None:
        if self.video_url and not self.video_url.startswith(("ws://", "wss://")):
            raise ValueError(f"link.video_url must be a ws:// or wss:// URL: {self.video_url!r}")
        if self.video_viewer_timeout_s <= 0:
            raise ValueError("link.video_viewer_timeout_s must be positive")
        if self.video_max_sessions < 1 or self.video_sessions_per_key < 1:
            raise ValueError("link.video_max_sessions and video_sessions_per_key must be >= 1")
        if not self.video_offers_per_s > 0:
            raise ValueError("link.video_offers_per_s must be positive")


@dataclass
class AssistConfig:
    """The assist (robot_side/node/assist.py): how it moves, slower than the arm's caps."""

    turn_speed_rad_s: float = param(
        0.45, "the wrist's top speed while turning (about 26 deg/s; the gripper is open)"
    )
    shift_speed_m_s: float = param(0.03, "the TCP's top speed while shifting")
    gain_per_s: float = param(
        6.0, "velocity per unit of error left (the approach slows near it; the pose is 50 ms old)"
    )
    side_offset_mm: float = param(
        5.0,
        "one shift toward centre (mm) when the band's offset cannot be measured: a side "
        "class is 3 mm or more off centre (the lab's threshold), so 5 mm centres anything "
        "3-8 mm off and re-grasps judge the rest",
    )
    max_shift_mm: float = param(
        10.0, "the longest shift one re-grasp makes by the band's measured offset (mm)"
    )
    centred_within_mm: float = param(
        2.5,
        "90 deg centre recognised is aligned only when the band's measured offset is this "
        "close to the pad centre too (mm): 'centre' ends 3 mm out",
    )
    max_turn_deg: float = param(
        50.0, "the wrist never turns further from where the assist began (a singularity nears)"
    )
    angle_tolerance_deg: float = param(
        3.0, "a turn this close to its target is done (the band is measured to 1-4 deg)"
    )
    aligned_within_deg: float = param(
        12.0,
        "90 deg centre recognised is aligned only when the band's angle on the pads (its "
        "second moments) is this close to 90 deg too: the classes are 45 deg wide, and a "
        "pipette at 113 deg can read '90' and lift as '135'",
    )
    position_tolerance_mm: float = param(
        0.5, "a shift this close to its target is done ('centre' spans 3 mm either way)"
    )
    release_ms: float = param(
        50.0,
        "the fingers ease off (gripper_ease) at least this long, and until nothing is felt, "
        "before moving",
    )
    settle_ms: float = param(
        250.0, "after a re-grasp: contact held this long before judging (the operator's own)"
    )
    phase_timeout_s: float = param(
        8.0, "a phase not finished by then (or nothing felt): the assist gives up"
    )
    max_regrasps: int = param(3, "re-grasps before giving up")
    box_margin_m: float = param(0.002, "its targets are kept this far inside the workspace box")

    def __post_init__(self) -> None:
        for name in (
            "turn_speed_rad_s",
            "shift_speed_m_s",
            "gain_per_s",
            "phase_timeout_s",
            "max_shift_mm",
            "centred_within_mm",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"assist.{name} must be positive")
        if self.max_regrasps < 1:
            raise ValueError("assist.max_regrasps must be at least 1")


@dataclass
class RobotConfig:
    publish_rate_hz: float = param(
        60.0, "at most this many stimuli per second (frames come at 120 Hz)"
    )
    max_frame_age_ms: float = param(50.0, "a frame older than this is never rendered")
    render: RenderConfig = param(RenderConfig(), "how frames become stimuli")
    classifier: ClassifierConfig = param(ClassifierConfig(), "the tilt/position CNN (mask mode)")
    link: RobotLinkConfig = param(RobotLinkConfig(), "sockets and link health")
    assist: AssistConfig = param(
        AssistConfig(), "the assist an operator holds (arm_assist): turn, shift, re-grasp"
    )
    tactile: dict[str, Any] = param(
        {"kind": "scripted"}, "tactile pads: kind + that kind's settings"
    )
    gripper: dict[str, Any] = param({"kind": "none"}, "gripper: kind (none = not built) + settings")
    arm: dict[str, Any] = param({"kind": "none"}, "arm: kind (none = not built) + settings")
