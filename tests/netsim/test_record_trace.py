"""``python -m common.netsim.record_trace --loopback``: a trace recorded against a child echo
that binds a port of its own choosing and says which."""

from __future__ import annotations

from common.netsim.record_trace import main


def test_a_loopback_trace_is_recorded_against_the_echo_its_child_bound(tmp_path):
    out = tmp_path / "trace.txt"
    assert main(["--loopback", "--seconds", "0.5", "--rate-hz", "20", "--out", str(out)]) == 0
    rows = [line.split() for line in out.read_text().splitlines() if not line.startswith("#")]
    assert len(rows) >= 5, rows
    assert all(float(delay_ms) >= 0.0 for _, delay_ms in rows)
