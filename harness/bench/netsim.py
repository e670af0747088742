"""Bench section: the link simulator measured from outside, against its scenarios.

Runs ``harness.bench.netsim_fidelity`` (a PUB at 100 Hz to a SUB directly and to
another through ``deepxpalm netsim`` in byte-stream mode, on loopback) for
the transparent case and the delayed scenarios (and metro in message mode),
and renders the table that docs/benchmarks.md and docs/netsim.md both carry; then the datagram mode
(the video's path): UDP datagrams at 200 Hz, directly and through a
``DatagramForwarder``, each timed by the receiver's kernel stamp. Every row
gets a verdict. The section also runs on its own and rewrites the block in
docs/netsim.md:

    python -m harness.bench.netsim --seconds 20 --update docs/netsim.md

As a bench section: the link simulator measured from outside, against its scenarios.
"""

from __future__ import annotations

import argparse
import os
import re
import socket
import statistics
import struct
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from harness.bench.doc_block import replace_block
from harness.bench.fmt import results_of
from harness.bench.section import Context, Results, Section, Verdict

SCENARIOS = ("none", "lan", "metro", "intercontinental", "loopback_trace")  # as the full preset
#: Run again in message mode (ZeroMQ PUB/SUB through the simulator, as without CURVE).
MESSAGE_SCENARIOS = ("metro",)
#: The datagram rows: a fixed delay (judged against the direct path too) and two shipped ones.
DATAGRAM_SCENARIOS = ("fixed_20ms", "metro", "loopback_trace")
#: A datagram path's p50 may exceed configured + direct by at most this, ms (a quiet machine).
DATAGRAM_P50_MS = 1.5
#: ... and fall under it by at most this: the median of a few thousand draws of the
#: scenario's distribution, not the distribution's own.
DATAGRAM_SAMPLING_MS = 0.3
DATAGRAM_RATE_HZ = 200.0
BEGIN, END = "<!-- netsim-fidelity:begin -->", "<!-- netsim-fidelity:end -->"


def fidelity(
    seconds: float,
    scenarios: tuple[str, ...] = SCENARIOS,
    message_scenarios: tuple[str, ...] = MESSAGE_SCENARIOS,
    datagram_scenarios: tuple[str, ...] = DATAGRAM_SCENARIOS,
) -> dict[str, Any]:
    """One rig run per scenario; the simulator gets every core the bench had before pinning."""
    from harness.bench.netsim_fidelity import measure as run_rig

    try:
        from harness.bench.timing import original_affinity

        cpus: set[int] | None = original_affinity()
    except (ImportError, OSError):
        cpus = None
    runs = [run_rig(name, seconds=seconds, netsim_cpus=cpus).as_dict() for name in scenarios]
    runs += [
        run_rig(name, seconds=seconds, netsim_cpus=cpus, mode="message").as_dict()
        for name in message_scenarios
    ]
    datagrams = [datagram_run(name, seconds) for name in datagram_scenarios]
    load = os.getloadavg()
    return {
        "seconds_per_scenario": seconds,  # the runner writes the section's total as "seconds"
        "date": time.strftime("%Y-%m-%d"),
        "runs": runs,
        "datagram_runs": datagrams,
        "loadavg_after": [round(x, 2) for x in load],
    }


def _datagram_scenario(name: str) -> Any:
    from common.netsim.scenario import load_scenario, scenario_from_dict

    if name == "fixed_20ms":
        return scenario_from_dict({"name": name, "both": {"delay_ms": 20.0}})
    return load_scenario(name)


def _send_and_time(to: tuple[str, int], rx: socket.socket, seconds: float) -> list[float]:
    """Datagrams stamped with their send time at ``DATAGRAM_RATE_HZ``; one-way ms of each."""
    from common.netsim.kernel_stamps import ANC_BYTES, arrival_ns, real_minus_mono_ns

    stamp = struct.Struct("!q")
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    offset = real_minus_mono_ns()
    got: list[float] = []

    def drain() -> None:
        while True:
            try:
                data, anc, _, _ = rx.recvmsg(256, ANC_BYTES)
            except BlockingIOError:
                return
            at = arrival_ns(anc, time.monotonic_ns(), offset)
            got.append((at - stamp.unpack_from(data)[0]) / 1e6)

    n, period = round(seconds * DATAGRAM_RATE_HZ), 1.0 / DATAGRAM_RATE_HZ
    t0 = time.monotonic()
    for i in range(n):
        while time.monotonic() < t0 + i * period:
            drain()
            time.sleep(period / 8)
        tx.sendto(stamp.pack(time.monotonic_ns()) + b"x" * 56, to)
    t_end = time.monotonic() + 0.5
    while time.monotonic() < t_end:
        drain()
        time.sleep(0.001)
    tx.close()
    return got


def datagram_run(name: str, seconds: float) -> dict[str, Any]:
    """The datagram relay (in this process) against a direct UDP hop, one scenario."""
    from common.netsim.datagram import DatagramForwarder
    from common.netsim.kernel_stamps import SO_TIMESTAMPNS

    scenario = _datagram_scenario(name)
    config = scenario.to_robot
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    rx.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    rx.setblocking(False)
    try:
        direct = _send_and_time(rx.getsockname(), rx, seconds)
        with DatagramForwarder(scenario, target=rx.getsockname(), seed=1) as relay:
            via = _send_and_time(relay.address, rx, seconds)
    finally:
        rx.close()
    sent = round(seconds * DATAGRAM_RATE_HZ)
    floor, configured = config.delay_quantile_ms(0.0), config.delay_quantile_ms(0.5)
    direct_p50 = statistics.median(direct) if direct else float("nan")
    via_p50 = statistics.median(via) if via else float("nan")
    extra = via_p50 - configured - direct_p50
    return {
        "scenario": name,
        "sent": sent,
        "received": len(via),
        "direct_p50_ms": round(direct_p50, 3),
        "configured_p50_ms": round(configured, 3),
        "floor_ms": round(floor, 3),
        "via_min_ms": round(min(via), 3) if via else None,
        "via_p50_ms": round(via_p50, 3),
        "extra_p50_ms": round(extra, 3),
        "early": sum(1 for d in via if d < floor),
        "ok": bool(via)
        and len(via) >= 0.99 * sent * (1 - config.loss_rate())
        and -DATAGRAM_SAMPLING_MS < extra < DATAGRAM_P50_MS
        and not any(d < floor for d in via),
    }


def _ms(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def _us(x: float | None) -> str:
    return "n/a" if x is None else str(round(x))


def verdicts(results: Results) -> list[Verdict]:
    """One per row: the stream and message modes' criteria, then the datagram mode's."""
    s = results_of(results, "netsim")
    if s is None:
        return []
    out = []
    for r in s["runs"]:
        v = r["via_ms"]
        failed = [k for k, ok in r["verdicts"].items() if not ok]
        if all(x == 0 for x in r["configured_ms"].values()):
            what = "p50 within 0.15 ms and p99 within 0.5 ms of a direct link"
        else:
            what = "p5/p50/p95 within 0.5 ms or 5 % of configured + direct"
        out.append(
            Verdict(
                f"netsim {r.get('mode', 'stream')}, {r['scenario']}: {what}",
                f"p50 {v['p50']:.2f} ms" + (f" (failed: {', '.join(failed)})" if failed else ""),
                bool(r["ok"]),
            )
        )
    for r in s.get("datagram_runs", []):
        out.append(
            Verdict(
                f"netsim datagrams, {r['scenario']}: none early, p50 within "
                f"{DATAGRAM_P50_MS:g} ms of configured + direct",
                f"{r['early']} early, p50 {r['extra_p50_ms']:+.2f} ms",
                bool(r["ok"]),
            )
        )
    return out


def datagram_table(section: dict[str, Any] | None) -> list[str]:
    """The datagram rows (empty when the section did not measure them)."""
    rows = (section or {}).get("datagram_runs")
    if not rows:
        return []
    out = [
        "",
        "The datagram mode (the video's path): UDP datagrams of 64 bytes at "
        f"{DATAGRAM_RATE_HZ:g} Hz for {section['seconds_per_scenario']:g} s, straight to a "
        "receiver and then through a `DatagramForwarder` in the bench's process, each timed "
        "from just before its send to the receiver's kernel receive stamp. Criteria: none "
        "under the scenario's floor (no datagram leaves early), the p50 within "
        f"{DATAGRAM_P50_MS:g} ms above configured + direct (and at most "
        f"{DATAGRAM_SAMPLING_MS:g} ms under it: the draws' own median), nothing lost but "
        "what the scenario loses.",
        "",
        "| scenario | received / sent | direct p50 | floor / configured p50 | through min / p50 "
        "| p50 beyond configured + direct | early | criteria met |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r['scenario']} | {r['received']} / {r['sent']} | {_ms(r['direct_p50_ms'])} | "
            f"{_ms(r['floor_ms'])} / {_ms(r['configured_p50_ms'])} | {_ms(r['via_min_ms'])} / "
            f"{_ms(r['via_p50_ms'])} | {r['extra_p50_ms']:+.2f} | {r['early']} | "
            f"{'yes' if r['ok'] else 'no'} |"
        )
    return out


def fidelity_table(section: dict[str, Any] | None) -> list[str]:
    """The fidelity table (empty when the section was skipped or failed)."""
    if not section or "runs" not in section:
        return []
    out = [
        "## Link simulator fidelity (over real sockets)",
        "",
        "A PUB sends 100 messages a second carrying their send time, for "
        f"{section['seconds_per_scenario']:g} s, to a SUB directly and to another through "
        "`deepxpalm netsim` (its own process, stream mode unless the row says message "
        "mode) on loopback; the two paths "
        "alternate half a period apart. One-way delays in ms, to the operator. "
        "Target: configured + direct. "
        "Criteria: at zero delay, p50 within 0.15 ms and p99 within 0.5 ms of the direct "
        "link; with a delay, p5/p50/p95 within 0.5 ms or 5 % of the target. Load average "
        f"after: {', '.join(str(x) for x in section['loadavg_after'])} (2 shared cores).",
        "",
        "| scenario | direct p5 / p50 / p95 / p99 | configured p5 / p50 / p95 | "
        "through netsim p5 / p50 / p95 / p99 | netsim's own p50 / p99 (us) | criteria met |",
        "|---|---|---|---|---|---|",
    ]
    for r in section["runs"]:
        d, v, c = r["direct_ms"], r["via_ms"], r["configured_ms"]
        own = r.get("netsim_own_latency_us") or {}
        failed = [k for k, ok in r["verdicts"].items() if not ok]
        mode = r.get("mode", "stream")
        label = r["scenario"] if mode == "stream" else f"{r['scenario']} ({mode} mode)"
        out.append(
            f"| {label} | {_ms(d['p5'])} / {_ms(d['p50'])} / {_ms(d['p95'])} / "
            f"{_ms(d['p99'])} | {_ms(c['p5'])} / {_ms(c['p50'])} / {_ms(c['p95'])} | "
            f"{_ms(v['p5'])} / {_ms(v['p50'])} / {_ms(v['p95'])} / {_ms(v['p99'])} | "
            f"{_us(own.get('p50'))} / {_us(own.get('p99'))} | "
            f"{'yes' if r['ok'] else 'no (' + ', '.join(failed) + ')'} |"
        )
    out += [
        "",
        "netsim's own time runs from the kernel's receive timestamp of a chunk to its send "
        "returning, minus the scheduled delay: what the forwarder adds beyond the scenario. "
        "`lan` (0.1 ms) and `loopback_trace` (0.07 ms median) are below what an extra "
        "loopback hop costs here, so they come out at about the `none` row.",
        *datagram_table(section),
        "",
    ]
    return out


def update_doc(path: Path, section: dict[str, Any]) -> None:
    """Replace the block between the markers in ``path`` with this run's table."""
    text = path.read_text()
    # the date the table was measured: a docs refresh from stored results keeps it
    # (results from before the section stored its date keep the one the page has)
    kept = re.search(re.escape(BEGIN) + r"\s*Measured (\d{4}-\d{2}-\d{2})", text)
    date = section.get("date") or (kept.group(1) if kept else "an unknown date")
    lines = [
        f"Measured {date}; regenerate with "
        "`deepxpalm bench --only netsim --update-docs` or "
        "`python -m harness.bench.netsim --update docs/netsim.md`.",
        "",
        *fidelity_table(section)[2:],
    ]
    replace_block(path, BEGIN, END, lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="the link simulator's fidelity table")
    parser.add_argument("--seconds", type=float, default=20.0, help="per scenario")
    parser.add_argument("--update", type=Path, help="rewrite the block in this markdown file")
    args = parser.parse_args(argv)
    section = fidelity(args.seconds)
    if args.update:
        update_doc(args.update, section)
    print("\n".join(fidelity_table(section)))
    return 0


@dataclass(frozen=True)
class NetsimSizes:
    netsim_seconds: float  # per scenario, 100 messages a second
    netsim_scenarios: tuple[str, ...]
    netsim_message_scenarios: tuple[str, ...] = MESSAGE_SCENARIOS
    netsim_datagram_scenarios: tuple[str, ...] = DATAGRAM_SCENARIOS


SIZES = {
    "full": NetsimSizes(netsim_seconds=20.0, netsim_scenarios=SCENARIOS),
    "quick": NetsimSizes(netsim_seconds=5.0, netsim_scenarios=SCENARIOS),
    "smallest": NetsimSizes(
        netsim_seconds=1.0,
        netsim_scenarios=("none",),
        netsim_message_scenarios=(),
        netsim_datagram_scenarios=("fixed_20ms",),
    ),
}


def measure(ctx: Context, sizes: NetsimSizes) -> dict[str, Any]:
    return fidelity(
        sizes.netsim_seconds,
        sizes.netsim_scenarios,
        sizes.netsim_message_scenarios,
        sizes.netsim_datagram_scenarios,
    )


def markdown(results: Results) -> list[str]:
    """The fidelity table docs/netsim.md carries too; nothing when the section did not run."""
    lines = fidelity_table(results_of(results, "netsim"))
    return ["", *lines] if lines else []


def update_netsim_doc(section: dict[str, Any], out_dir: Path) -> list[Path]:
    """docs/netsim.md carries the same table between its markers, when the folder has it."""
    page = out_dir / "netsim.md"
    if not page.exists():
        return []
    update_doc(page, section)
    return [page]


SECTION = Section(
    name="netsim",
    title="Link simulator fidelity",
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
    update_other_docs=update_netsim_doc,
    quick=False,
)


if __name__ == "__main__":
    sys.exit(main())
