"""The operator node's configuration: every default in one place, printed by --help."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from common.config.typed import param
from common.fabric.session import FabricConfig
from common.keys.curve import SecurityConfig
from operator_side.dashboard.config import DashboardConfig
from operator_side.palm.renderer import RendererConfig


@dataclass
class OperatorLinkConfig:
    telemetry_endpoint: str = param(
        "tcp://127.0.0.1:5555", "the robot's telemetry PUB (or the netsim's)"
    )
    command_endpoint: str = param(
        "tcp://127.0.0.1:5556", "the robot's command SUB (or the netsim's)"
    )
    stale_after_ms: float = param(
        150.0,
        "a stimulus older than this is not rendered; with none fresher, every linkage lifts off",
    )
    jog_blind_after_ms: float = param(
        150.0,
        "nothing from the robot sent within this long (its send time on our clock): jogs are "
        "held, since we no longer see what we steer; the robot's deadman then stops the arm",
    )
    jog_max_age_ms: float = param(
        150.0,
        "a jog or assist enable older than this when it would go out (it waited on a busy "
        "operator PC: in the page's socket, the dashboard or this node's queue) is dropped; "
        "the robot's deadman then stops the arm",
    )
    heartbeat_rate_hz: float = param(20.0, "heartbeats keep the robot's deadman satisfied")
    heartbeat_early_ms: float = param(
        20.0, "a heartbeat due within this long goes out on a wake-up already happening"
    )
    reopen_after_ms: float = param(
        1000.0,
        "no telemetry for this long: open the sockets again (libzmq gives up on a "
        "connection after a protocol error such as an oversized frame)",
    )
    robot_name: str = param(
        "",
        "the robot to follow (its link.robot_name): required on the fabric; on a direct link "
        "empty = an unnamed robot",
    )
    signing_key_file: Path | None = param(
        None,
        "our Ed25519 key (NAME.sign_secret from `deepxpalm keys generate-signing`): every "
        "command and heartbeat is signed, as a robot with a roster requires",
    )
    robot_key_file: Path | None = param(
        None,
        "the robot's public signing key (its NAME.sign): telemetry not signed by it is "
        "dropped (a compromised router cannot forge what the palm feels); needed with mode "
        "fabric unless unsigned_stream",
    )
    unsigned_stream: bool = param(
        False,
        "with mode fabric, run without robot_key_file and take the robot's telemetry unsigned: "
        "a compromised router can then make the palm feel what did not happen",
    )
    max_telemetry_age_ms: float = param(
        500.0,
        "with robot_key_file: signed telemetry sent longer ago than this (its send time on our "
        "clock) is refused, and a restarted robot is believed once a heartbeat of its new run "
        "answers one of ours; must exceed the link's round trip (docs/protocol.md)",
    )
    want_frames: bool = param(
        True,
        "subscribe to raw frames while something shows them (the dashboard's heatmap, "
        "--status-file); a node with neither never does; false = never. A robot skips "
        "encoding frames nobody subscribes to (on the fabric; a direct link always sends)",
    )
    request_control: bool = param(
        False,
        "ask the robot for its control lease at start, and again while nobody holds it "
        "(controller keys only; a held lease changes hands only when its holder grants it)",
    )
    gripper_confirm_ms: float = param(
        600.0,
        "a gripper command the robot's heartbeats have not confirmed by then (lost, or refused "
        "as stale on a slow link) is sent again, fresh",
    )
    stop_resend_ms: float = param(
        50.0,
        "an arm_stop the robot's heartbeats have not yet shown latched is sent again this often "
        "(a new command), so a lost one cannot delay a STOP by a retransmission; 0 = never",
    )
    stop_resend_for_ms: float = param(
        1000.0,
        "resending a STOP ends after this long without the robot showing it latched (counted "
        "stops_unconfirmed), or at once when this operator sends another arm command",
    )
    gripper_resends: int = param(
        2, "resends of an unconfirmed gripper command before it is counted gripper_unconfirmed"
    )
    observer_heartbeat_rate_hz: float = param(
        2.0,
        "signed and neither holding nor asking for the lease: heartbeats only keep the "
        "robot's clock estimate for us, and each costs it a signature check (docs/security.md), "
        "so an observer sends this few; holders and requesters send heartbeat_rate_hz",
    )
    security: SecurityConfig = param(
        SecurityConfig(), "CURVE keys: ours and the robot's public key (mode direct)"
    )
    mode: Literal["direct", "fabric"] = param(
        "direct",
        "direct: ZeroMQ to the two endpoints above (the robot's, or a netsim's in between); "
        "fabric: through a Zenoh router across sites ([link.fabric]; robot_name says which "
        "robot), where the endpoints and CURVE settings are unused",
    )
    fabric: FabricConfig = param(
        FabricConfig(), "mode fabric: the router, our certificate and our roster name"
    )

    def __post_init__(self) -> None:
        if not (math.isfinite(self.jog_max_age_ms) and self.jog_max_age_ms > 0):
            raise ValueError(f"link.jog_max_age_ms must be positive, not {self.jog_max_age_ms}")


@dataclass
class OperatorConfig:
    link: OperatorLinkConfig = param(OperatorLinkConfig(), "sockets and link health")
    renderer: RendererConfig = param(RendererConfig(), "stimulus to servo goals")
    servos: dict[str, Any] = param({"kind": "in_memory"}, "LinkGlide servo bus: kind + settings")
    palm_guard: bool = param(
        True,
        "with a feetech bus, `deepxpalm operator` starts `deepxpalm palm guard` beside the node: "
        "it lifts the palm the moment the node ends, however it ends",
    )
    latency_window: int = param(20000, "latency samples kept for percentiles")
    dashboard: DashboardConfig = param(DashboardConfig(), "live web page for the operator")
