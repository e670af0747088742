"""The roster file: names bound to robot keys, and the rule that refuses a lock-out."""

from __future__ import annotations

import pytest

from common.errors import ConfigError
from common.keys.roster import (
    RosterLockoutError,
    check_replacement,
    operator_entry,
    parse_roster,
    robot_entry,
)

KEY1, KEY2 = b"1" * 40, b"2" * 40
ALICE = operator_entry("alice", "controller", b"a" * 40, bytes(32))


def test_a_robot_key_may_use_its_name_and_the_names_it_lists():
    roster = parse_roster(ALICE + robot_entry("cell1", KEY1, ("cell1-cam",)), "r")
    assert roster.robot_names_by_curve_key() == {KEY1: {b"cell1", b"cell1-cam"}}
    plain = parse_roster(robot_entry("cell2", KEY2), "r")
    assert plain.robot_names_by_curve_key() == {KEY2: {b"cell2"}}


@pytest.mark.parametrize(
    "second",
    [
        robot_entry("cell1", KEY2),  # the same name under another key
        robot_entry("cell2", KEY2, ("cell1",)),  # another key claiming it among its names
        robot_entry("cell1", KEY1),  # the same entry twice
    ],
)
def test_a_name_belongs_to_one_key(second):
    with pytest.raises(ConfigError, match="'cell1' is already 'cell1'"):
        parse_roster(robot_entry("cell1", KEY1) + second, "r")


def test_a_reload_that_would_remove_every_robot_or_controller_is_refused_unless_marked():
    old = parse_roster(ALICE + robot_entry("cell1", KEY1), "r")
    for text, lost in [
        ("", "every robot (1) and every controller (alice)"),
        (ALICE, "every robot (1)"),
        (robot_entry("cell1", KEY1), "every controller (alice)"),
    ]:
        with pytest.raises(RosterLockoutError, match=lost.replace("(", r"\(").replace(")", r"\)")):
            check_replacement(old, parse_roster(text, "r"), "r")
        check_replacement(old, parse_roster("allow_lockout = true\n" + text, "r"), "r")
    # fewer robots, another controller: a change, not a lock-out
    smaller = operator_entry("bob", "controller", b"b" * 40, bytes(32)) + robot_entry("c", KEY2)
    check_replacement(old, parse_roster(smaller, "r"), "r")


def test_video_is_a_controllers_unless_the_roster_grants_an_observer_never_a_recorder():
    ops = "".join(
        f'[[operator]]\nname = "{name}"\nrole = "{role}"\n{extra}\n'
        for name, role, extra in (
            ("alice", "controller", ""),
            ("bob", "observer", ""),
            ("carol", "observer", "video = true"),
            ("dave", "controller", "video = false"),
            ("rec", "recorder", ""),
        )
    )
    watch = {op.name: op.may_watch for op in parse_roster(ops, "r.toml").operators}
    assert watch == {"alice": True, "bob": False, "carol": True, "dave": False, "rec": False}
    with pytest.raises(ConfigError, match="a recorder never gets video"):
        parse_roster('[[operator]]\nname = "r"\nrole = "recorder"\nvideo = true\n', "r.toml")
    with pytest.raises(ConfigError, match="video must be true or false"):
        parse_roster('[[operator]]\nname = "b"\nrole = "observer"\nvideo = "yes"\n', "r.toml")
