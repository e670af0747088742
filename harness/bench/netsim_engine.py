"""The link simulator against its configuration, and its own cost on real sockets.

Not a test: the socket numbers depend on the machine and on what else runs
on it. Kept beside ``deepxpalm bench`` rather than in it: its netsim section
measures the stream mode from outside, this the engine itself. Two parts:

1. Virtual time. Every built-in scenario (and a datagram stress config
   with duplication, reordering and corruption) carries 10,000 timestamped
   messages at 120 Hz and at 500 Hz through the impairment engine, the same
   code the proxy runs. Each scenario runs twice: as a datagram path, where
   what arrives is exactly what the path did (this is where measured delay
   and loss are checked against the configured distribution), and with its
   own delivery model (stream: retransmissions and head-of-line blocking
   included, reported, not checked against the path).
2. Real sockets on loopback. The simulator at zero delay against a direct
   PUB/SUB hop (its own cost), and a jittered scenario replayed in virtual
   time with the same seed to measure how late the proxy releases each
   message against the delay the engine chose for it.

    python -m harness.bench.netsim_engine                       # everything, tables to stdout
    python -m harness.bench.netsim_engine --update-docs docs/netsim.md --json runs/netsim.json
    python -m harness.bench.netsim_engine --skip-sockets        # virtual time only (seconds)

Exits 1 if a criterion fails: delay p50/p99 within 0.5 ms or 5%
(whichever is larger) of configured, loss within 1 percentage point, the
simulator's own median cost under 100 us.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import zmq
from scipy.stats import norm

from common.netsim.impairments import DirectionConfig, DirectionImpairment, Scenario
from common.netsim.proxy import Endpoints, LinkSimulator
from common.netsim.scenario import builtin_scenarios, load_scenario
from harness.bench.doc_block import replace_block

MS = 1_000_000
SIZE = 200  # bytes, about a stimulus message
RATES_HZ = (120, 500)
BEGIN, END = "<!-- netsim-bench:begin -->", "<!-- netsim-bench:end -->"

#: Not a shipped scenario: exercises what the TCP-like ones cannot show.
STRESS = DirectionConfig(
    delivery="datagram",
    delay_ms=20.0,
    jitter_ms=0.2,  # small, so reordering is the explicit kind even at 500 Hz
    distribution="normal",
    loss_model="gilbert_elliott",
    ge_p_percent=1.0,
    ge_r_percent=25.0,
    ge_loss_bad_percent=80.0,
    ge_loss_good_percent=0.5,
    duplicate_percent=2.0,
    reorder_percent=5.0,
    corrupt_percent=1.0,
)


# ---------------------------------------------------------------- configured
def configured(cfg: DirectionConfig, rate_hz: float, n: int) -> dict[str, float]:
    """What the config says the path should do, computed from its definition (no engine)."""
    ser_ms = (SIZE + cfg.packet_overhead_bytes) * 8 / cfg.rate_kbit if cfg.rate_kbit else 0.0
    m = 20_000
    grid = (np.arange(m) + 0.5) / m
    q = np.array([cfg.delay_quantile_ms(u) for u in grid]) + ser_ms
    # Deliveries mix the path delay with the reordered ones sent at once
    # (netem: no delay) and duplicates (their own path delay).
    w0 = (cfg.reorder_percent / 100) / (1 + cfg.duplicate_percent / 100)

    def quantile(p: float) -> float:
        if p <= w0:
            return ser_ms
        return cfg.delay_quantile_ms((p - w0) / (1 - w0)) + ser_ms

    # Mean |D(i) - D(i-1)| for the Gaussian copula with the configured
    # correlation: what RFC 3550 jitter converges to without reordering.
    rng = np.random.default_rng(0)
    rho = cfg.delay_correlation
    z1 = rng.standard_normal(200_000)
    z2 = rho * z1 + math.sqrt(1 - rho * rho) * rng.standard_normal(200_000)
    x1, x2 = (np.interp(norm.cdf(z), grid, q) for z in (z1, z2))
    duration_s = n / rate_hz
    out_s = sum(max(0.0, min(t2, duration_s) - t1) for t1, t2 in cfg.outages if t1 < duration_s)
    f_out = out_s / duration_s
    n_outages = sum(1 for t1, _ in cfg.outages if t1 < duration_s)
    p = cfg.loss_rate()
    datagram_loss = f_out + (1 - f_out) * p
    burst = cfg.mean_loss_burst()
    lost_exp = n * (1 - f_out) * p
    bursts_exp = (lost_exp / burst if burst else 0.0) + n_outages
    return {
        "mean_ms": float(w0 * ser_ms + (1 - w0) * q.mean()),
        "p50_ms": quantile(0.5),
        "p99_ms": quantile(0.99),
        # With explicit reordering the arrival order is not the send order.
        "jitter_ms": float(np.mean(np.abs(x1 - x2))) if w0 == 0 else math.nan,
        "loss": datagram_loss if cfg.delivery == "datagram" else 0.0,
        "burst": (lost_exp + n * f_out) / bursts_exp if bursts_exp else 0.0,
        "dup": cfg.duplicate_percent / 100,
        "reorder": cfg.reorder_percent / 100,
        "corrupt": cfg.corrupt_percent / 100,
    }


# ---------------------------------------------------------------- measured
def measure(cfg: DirectionConfig, rate_hz: float, n: int, *, seed: int, name: str) -> dict:
    """Drive the engine with n timestamped messages; statistics as a receiver sees them."""
    engine = DirectionImpairment(cfg, seed=seed, name=name)
    period = round(1e9 / rate_hz)
    arrivals = []  # (due, order, seq, t_send, corrupted)
    k = 0
    t0 = time.perf_counter()
    for seq in range(n):
        t = seq * period
        payload = b"STIM" + seq.to_bytes(8, "little") + bytes(SIZE - 12)
        for due, data in engine.process(t, payload):
            arrivals.append((due, k, seq, t, data != payload))
            k += 1
    cost_us = (time.perf_counter() - t0) / n * 1e6
    arrivals.sort()
    delays = np.array([(due - t) / MS for due, _, _, t, _ in arrivals])
    seqs = [a[2] for a in arrivals]
    unique = set(seqs)
    # Loss bursts: runs of seq that never arrived.
    runs, run = [], 0
    for s in range(n):
        if s in unique:
            if run:
                runs.append(run)
            run = 0
        else:
            run += 1
    if run:
        runs.append(run)
    # Reordering: messages that arrived ahead of an earlier one that still
    # arrived later (netem's "sent immediately"), and RFC 4737-style late
    # arrivals (below the highest seq already seen).
    first = []
    seen: set[int] = set()
    for s in seqs:
        if s not in seen:
            seen.add(s)
            first.append(s)
    suffix_min = math.inf
    overtakers = 0
    for s in reversed(first):
        if s > suffix_min:
            overtakers += 1
        suffix_min = min(suffix_min, s)
    late, highest = 0, -1
    for s in first:
        if s < highest:
            late += 1
        highest = max(highest, s)
    # RFC 3550 jitter over the arrival order, averaged over the run.
    transit = [due - t for due, _, _, t, _ in arrivals]
    j, js = 0.0, []
    for a, b in itertools.pairwise(transit):
        j += (abs(b - a) - j) / 16
        js.append(j)
    return {
        "mean_ms": float(delays.mean()) if len(delays) else math.nan,
        "p50_ms": float(np.quantile(delays, 0.5)) if len(delays) else math.nan,
        "p99_ms": float(np.quantile(delays, 0.99)) if len(delays) else math.nan,
        "max_ms": float(delays.max()) if len(delays) else math.nan,
        "jitter_ms": float(np.mean(js)) / MS if js else 0.0,
        "loss": 1 - len(unique) / n,
        "burst": float(np.mean(runs)) if runs else 0.0,
        "max_burst": max(runs, default=0),
        "dup": (len(arrivals) - len(unique)) / n,
        "reorder": overtakers / n,
        "late": late / n,
        "corrupt": sum(a[4] for a in arrivals) / max(1, len(arrivals)),
        "retransmitted": engine.counts.retransmitted / n,
        "held_back": engine.counts.held_back / n,
        "engine_us_per_msg": cost_us,
    }


def close_enough(measured: float, want: float) -> bool:
    return abs(measured - want) <= max(0.5, 0.05 * abs(want))


def virtual_part(n: int, seed: int) -> list[dict[str, Any]]:
    cases: list[tuple[str, str, DirectionConfig]] = []
    for name in builtin_scenarios():
        if name == "none":
            continue
        s = load_scenario(name)
        cases.append((name, "to_operator", s.to_operator))
        if s.to_robot != s.to_operator:
            cases.append((name, "to_robot", s.to_robot))
    cases.append(("stress (datagram)", "to_operator", STRESS))
    rows = []
    for name, direction, cfg in cases:
        for rate in RATES_HZ:
            # the path's own draws, each datagram its delay (a scenario that keeps the order
            # holds some back behind the one before: the delivery rows' kind of figure)
            path_cfg = dataclasses.replace(cfg, delivery="datagram", jitter_reorders=True)
            conf = configured(path_cfg, rate, n)
            run_seed = seed * 1000 + rate  # independent runs per rate
            path = measure(path_cfg, rate, n, seed=run_seed, name=direction)
            row: dict[str, Any] = {
                "scenario": name,
                "direction": direction,
                "rate_hz": rate,
                "configured": conf,
                "path": path,
            }
            if cfg.delivery == "stream":
                row["stream"] = measure(cfg, rate, n, seed=run_seed, name=direction)
            row["checks"] = {
                "p50": close_enough(path["p50_ms"], conf["p50_ms"]),
                "p99": close_enough(path["p99_ms"], conf["p99_ms"]),
                "loss": abs(path["loss"] - conf["loss"]) <= 0.01,
            }
            rows.append(row)
    return rows


# ---------------------------------------------------------------- sockets
def _sock(ctx: zmq.Context, kind: int) -> zmq.Socket:
    s = ctx.socket(kind)
    s.setsockopt(zmq.LINGER, 0)
    if kind == zmq.SUB:
        s.setsockopt(zmq.SUBSCRIBE, b"")
    return s


def _join(pub: zmq.Socket, sub: zmq.Socket) -> None:
    t_end = time.monotonic() + 5
    while time.monotonic() < t_end:
        pub.send(b"PRBE")
        if sub.poll(20):
            break
    else:
        raise TimeoutError("subscription never completed")
    time.sleep(0.1)
    while sub.poll(0):
        sub.recv()


def socket_run(scenario: Scenario, rate_hz: float, n: int, seed: int) -> dict[str, Any]:
    """Interleave a direct PUB->SUB hop and the same hop through the simulator."""
    ctx = zmq.Context()
    try:
        robot_pub = _sock(ctx, zmq.PUB)
        robot_pub.bind("tcp://127.0.0.1:*")
        robot_sub = _sock(ctx, zmq.SUB)
        robot_sub.bind("tcp://127.0.0.1:*")
        direct_pub = _sock(ctx, zmq.PUB)
        direct_pub.bind("tcp://127.0.0.1:*")
        direct_sub = _sock(ctx, zmq.SUB)
        direct_sub.connect(direct_pub.getsockopt(zmq.LAST_ENDPOINT).decode())
        ep = Endpoints(
            robot_telemetry=robot_pub.getsockopt(zmq.LAST_ENDPOINT).decode(),
            robot_commands=robot_sub.getsockopt(zmq.LAST_ENDPOINT).decode(),
            operator_telemetry="tcp://127.0.0.1:*",
            operator_commands="tcp://127.0.0.1:*",
        )
        with LinkSimulator(scenario, endpoints=ep, seed=seed) as sim:
            op_sub = _sock(ctx, zmq.SUB)
            op_sub.connect(sim.operator_telemetry_endpoint)
            _join(robot_pub, op_sub)
            _join(direct_pub, direct_sub)
            sim.own_latency_ns()  # (the probes' costs are dropped below)
            n_probe = sim.counters()["to_operator"]["sent"]
            period = 1.0 / rate_hz
            via, direct, lateness = [], [], []
            replay = DirectionImpairment(scenario.to_operator, seed=seed, name="to_operator")
            # The probes went through the engine first; replay them too.
            for _ in range(sim.counters()["to_operator"]["received"]):
                replay.process(0, b"PRBE")
            t_next = time.monotonic()
            for i in range(n):
                t_next += period
                while (rest := t_next - time.monotonic()) > 0:
                    time.sleep(rest)
                payload = b"STIM" + i.to_bytes(8, "little") + bytes(SIZE - 12)
                use_sim = i % 2 == 0
                pub, sub = (robot_pub, op_sub) if use_sim else (direct_pub, direct_sub)
                t0 = time.monotonic_ns()
                pub.send(payload)
                if use_sim:
                    (chosen_due, _), *_ = replay.process(0, payload)
                if not sub.poll(5000):
                    raise TimeoutError("message lost on a lossless link")
                sub.recv()
                dt = time.monotonic_ns() - t0
                if use_sim:
                    via.append(dt / 1e3)
                    lateness.append((dt - chosen_due) / 1e3)
                else:
                    direct.append(dt / 1e3)
            own = [x / 1e3 for x in sim.own_latency_ns()[n_probe:]]
    finally:
        ctx.destroy(linger=0)

    def pct(v: list[float], q: float) -> float:
        return float(np.quantile(v, q))

    return {
        "rate_hz": rate_hz,
        "n": n,
        "direct_p50_us": pct(direct, 0.5),
        "direct_p99_us": pct(direct, 0.99),
        "via_p50_us": pct(via, 0.5),
        "via_p99_us": pct(via, 0.99),
        "own_p50_us": pct(own, 0.5),
        "own_p99_us": pct(own, 0.99),
        "lateness_p50_us": pct(lateness, 0.5),
        "lateness_p99_us": pct(lateness, 0.99),
        "own_from_e2e_p50_us": statistics.median(via) - 2 * statistics.median(direct),
    }


def socket_part(seed: int, seconds: float) -> list[dict[str, Any]]:
    zero = Scenario(name="none")
    jittered = Scenario(
        name="jittered",
        to_operator=DirectionConfig(
            delivery="datagram", delay_ms=20, jitter_ms=5, distribution="normal"
        ),
    )
    out = []
    for scenario in (zero, jittered):
        for rate in RATES_HZ:
            n = int(seconds * rate)
            r = socket_run(scenario, rate, n, seed)
            r["scenario"] = scenario.name
            out.append(r)
    return out


# ---------------------------------------------------------------- report
def _f(x: float, nd: int = 2) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{nd}f}"


def _pc(x: float) -> str:
    return f"{100 * x:.2f}"


def report(rows: list[dict], sockets: list[dict], n: int, seed: int) -> tuple[str, bool]:
    ok = True
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    lines = [
        f"Measured {time.strftime('%Y-%m-%d')} on {platform.machine()} ({os.cpu_count()} cores, "
        f"load average {load} at the end), Python "
        f"{platform.python_version()}, seed {seed} (x 1000 + rate), {n:,} messages of {SIZE} B "
        "per run; `python -m harness.bench.netsim_engine` regenerates this section.",
        "",
        "### Path delay and loss (datagram, virtual time): configured / measured",
        "",
        "Delays in ms. Check: p50 and p99 within 0.5 ms or 5 %, loss within 1 point "
        "(configured loss includes the share of the run spent in an outage).",
        "",
        "| scenario | dir | Hz | mean | p50 | p99 | jitter | loss % | mean burst | max burst "
        "| ok |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        c, m = r["configured"], r["path"]
        good = all(r["checks"].values())
        ok &= good
        lines.append(
            f"| {r['scenario']} | {r['direction']} | {r['rate_hz']} "
            f"| {_f(c['mean_ms'])} / {_f(m['mean_ms'])} "
            f"| {_f(c['p50_ms'])} / {_f(m['p50_ms'])} "
            f"| {_f(c['p99_ms'])} / {_f(m['p99_ms'])} "
            f"| {_f(c['jitter_ms'])} / {_f(m['jitter_ms'])} "
            f"| {_pc(c['loss'])} / {_pc(m['loss'])} "
            f"| {_f(c['burst'])} / {_f(m['burst'])} | {m['max_burst']} "
            f"| {'yes' if good else '**NO**'} |"
        )
    lines += [
        "",
        "### Duplication, reordering, corruption (datagram stress config): configured / measured",
        "",
        "Reordered = sent at once and overtook an earlier message (netem's definition); "
        "late = arrived below the highest sequence already seen (RFC 4737 style), "
        "which counts each overtaken message.",
        "",
        "| Hz | dup % | reordered % | late % | corrupted % |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        if r["scenario"].startswith("stress"):
            c, m = r["configured"], r["path"]
            lines.append(
                f"| {r['rate_hz']} | {_pc(c['dup'])} / {_pc(m['dup'])} "
                f"| {_pc(c['reorder'])} / {_pc(m['reorder'])} | {_pc(m['late'])} "
                f"| {_pc(c['corrupt'])} / {_pc(m['corrupt'])} |"
            )
    lines += [
        "",
        "### Delivered as configured (stream: retransmission and head-of-line blocking)",
        "",
        "What a receiver sees over ZeroMQ/TCP with the scenario's own delivery model: nothing "
        "is lost, but each loss costs `retransmit_ms` (doubling while the link is down) and "
        "holds back the messages behind it. Not compared with the path distribution.",
        "",
        "| scenario | dir | Hz | path p50 | p50 | p99 | max | jitter | resent % | held back % |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "stream" in r:
            m = r["stream"]
            lines.append(
                f"| {r['scenario']} | {r['direction']} | {r['rate_hz']} "
                f"| {_f(r['configured']['p50_ms'])} | {_f(m['p50_ms'])} | {_f(m['p99_ms'])} "
                f"| {_f(m['max_ms'], 0)} | {_f(m['jitter_ms'])} | {_pc(m['retransmitted'])} "
                f"| {_pc(m['held_back'])} |"
            )
    engine_us = [r["path"]["engine_us_per_msg"] for r in rows]
    lines += [
        "",
        f"Engine cost: {min(engine_us):.1f}-{max(engine_us):.1f} us per message "
        "(decisions only, no sockets).",
    ]
    if sockets:
        lines += [
            "",
            "### Real sockets on loopback (tcp, 200 B messages), microseconds",
            "",
            "direct = one PUB->SUB hop; via = robot PUB -> simulator -> operator SUB (two hops); "
            "own = inside the simulator, from its receive returning to its send returning "
            "(minus any configured delay); late = via minus the delay the engine chose for that "
            "message (replayed in virtual time with the same seed).",
            "",
            "| scenario | Hz | n | direct p50 / p99 | via p50 / p99 | own p50 / p99 "
            "| via - 2 x direct (p50) | late p50 / p99 |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for s in sockets:
            if s["scenario"] == "none":
                ok &= s["own_p50_us"] < 100
            lines.append(
                f"| {s['scenario']} | {s['rate_hz']} | {s['n']} "
                f"| {_f(s['direct_p50_us'], 0)} / {_f(s['direct_p99_us'], 0)} "
                f"| {_f(s['via_p50_us'], 0)} / {_f(s['via_p99_us'], 0)} "
                f"| {_f(s['own_p50_us'], 0)} / {_f(s['own_p99_us'], 0)} "
                f"| {_f(s['own_from_e2e_p50_us'], 0)} "
                f"| {_f(s['lateness_p50_us'], 0)} / {_f(s['lateness_p99_us'], 0)} |"
            )
    lines += ["", f"All criteria met: {'yes' if ok else '**NO**'}."]
    return "\n".join(lines) + "\n", ok


def update_docs(path: Path, section: str) -> None:
    replace_block(path, BEGIN, END, section.removesuffix("\n").split("\n"))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--messages", type=int, default=10_000, help="per scenario, rate and model")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--socket-seconds", type=float, default=6.0, help="per socket run")
    p.add_argument("--skip-sockets", action="store_true")
    p.add_argument("--update-docs", type=Path, help="replace the marked section of this file")
    p.add_argument("--json", type=Path, help="write every number here")
    args = p.parse_args()
    rows = virtual_part(args.messages, args.seed)
    sockets = [] if args.skip_sockets else socket_part(args.seed, args.socket_seconds)
    section, ok = report(rows, sockets, args.messages, args.seed)
    print(section)
    if args.update_docs:
        update_docs(args.update_docs, section)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"virtual": rows, "sockets": sockets}, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
