"""The router's access control, made from the roster: what each role may put and read."""

from __future__ import annotations

from common.keys.roster import parse_roster
from common.wire.codec import MAX_MESSAGE_BYTES
from router_side.acl import RateLimits, access_control, rate_gates, size_filter

KEY = "a" * 40
ROSTER = f"""
[[operator]]
name = "alice"
role = "controller"
[[operator]]
name = "olga"
role = "observer"
[[operator]]
name = "vera"
role = "observer"
video = true
[[operator]]
name = "rec"
role = "recorder"
[[robot]]
name = "cell1"
curve_key = "{KEY}"
names = ["cell1", "cell1-cam"]
[[robot]]
name = "cell2"
curve_key = "{"b" * 40}"
"""


def _grants(acl: dict, member: str) -> dict[tuple[str, str], set[str]]:
    """(message, flow) -> key expressions ``member`` is allowed."""
    rules = {r["id"]: r for r in acl["rules"]}
    subject = next(s["id"] for s in acl["subjects"] if s["cert_common_names"] == [member])
    out: dict[tuple[str, str], set[str]] = {}
    for policy in acl["policies"]:
        if subject in policy["subjects"]:
            for rid in policy["rules"]:
                rule = rules[rid]
                assert rule["permission"] == "allow"
                for message in rule["messages"]:
                    for flow in rule["flows"]:
                        out.setdefault((message, flow), set()).update(rule["key_exprs"])
    return out


def _acl() -> dict:
    return access_control(parse_roster(ROSTER, "roster.toml"))


def test_deny_by_default_and_every_subject_is_a_certificate_name():
    acl = _acl()
    assert acl["enabled"] and acl["default_permission"] == "deny"
    names = [s["cert_common_names"] for s in acl["subjects"]]
    assert sorted(n for (n,) in names) == ["alice", "cell1", "cell2", "olga", "rec", "vera"]
    assert all(set(s) == {"id", "cert_common_names"} for s in acl["subjects"])


def test_a_robot_puts_under_its_own_names_and_reads_only_its_inbox():
    g = _grants(_acl(), "cell1")
    puts = g[("put", "ingress")]
    assert "dxp/cell1/stimulus" in puts and "dxp/cell1-cam/heartbeat" in puts
    assert not any(k.startswith("dxp/cell2/") for k in puts)
    assert g[("declare_subscriber", "ingress")] == {"dxp/cell1/op/*/*", "dxp/cell1-cam/op/*/*"}
    assert g[("put", "egress")] == {"dxp/cell1/op/*/*", "dxp/cell1-cam/op/*/*"}


def test_each_operator_role_puts_only_what_it_may_under_its_own_name():
    acl = _acl()
    alice = _grants(acl, "alice")[("put", "ingress")]
    assert {k.rsplit("/", 1)[1] for k in alice} == {
        "command",
        "stop",
        "stop_copy",
        "heartbeat",
        "video",
    }
    assert all("/op/alice/" in k for k in alice)
    olga = _grants(acl, "olga")[("put", "ingress")]
    assert {k.rsplit("/", 1)[1] for k in olga} == {"stop", "stop_copy", "heartbeat"}
    vera = _grants(acl, "vera")[("put", "ingress")]
    assert {k.rsplit("/", 1)[1] for k in vera} == {"stop", "stop_copy", "heartbeat", "video"}
    assert ("put", "ingress") not in _grants(acl, "rec")


def test_reads_are_exact_keys_and_never_another_operators_commands():
    acl = _acl()
    for member in ("alice", "olga", "vera", "rec"):
        reads = _grants(acl, member)[("declare_subscriber", "ingress")]
        assert all("*" not in k and "/op/" not in k for k in reads), member
    assert "dxp/cell2/video" not in _grants(acl, "olga")[("put", "egress")]
    assert "dxp/cell2/video" in _grants(acl, "vera")[("put", "egress")]
    assert {k.rsplit("/", 1)[1] for k in _grants(acl, "rec")[("put", "egress")]} == {
        "stimulus",
        "frame",
        "heartbeat",
    }


def test_limits_match_the_codec_and_gate_each_robot_apart():
    (size,) = size_filter()
    assert size["size_limit"] == MAX_MESSAGE_BYTES and size["key_exprs"] == ["**"]
    roster = parse_roster(ROSTER, "roster.toml")
    (gates,) = rate_gates(RateLimits(), roster)
    keys = [r["key_expr"] for r in gates["rules"]]
    assert "dxp/cell1/op/*/stop" in keys and "dxp/cell2/op/*/stop" in keys
    assert "dxp/cell1/op/*/stop_copy" in keys and "dxp/cell2/op/*/stop_copy" in keys
    # what must each arrive is never dropped by a spacing gate
    assert not any(k.endswith(("/command", "/video")) for k in keys)
    assert len(keys) == len(set(keys))
    assert gates["flows"] == ["ingress"]
