"""The router's access control, made from the roster: deny by default, exact keys per role.

Each roster member is a subject of its own, known by its certificate's common
name (its roster name) and nothing else. What each may do, in Zenoh's terms
(a publisher needs ``put`` in and learns who listens through
``declare_subscriber`` out; a subscriber needs ``declare_subscriber`` in and
``put`` out):

- a robot puts only under its own names (stimulus, frame, heartbeat, video)
  and reads only its own inbox (``dxp/NAME/op/*/*``);
- a controller puts commands, stops and heartbeats to every robot under its
  own name, video offers if it may watch, and reads every robot's stimuli,
  frames and heartbeats (and video answers if it may watch);
- an observer puts only stops and heartbeats (and video offers if its entry
  says ``video = true``), and reads as a controller does;
- a recorder puts nothing and reads stimuli, frames and heartbeats.

Every key in a rule is exact (robots and operators enumerated from the roster)
except a robot's inbox, which is that robot's alone. A wildcard subscription
that a rule does not cover is refused. The robot still verifies every
command's signature against its own copy of the roster: the router is a
second wall, not the only one.

Size and rate: every put is refused above the codec's limit
(``low_pass_filter``), and each peer's puts on each key pass at most
``RateLimits`` times a second (``downsampling``: a minimum interval per peer
and key, not a bucket, so the limits stand two to three times above what an
honest node sends).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from common.config.typed import param
from common.fabric import keyexprs
from common.keys.roster import OperatorEntry, Roster
from common.wire.codec import MAX_MESSAGE_BYTES

ROBOT_PUTS = ("stimulus", "frame", "heartbeat", "video")
READS = ("stimulus", "frame", "heartbeat")


@dataclass
class RateLimits:
    """Per peer and key, at most this many messages a second pass the router.

    Zenoh's gate (``downsampling``) is a minimum interval, not a bucket: a
    message within 1/hz of the last one passed is dropped. So it gates only
    what may be dropped, the latest values and the stops (resent until
    latched); commands and video signals, which must each arrive and are sent
    two in one instant (a jog and a gripper command, a bye and an offer), are
    not gated here: the robot queues each sender apart and refuses beyond its
    own budgets, with a reason."""

    stimulus_hz: float = param(
        360.0, "a robot's stimuli (60/s by default, 120 at most, plus keyframes)"
    )
    frame_hz: float = param(60.0, "a robot's raw frames for heatmaps (15/s by default)")
    robot_heartbeat_hz: float = param(
        200.0, "a robot's heartbeats (20/s, plus one when its state changes)"
    )
    stop_hz: float = param(
        100.0, "an operator's stops to one robot (resent every 50 ms; the first copy passes)"
    )
    operator_heartbeat_hz: float = param(
        100.0, "an operator's heartbeats to one robot (20/s, plus answers)"
    )


def _robot_names(roster: Roster) -> list[str]:
    names: list[str] = []
    for robot in roster.robots:
        names.extend(n.decode() for n in sorted(robot.wire_names()))
    return names


def _operator_puts(op: OperatorEntry) -> tuple[str, ...]:
    kinds: list[str] = []
    if op.role == "controller":
        kinds += ["command", keyexprs.STOP, keyexprs.STOP_COPY, "heartbeat"]
    elif op.role == "observer":
        kinds += [keyexprs.STOP, keyexprs.STOP_COPY, "heartbeat"]
    if op.may_watch:
        kinds.append("video")
    return tuple(kinds)


def _operator_reads(op: OperatorEntry) -> tuple[str, ...]:
    return READS + (("video",) if op.may_watch else ())


def _rule(rule_id: str, messages: list[str], flow: str, keys: list[str]) -> dict[str, Any]:
    return {
        "id": rule_id,
        "messages": messages,
        "flows": [flow],
        "permission": "allow",
        "key_exprs": sorted(set(keys)),
    }


def access_control(roster: Roster) -> dict[str, Any]:
    """Zenoh's ``access_control`` section for ``roster``."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    robots = _robot_names(roster)

    def member(name: str, puts: list[str], reads: list[str], listeners: list[str]) -> None:
        sid = f"member:{name}"
        subjects.append({"id": sid, "cert_common_names": [name]})
        ids = []
        if puts:
            rules.append(_rule(f"{sid}:put", ["put"], "ingress", puts))
            # who listens to what we put: without it a publisher thinks nobody does and
            # drops at the source (a robot's inbox subscription covers every operator)
            rules.append(_rule(f"{sid}:listeners", ["declare_subscriber"], "egress", listeners))
            ids += [f"{sid}:put", f"{sid}:listeners"]
        if reads:
            rules.append(_rule(f"{sid}:subscribe", ["declare_subscriber"], "ingress", reads))
            rules.append(_rule(f"{sid}:read", ["put"], "egress", reads))
            ids += [f"{sid}:subscribe", f"{sid}:read"]
        if ids:
            policies.append({"id": f"{sid}:policy", "rules": ids, "subjects": [sid]})

    for robot in roster.robots:
        names = sorted(n.decode() for n in robot.wire_names())
        puts = [keyexprs.robot_key(n, kind) for n in names for kind in ROBOT_PUTS]
        reads = [keyexprs.robot_inbox(n) for n in names]
        member(robot.name, puts, reads, puts)
    for op in roster.operators:
        keyexprs.check_operator_name(op.name)
        puts = [keyexprs.operator_key(r, op.name, k) for r in robots for k in _operator_puts(op)]
        reads = [keyexprs.robot_key(r, k) for r in robots for k in _operator_reads(op)]
        inboxes = [keyexprs.robot_inbox_for(r, k) for r in robots for k in _operator_puts(op)]
        member(op.name, puts, reads, puts + inboxes)
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def size_filter() -> list[dict[str, Any]]:
    """Zenoh's ``low_pass_filter``: no put over the codec's limit crosses the router."""
    return [
        {
            "id": "codec-limit",
            "flows": ["ingress", "egress"],
            "messages": ["put", "delete", "query", "reply"],
            "key_exprs": ["**"],
            "size_limit": MAX_MESSAGE_BYTES,
        }
    ]


def rate_gates(limits: RateLimits, roster: Roster) -> list[dict[str, Any]]:
    """Zenoh's ``downsampling``: each peer's puts on each kind of key, at most so often.

    One rule per robot and kind: the gate keeps one time per peer and rule, so
    an operator's jogs to two robots at once must not share one.
    """
    per_kind = {
        "stimulus": limits.stimulus_hz,
        "frame": limits.frame_hz,
        "heartbeat": limits.robot_heartbeat_hz,
    }
    per_operator_kind = {
        keyexprs.STOP: limits.stop_hz,
        keyexprs.STOP_COPY: limits.stop_hz,
        "heartbeat": limits.operator_heartbeat_hz,
    }
    rules = []
    for robot in _robot_names(roster):
        for kind, hz in per_kind.items():
            rules.append({"key_expr": keyexprs.robot_key(robot, kind), "freq": hz})
        for kind, hz in per_operator_kind.items():
            key = f"{keyexprs.ROOT}/{robot}/op/*/{kind}"
            rules.append({"key_expr": key, "freq": hz})
    if not rules:
        return []
    return [{"id": "per-peer-rates", "flows": ["ingress"], "messages": ["put"], "rules": rules}]
