"""The UR driver's settings, and the checks that keep its watchdog able to stop the arm."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from common.config.typed import param
from common.errors import ConfigError
from robot_side.arm.base import ArmLimits

log = logging.getLogger(__name__)

#: A dead node's arm is still within this (docs/arm.md): two watchdog windows (a controller
#: was reported to trip that late, on URSim) must leave time to decelerate inside it.
STOP_BUDGET_S = 0.4


@dataclass
class URArmConfig:
    host: str = param("192.168.1.10", "the UR controller's IP (pendant: Settings > Network)")
    frequency_hz: float = param(
        125.0,
        "RTDE rate of both interfaces (the state stream, the control script's replies); the "
        "e-Series streams up to 500 Hz, and nothing here reads faster than the 120 Hz frame loop",
    )
    stale_after_s: float = param(
        0.1, "a controller timestamp frozen this long means it stopped streaming: reads raise"
    )
    command_timeout_s: float = param(
        2.0, "a control call still busy after this (plus any deceleration) is abandoned"
    )
    watchdog_window_s: float = param(
        0.15,
        "ur-rtde's watchdog (setWatchdog at 1/window Hz): the controller stops the program and "
        "the arm when this process sends nothing this long (kill -9, SIGSTOP); kicked every "
        "20 ms, so a kick may come 130 ms late before it trips",
    )
    limits: ArmLimits = param(ArmLimits(), "workspace box, speed caps and the jog deadman")
    own_process: bool = param(
        True,
        "run the driver (the watchdog's keep-alive, the jog deadman, stops, the pose read "
        "back) in a process of its own, its keep-alive real-time where the unit grants it "
        "(docs/arm.md); false = inside the robot node, sharing its interpreter lock",
    )
    realtime_priority: int = param(
        20,
        "SCHED_FIFO priority of the keep-alive and deadman threads in the arm process where "
        "granted (the unit's LimitRTPRIO=, or root); refused: the highest niceness allowed. "
        "0 = never real-time",
    )


def check_watchdog_config(config: URArmConfig, lim: ArmLimits, deadman_period_s: float) -> None:
    """Refuse a watchdog window the keep-alive (kicks every ``deadman_period_s``) or the stops
    could not live with, or one that leaves a dead node's arm moving past the stop budget."""
    window = config.watchdog_window_s
    if not window > 0:
        raise ConfigError(
            "arm watchdog_window_s must be positive: the watchdog cannot be turned off"
        )
    if 2 * window >= STOP_BUDGET_S:
        raise ConfigError(
            f"arm watchdog_window_s {window:g}: a controller that trips as late as two "
            f"windows would leave no time to decelerate within the {STOP_BUDGET_S * 1000:.0f}"
            " ms a dead node may leave the arm moving (docs/arm.md); shorten it"
        )
    if window < 3 * deadman_period_s:
        raise ConfigError(
            f"arm watchdog_window_s {window:g} is less than three kicks "
            f"({deadman_period_s * 1000:.0f} ms apart): one late thread would stop "
            "the program; lengthen it"
        )
    # a stop waits for the script's answer and no kick may interrupt it (keep_alive)
    decel_s = lim.max_linear_speed_m_s / lim.stop_deceleration_m_s2
    if decel_s >= window:
        raise ConfigError(
            f"arm stop_deceleration_m_s2 {lim.stop_deceleration_m_s2:g} takes "
            f"{decel_s * 1000:.0f} ms from the speed cap, as long as the watchdog window "
            f"({window * 1000:.0f} ms): a stop sends nothing while it waits for the script, "
            "so the watchdog would trip on our own stops. Raise the deceleration"
        )
    if decel_s > window / 2:
        log.warning(
            "URArm: a stop from the %.2f m/s cap takes %.0f ms, over half the %.0f ms "
            "watchdog window: on a loaded machine the watchdog may trip during a stop "
            "(the arm stops either way); raise stop_deceleration_m_s2",
            lim.max_linear_speed_m_s,
            decel_s * 1000,
            window * 1000,
        )
