"""An old key name still loads, with a warning that names the new one."""

from __future__ import annotations

import logging

import pytest

from common.config.typed import from_dict
from common.errors import ConfigError
from robot_side.tactile.serial_board import SerialTactileConfig


def test_old_baud_key_is_read_as_baudrate_with_a_warning(caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="common.config.typed"):
        config = from_dict(SerialTactileConfig, {"baud": 115200}, where="robot.tactile")
    assert config.baudrate == 115200
    assert "[robot.tactile] baud is deprecated: call it baudrate" in caplog.text


def test_both_names_at_once_is_an_error_that_says_which_to_keep() -> None:
    with pytest.raises(ConfigError, match="keep 'baudrate'"):
        from_dict(SerialTactileConfig, {"baud": 1, "baudrate": 2}, where="robot.tactile")


def test_an_old_name_the_table_does_not_have_stays_unknown() -> None:
    from robot_side.arm.ur_rtde import URArmConfig

    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['baud'\]"):
        from_dict(URArmConfig, {"baud": 1}, where="robot.arm")


def test_the_palm_step_rate_under_its_old_control_name_is_read_with_a_warning(caplog) -> None:
    """``control`` is the lease; the renderer's rate is of palm steps. A config (or a session
    recorded before) naming ``control_rate_hz`` still loads, and is told the new name."""
    from operator_side.palm.renderer_config import RendererConfig

    with caplog.at_level(logging.WARNING):
        config = from_dict(RendererConfig, {"control_rate_hz": 50.0}, where="operator.renderer")
    assert config.palm_step_rate_hz == 50.0
    assert "control_rate_hz is deprecated: call it palm_step_rate_hz" in caplog.text
