"""Section: end to end across two processes over loopback TCP, the machine's floor beside it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from deploy.bench.fmt import num, results_of
from deploy.bench.section import Context, Results, Section, Verdict

#: the issue's target for the two-process chain
MEDIAN_TARGET_US = 1000.0


@dataclass(frozen=True)
class TcpSizes:
    tcp_frames: int
    tcp_rate_hz: float


SIZES = {
    "full": TcpSizes(tcp_frames=3000, tcp_rate_hz=120.0),
    "quick": TcpSizes(tcp_frames=400, tcp_rate_hz=200.0),
    "smallest": TcpSizes(tcp_frames=50, tcp_rate_hz=500.0),
}


def measure(ctx: Context, sizes: TcpSizes) -> dict[str, Any]:
    """Both processes on the bench's core, then the operator on another when there is one."""
    from deploy.bench.e2e_tcp import end_to_end_tcp, loopback_floor
    from deploy.bench.timing import original_affinity

    n, rate, core = sizes.tcp_frames, sizes.tcp_rate_hz, ctx.core
    out = end_to_end_tcp(n, rate, ctx.classifier, core)
    out["floor"] = loopback_floor(n, rate, core)
    others = sorted(original_affinity() - {core})
    if others:  # two machines in the field: the operator on a core of its own
        apart = end_to_end_tcp(n, rate, ctx.classifier, core, peer_cpu=others[0])
        apart["floor"] = loopback_floor(n, rate, core, peer_cpu=others[0])
        out["operator_on_other_core"] = apart
    return out


def verdicts(results: Results) -> list[Verdict]:
    """Judged with a core each (two machines in the field); both on one core given beside it."""
    tcp = results_of(results, "e2e_tcp")
    apart = None if tcp is None else tcp.get("operator_on_other_core")
    judged = apart or tcp
    measured = None
    if judged is not None:
        measured = (
            f"median {num(judged['median_us'])} us, p99 {num(judged['p99_us'])} us "
            + ("(a core each)" if apart else "(one core)")
            + f"; this machine's floor with no work: median "
            f"{num(judged.get('floor', {}).get('median_us'))} us"
        )
        if apart:
            measured += (
                f". Both on one core: median {num(tcp['median_us'])} us, "
                f"p99 {num(tcp['p99_us'])} us"
            )
    return [
        Verdict(
            "end to end, two processes, loopback TCP: median < "
            f"{MEDIAN_TARGET_US / 1000:g} ms (p99 reported)",
            measured,
            None if judged is None else judged["median_us"] < MEDIAN_TARGET_US,
        )
    ]


def markdown(results: Results) -> list[str]:
    """Nothing of its own: its rows are in the end-to-end table (the e2e_inproc section)."""
    return []


SECTION = Section(
    name="e2e_tcp",
    title="End to end: frame bytes to servo packet",
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
)
