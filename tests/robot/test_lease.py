"""The control lease's rules (robot_side/node/commands/lease.py): request, grant, release,
timeout, expiry."""

from __future__ import annotations

from common.keys.roster import OperatorEntry
from common.wire.messages import Command
from robot_side.node.commands import lease as L
from robot_side.node.commands.lease import ControlLease

MS = 1_000_000
A, B, OBS = b"a" * 32, b"b" * 32, b"o" * 32


def _lease() -> ControlLease:
    ops = {
        A: OperatorEntry("a", "controller", None, A),
        B: OperatorEntry("b", "controller", None, B),
        OBS: OperatorEntry("obs", "observer", None, OBS),
    }
    return ControlLease(ops, 250 * MS, 2000 * MS)


def _cmd(action: str, grantee: bytes | None = None) -> Command:
    return Command(seq=1, t_send_ns=1, action=action, grantee=grantee)


def test_the_first_controller_to_ask_gets_it_an_observer_never():
    lease = _lease()
    assert lease.peer(b"x" * 32) is None  # not in the roster
    for key in (A, B, OBS):
        lease.peer(key)
    assert lease.handle(OBS, _cmd("lease_request"), 0) == L.REFUSED_ROLE
    assert lease.handle(A, _cmd("lease_request"), 0) == L.GRANTED and lease.holder == A
    assert lease.handle(A, _cmd("lease_request"), 0) == L.HELD


def _heard(lease: ControlLease, key: bytes, t_ns: int) -> None:
    lease.peer(key).gate.heard(t_ns, t_ns, t_ns)


def test_a_held_lease_moves_only_when_its_holder_grants_or_releases_it():
    lease = _lease()
    for key in (A, B, OBS):
        _heard(lease, key, 0)
    lease.handle(A, _cmd("lease_request"), 0)
    assert lease.handle(B, _cmd("lease_request"), 0) == L.PENDING and lease.holder == A
    assert lease.handle(B, _cmd("lease_grant", B), 0) == L.REFUSED_NOT_HOLDER
    assert lease.handle(A, _cmd("lease_grant", OBS), 0) == L.REFUSED_GRANTEE
    assert lease.handle(A, _cmd("lease_grant"), 0) == L.HANDED_OVER and lease.holder == B
    assert lease.pending is None
    assert lease.handle(A, _cmd("lease_request"), 0) == L.PENDING
    assert lease.handle(B, _cmd("lease_release"), 0) == L.HANDED_OVER and lease.holder == A
    assert lease.handle(A, _cmd("lease_release"), 0) == L.RELEASED and lease.holder is None


def test_an_unanswered_request_lapses():
    lease = _lease()
    for key in (A, B):
        lease.peer(key)
    lease.handle(A, _cmd("lease_request"), 0)
    lease.handle(B, _cmd("lease_request"), 0)
    assert lease.tick(1999 * MS) is None and lease.pending == B
    assert lease.tick(2000 * MS) == L.TIMED_OUT and lease.pending is None and lease.holder == A


def test_a_silent_holder_loses_it_to_a_fresh_waiting_requester_only():
    lease = _lease()
    for key in (A, B):
        lease.peer(key)
    lease.handle(A, _cmd("lease_request"), 0)
    lease.handle(B, _cmd("lease_request"), 0)
    lease.peers[B].gate.heard(900 * MS, 900 * MS, 900 * MS)
    lease.expire(1000 * MS)
    assert lease.holder == B
    lease.handle(A, _cmd("lease_request"), 1000 * MS)  # a asks again, but is silent after
    lease.expire(1500 * MS)
    assert lease.holder is None  # a's newest word is too old to hand it the arm


def test_a_grant_to_a_key_not_heard_lately_is_refused_and_the_holder_keeps_it():
    lease = _lease()
    _heard(lease, A, 0)
    _heard(lease, B, 0)
    lease.handle(A, _cmd("lease_request"), 0)
    now = 1000 * MS  # b last heard a second ago: beyond max_age (250 ms)
    _heard(lease, A, now)
    assert lease.handle(A, _cmd("lease_grant", B), now) == L.REFUSED_SILENT
    assert lease.holder == A
    _heard(lease, B, now)
    assert lease.handle(A, _cmd("lease_grant", B), now) == L.HANDED_OVER and lease.holder == B


def test_a_reloaded_roster_takes_the_lease_from_a_holder_demoted_or_removed():
    lease = _lease()
    for key in (A, B):
        _heard(lease, key, 0)
    lease.handle(A, _cmd("lease_request"), 0)
    lease.handle(B, _cmd("lease_request"), 0)  # waiting
    demoted = {**lease.operators, A: OperatorEntry("a", "observer", None, A)}
    changes_before = lease.changes
    assert lease.replace_roster(demoted) == [
        "a (controller) now a (observer)",
        "the lease holder may no longer hold it: nobody holds it now",
    ]
    assert lease.holder is None and lease.changes == changes_before + 1
    assert lease.pending == B, "a waiting controller still waits"
    assert lease.peer(A).entry.role == "observer", "its clock kept, its role new"
    assert lease.handle(A, _cmd("lease_request"), 0) == L.REFUSED_ROLE
    without_b = {k: e for k, e in demoted.items() if k != B}
    assert lease.replace_roster(without_b) == ["b removed"]
    assert lease.pending is None and lease.peer(B) is None
    assert lease.replace_roster(without_b) == [], "the same file again changes nothing"
