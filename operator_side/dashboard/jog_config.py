"""How the operator's input devices steer the arm: caps, shaping and mappings.

The page reads these from the dashboard's hello and applies them to the raw
input (``jog.js``); the server applies the speed caps again to every jog it
forwards, and the robot clips once more to its own envelope.

A mapping gives, for each twist component ``vx vy vz wx wy wz`` (base frame),
a sum of signed device inputs: ``"-axis1"`` (gamepad axis 1, inverted),
``"button7-button6"`` (right trigger minus left), ``"-ty"`` (SpaceMouse
translation y, inverted), or ``""`` for none.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from common.config.typed import param

TWIST = ("vx", "vy", "vz", "wx", "wy", "wz")
_TERM = re.compile(r"([+-]?)(axis|button|tx|ty|tz|rx|ry|rz)(\d*)")


def parse_mapping(expr: str, inputs: tuple[str, ...]) -> list[tuple[float, str, int]]:
    """``"button7-button6"`` -> ``[(1, "button", 7), (-1, "button", 6)]``; ValueError if bad."""
    out: list[tuple[float, str, int]] = []
    pos = 0
    text = expr.replace(" ", "")
    while pos < len(text):
        m = _TERM.match(text, pos)
        if m is None or m.end() == pos:
            raise ValueError(f"cannot read {expr!r} at {text[pos:]!r}")
        sign, name, index = m.groups()
        if name not in inputs:
            raise ValueError(f"{expr!r}: {name!r} is not one of {', '.join(inputs)}")
        if (name in ("axis", "button")) != bool(index):
            raise ValueError(f"{expr!r}: axis and button need an index, {name} takes none")
        out.append((-1.0 if sign == "-" else 1.0, name, int(index) if index else 0))
        pos = m.end()
    return out


def _check_shaping(dead_zone: float, curve: float, what: str) -> None:
    if not 0 <= dead_zone < 1:
        raise ValueError(f"{what} dead_zone must be in [0, 1), not {dead_zone}")
    if not (math.isfinite(curve) and 1 <= curve <= 5):
        raise ValueError(f"{what} curve_exponent must be in [1, 5], not {curve}")


def _check_mapping(mapping: tuple[str, ...], inputs: tuple[str, ...], what: str) -> None:
    if len(mapping) != 6:
        raise ValueError(f"{what} mapping must have 6 entries ({' '.join(TWIST)})")
    for expr in mapping:
        parse_mapping(expr, inputs)


@dataclass
class GamepadConfig:
    dead_zone: float = param(0.12, "stick travel ignored around centre (worn sticks drift)")
    curve_exponent: float = param(
        2.0, "response curve: output = input^n past the dead zone; fine control near centre"
    )
    enable_button: int = param(
        5, "hold-to-move: the arm moves only while this button is held (5: right bumper)"
    )
    mapping: tuple[str, ...] = param(
        ("-axis1", "-axis0", "button7-button6", "", "", "-axis2"),
        "vx vy vz wx wy wz from the standard mapping: left stick x/y, triggers z, right stick x "
        "turns the wrist",
    )
    stop_button: int = param(
        1,
        "pressing it is STOP ARM: latched on the robot until a resume (1: B / circle); -1: none",
    )
    assist_button: int = param(
        0,
        "hold it for the assist (arm_assist): the robot aligns its grasp to what it feels "
        "(0: A / cross); -1: none",
    )

    def __post_init__(self) -> None:
        _check_shaping(self.dead_zone, self.curve_exponent, "gamepad")
        if not 0 <= self.enable_button < 32:
            raise ValueError(f"gamepad enable_button must be 0..31, not {self.enable_button}")
        _check_mapping(self.mapping, ("axis", "button"), "gamepad")
        if not -1 <= self.stop_button < 32:
            raise ValueError(f"gamepad stop_button must be 0..31 or -1, not {self.stop_button}")
        used = {
            index
            for expr in self.mapping
            for _, name, index in parse_mapping(expr, ("axis", "button"))
            if name == "button"
        }
        if self.stop_button in used | {self.enable_button}:
            raise ValueError(
                f"gamepad stop_button {self.stop_button} is already the enable button or in "
                "the mapping: a stop must do nothing else"
            )
        if not -1 <= self.assist_button < 32:
            raise ValueError(f"gamepad assist_button must be 0..31 or -1, not {self.assist_button}")
        if self.assist_button >= 0 and self.assist_button in used | {
            self.enable_button,
            self.stop_button,
        }:
            raise ValueError(
                f"gamepad assist_button {self.assist_button} is already the enable or stop "
                "button or in the mapping: holding the assist must do nothing else"
            )


@dataclass
class SpaceMouseConfig:
    dead_zone: float = param(0.08, "cap travel ignored around rest (the cap never rests at 0)")
    curve_exponent: float = param(1.5, "response curve past the dead zone")
    full_scale: float = param(350.0, "raw HID count at full deflection (SpaceMouse: about 350)")
    enable_button: int = param(
        0, "hold-to-move: the arm moves only while this button is held (0: left button)"
    )
    mapping: tuple[str, ...] = param(
        ("-ty", "-tx", "-tz", "", "", "-rz"),
        "vx vy vz wx wy wz from the cap: push away moves +x, left +y, lift +z, twist turns "
        "the wrist",
    )

    def __post_init__(self) -> None:
        _check_shaping(self.dead_zone, self.curve_exponent, "spacemouse")
        if not self.full_scale > 0:
            raise ValueError("spacemouse full_scale must be positive")
        if not 0 <= self.enable_button < 32:
            raise ValueError(f"spacemouse enable_button must be 0..31, not {self.enable_button}")
        _check_mapping(self.mapping, ("tx", "ty", "tz", "rx", "ry", "rz"), "spacemouse")


@dataclass
class JogConfig:
    max_linear_speed_m_s: float = param(
        0.10, "TCP speed at full deflection and scale 100%; the robot clips to its own cap too"
    )
    max_angular_speed_rad_s: float = param(0.5, "wrist rotation speed at full deflection")
    default_speed_scale: float = param(0.3, "the speed slider's starting position (0..1)")
    send_rate_hz: float = param(
        30.0, "jog commands per second while moving; the robot's deadman needs one every 250 ms"
    )
    keyboard: dict[str, str] = param(
        {
            "w": "+vx",
            "s": "-vx",
            "a": "+vy",
            "d": "-vy",
            "r": "+vz",
            "f": "-vz",
            "q": "+wz",
            "e": "-wz",
        },
        "held key -> twist component at full speed (hold-to-move: releasing stops)",
    )
    assist_key: str = param(
        "g",
        "held key for the assist (arm_assist): the robot aligns its grasp to what it feels "
        "(hold-to-assist: releasing stops it)",
    )
    gamepad: GamepadConfig = param(GamepadConfig(), "browser Gamepad API, standard mapping")
    spacemouse: SpaceMouseConfig = param(SpaceMouseConfig(), "3Dconnexion SpaceMouse via WebHID")

    def __post_init__(self) -> None:
        for name in ("max_linear_speed_m_s", "max_angular_speed_rad_s", "send_rate_hz"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"jog {name} must be positive, not {value}")
        if not 4 <= self.send_rate_hz <= 60:
            raise ValueError("jog send_rate_hz must be 4..60 (the deadman needs >= 4 per second)")
        if not 0 < self.default_speed_scale <= 1:
            raise ValueError("jog default_speed_scale must be in (0, 1]")
        if len(self.assist_key) != 1 or self.assist_key in self.keyboard:
            raise ValueError(
                f"jog assist_key {self.assist_key!r} must be one key that moves nothing else"
            )
        for key, target in self.keyboard.items():
            if len(target) < 3 or target[0] not in "+-" or target[1:] not in TWIST:
                raise ValueError(f"keyboard {key!r}: {target!r} must be +/- and one of {TWIST}")
