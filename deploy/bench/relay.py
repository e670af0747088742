"""The relay (deepxpalm relay): what it adds to latency, and what fan-out costs the robot.

Many subscribers behind a relay, in one process: what the relay section and
its tests measure.

``swarm`` (a process target) holds many relay clients at once, each with its
own CURVE and signing key, and serves them from one poll loop so that every
subscriber is treated alike: a ``normal`` one reads everything at once and
notes each stimulus's latency (receive time minus the sender's send time:
one machine, one monotonic clock); a ``stalled`` one subscribes and never
reads; a ``slow`` one reads no faster than ``slow_bytes_per_s`` (64 kbit/s
is 8,000 bytes/s) with small socket buffers, as a thin link would. Clients
with a signing key also send signed heartbeats that echo the robot's, so
the robot sees them as the observers they stand for.

``publish`` (a process target) sends the same stimulus stream to several
relays at once, alternating which goes first, so that two relays' subscribers
can be compared side by side in one run.

The section's two measurements, both with CURVE on every hop and real
processes:

- **added latency**: one stream sent, in the same run, through the relay
  and straight to a subscriber that binds as a robot does today; the ratio
  of the two paths' percentiles;
- **robot CPU against observers**: a robot node connected out to the relay,
  with 1, 4 and 16 signed observers behind it (each with its own keys,
  subscribed to stimuli, heartbeats and frames, heartbeating at the observer
  rate). The relay fans the stream out, so the robot sends each message once.
"""

from __future__ import annotations

import secrets
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import zmq

from common.codec import MAX_MESSAGE_BYTES, MAX_NAME_LEN, DecodeError, decode_named, name_prefix
from common.messages import Heartbeat, Stimulus, TactileFrame
from common.security import SecurityConfig, client_options, server_options
from common.signing import load_signer
from common.tactile import FRAME_SHAPE
from common.transport import free_loopback_ports
from deploy.bench.fmt import num, results_of, table
from deploy.bench.section import Context, Results, Section, Verdict


@dataclass
class ClientSpec:
    """One subscriber of the swarm."""

    label: str
    endpoint: str  # the relay's operator telemetry endpoint
    command_endpoint: str | None  # where its heartbeats go (None: it sends nothing)
    security: dict[str, str]  # SecurityConfig keys
    signing_secret: str | None = None
    kind: str = "normal"  # normal, stalled, slow
    #: bind ``endpoint`` as the CURVE server with ``security``'s key (a direct path, no relay)
    bind: bool = False


def _security(d: dict[str, str]) -> SecurityConfig:
    return SecurityConfig(
        mode=d.get("mode", "plain"),
        secret_key_file=d.get("secret_key_file"),
        server_public_key_file=d.get("server_public_key_file"),
    )


def swarm(
    clients: list[ClientSpec],
    robot: str,
    duration_s: float,
    heartbeat_hz: float,
    slow_bytes_per_s: float,
    conn: Any,
) -> None:
    """Serve every client for ``duration_s``; send back per-client counts and latencies (us)."""
    from common.clock_sync import ClockSync

    ctx = zmq.Context()
    name = robot.encode()
    subs, pubs, signers, clocks = [], [], [], []
    for spec in clients:
        sec = _security(spec.security)
        opts = server_options(sec) if spec.bind else client_options(sec)
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.MAXMSGSIZE, MAX_MESSAGE_BYTES + 1 + MAX_NAME_LEN)
        if spec.kind == "slow":  # a thin link: little buffered anywhere on the way in
            sub.setsockopt(zmq.RCVBUF, 4096)
            sub.setsockopt(zmq.RCVHWM, 4)
        for k, v in opts.items():
            sub.setsockopt(k, v)
        if spec.bind:
            sub.bind(spec.endpoint)
        else:
            sub.connect(spec.endpoint)
        for topic in (Stimulus.TOPIC, Heartbeat.TOPIC, TactileFrame.TOPIC):
            sub.setsockopt(zmq.SUBSCRIBE, name_prefix(topic, name))
        subs.append(sub)
        pub = None
        if spec.command_endpoint is not None and spec.signing_secret is not None:
            pub = ctx.socket(zmq.PUB)
            pub.setsockopt(zmq.LINGER, 0)
            for k, v in client_options(sec).items():
                pub.setsockopt(k, v)
            pub.connect(spec.command_endpoint)
        pubs.append(pub)
        signers.append(load_signer(spec.signing_secret) if spec.signing_secret else None)
        clocks.append(ClockSync())
    poller = zmq.Poller()
    readers = [i for i, spec in enumerate(clients) if spec.kind != "stalled"]
    for i in readers:
        poller.register(subs[i], zmq.POLLIN)
    latencies: list[list[float]] = [[] for _ in clients]
    received = [0] * len(clients)
    bytes_in = [0] * len(clients)
    rejected = [0] * len(clients)
    budget = [0.0] * len(clients)
    hb_seq = 0
    boot = secrets.randbits(63) or 1  # this bench run's operator boot id
    runs: list[int | None] = [None] * len(clients)  # each client's robot run heard
    period = 1e9 / heartbeat_hz if heartbeat_hz > 0 else None
    next_hb = time.monotonic_ns()
    last_t = time.monotonic_ns()
    t_end = time.monotonic() + duration_s
    from common.codec import encode

    turn = 0
    while time.monotonic() < t_end:
        ready = dict(poller.poll(5))
        now = time.monotonic_ns()
        dt = (now - last_t) / 1e9
        last_t = now
        turn += 1
        for i in readers if turn % 2 else readers[::-1]:  # nobody always reads first
            sock = subs[i]
            slow = clients[i].kind == "slow"
            if slow:
                budget[i] = min(budget[i] + dt * slow_bytes_per_s, 2 * slow_bytes_per_s / 10)
            if sock not in ready and not slow:
                continue
            while sock.get(zmq.EVENTS) & zmq.POLLIN:
                if slow and budget[i] <= 0:
                    break
                data = sock.recv(zmq.NOBLOCK)
                t_recv = time.monotonic_ns()
                received[i] += 1
                bytes_in[i] += len(data)
                if slow:
                    budget[i] -= len(data)
                try:
                    _, msg = decode_named(data)
                except DecodeError:
                    rejected[i] += 1
                    continue
                if isinstance(msg, Stimulus):
                    latencies[i].append((t_recv - msg.t_send_ns) / 1e3)
                elif isinstance(msg, Heartbeat):
                    runs[i] = msg.session  # echoed: the robot believes our heartbeats from it
                    echo = msg.echo_signer
                    mine = signers[i] is not None and echo == signers[i].public
                    clocks[i].on_heartbeat(
                        msg.t_send_ns,
                        msg.echo_t_send_ns if mine else None,
                        msg.echo_t_recv_ns if mine else None,
                        t_recv,
                    )
        if period is not None and now >= next_hb:
            next_hb = now + period
            hb_seq += 1
            for i, pub in enumerate(pubs):
                if pub is None:
                    continue
                echo_send, echo_recv = clocks[i].echo_fields()
                hb = Heartbeat(
                    seq=hb_seq,
                    t_send_ns=time.monotonic_ns(),
                    node="operator",
                    state="ok",
                    echo_t_send_ns=echo_send,
                    echo_t_recv_ns=echo_recv,
                    session=boot,
                    echo_session=runs[i],
                )
                pub.send(encode(hb, name, signers[i]), zmq.NOBLOCK)
    out = []
    for i, spec in enumerate(clients):
        lat = np.asarray(latencies[i])
        out.append(
            {
                "label": spec.label,
                "kind": spec.kind,
                "received": received[i],
                "bytes": bytes_in[i],
                "rejected": rejected[i],
                "stimuli": len(lat),
                "p50_us": float(np.percentile(lat, 50)) if len(lat) else None,
                "p99_us": float(np.percentile(lat, 99)) if len(lat) else None,
                "latencies_us": lat.tolist(),
            }
        )
    for sock in subs + [p for p in pubs if p is not None]:
        sock.close(0)
    ctx.term()
    conn.send(out)


def publish(
    endpoints: list[str],
    security: dict[str, str],
    robot: str,
    rate_hz: float,
    frame_every: int,
    duration_s: float,
    conn: Any,
) -> None:
    """The same stream to every relay: stimuli at ``rate_hz``, a raw frame every few."""
    from common.codec import encode

    ctx = zmq.Context()
    opts = client_options(_security(security))
    socks = []
    for endpoint in endpoints:
        sock = ctx.socket(zmq.PUB)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.SNDHWM, 1000)
        for k, v in opts.items():
            sock.setsockopt(k, v)
        sock.connect(endpoint)
        socks.append(sock)
    name = robot.encode()
    cells = np.zeros((3, 3), np.float32)
    cells[1, 1] = 3.0
    frame = np.full(FRAME_SHAPE, 1.5, np.float32)
    time.sleep(1.0)  # subscriptions reach the relays and come back to us
    period = 1.0 / rate_hz
    t_next = time.monotonic()
    t_end = t_next + duration_s
    seq = 0
    while time.monotonic() < t_end:
        seq += 1
        now = time.monotonic_ns()
        msgs = [
            Stimulus(
                seq=seq,
                t_send_ns=now,
                t_capture_ns=now,
                frame_seq=seq,
                mode="direct",
                contact=True,
                stimulus=cells,
            )
        ]
        if seq % frame_every == 0:
            msgs.append(
                TactileFrame(seq=seq, t_send_ns=now, t_capture_ns=now, frame_seq=seq, frame=frame)
            )
        order = socks if seq % 2 else socks[::-1]  # neither relay always goes first
        for msg in msgs:
            data = encode(msg, name)
            for sock in order:
                sock.send(data, zmq.NOBLOCK)
        t_next += period
        delay = t_next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    for sock in socks:
        sock.close(0)
    ctx.term()
    conn.send({"sent": seq})


def run_isolation(
    duration_s: float = 10.0,
    rate_hz: float = 200.0,
    frame_every: int = 1,
    slow_bytes_per_s: float = 8000.0,
    workdir: Any = None,
    swap: bool = False,
) -> dict[str, Any]:
    """Two relays fed the same stream, four subscribers each: on A two measured ones, a
    stalled one and a 64 kbit/s one; on B two measured ones and two more that read
    everything (so B forwards as much as A, or more). The measured subscribers' pooled
    p99 on A against B's, in one run, one process, one poll loop. ``swap``: the stalled
    and slow subscribers go to the other relay process (A and B trade places).
    """
    import multiprocessing

    from deploy.fleet import Fleet

    fleet = Fleet(
        robots=["pub"],
        operators={n: "observer" for n in ("a1", "a2", "stall", "slow", "b1", "b2", "b3", "b4")},
        **({} if workdir is None else {"workdir": workdir}),
    )
    mp = multiprocessing.get_context("spawn")
    with fleet:
        fleet.start_relay("relay")
        fleet.start_relay("relay_b")
        ends = fleet.relay_endpoints
        time.sleep(1.0)
        clients = []
        ra, rb = ("relay_b", "relay") if swap else ("relay", "relay_b")
        for label, relay, kind in (
            ("a1", ra, "normal"),
            ("b1", rb, "normal"),
            ("stall", ra, "stalled"),
            ("slow", ra, "slow"),
            ("b3", rb, "normal"),
            ("b4", rb, "normal"),
            ("a2", ra, "normal"),
            ("b2", rb, "normal"),
        ):
            clients.append(
                ClientSpec(
                    label,
                    ends[relay]["operators_telemetry"],
                    None,
                    fleet.client_security(label),
                    kind=kind,
                )
            )
        sw_parent, sw_child = mp.Pipe(duplex=False)
        pub_parent, pub_child = mp.Pipe(duplex=False)
        sw = mp.Process(
            target=swarm,
            args=(clients, "pub", duration_s + 3.0, 0.0, slow_bytes_per_s, sw_child),
            daemon=True,
        )
        sw.start()
        time.sleep(1.0)
        pub = mp.Process(
            target=publish,
            args=(
                [ends["relay"]["robots_telemetry"], ends["relay_b"]["robots_telemetry"]],
                fleet.client_security("pub"),
                "pub",
                rate_hz,
                frame_every,
                duration_s,
                pub_child,
            ),
            daemon=True,
        )
        pub.start()
        sent = pub_parent.recv() if pub_parent.poll(duration_s + 60) else {}
        result = sw_parent.recv() if sw_parent.poll(duration_s + 60) else []
        pub.join(5)
        sw.join(5)
    by = {r["label"]: r for r in result}
    pooled = {}
    for side, labels in (("with_stalled", ("a1", "a2")), ("without", ("b1", "b2"))):
        lat = np.concatenate([by[x]["latencies_us"] for x in labels if x in by] or [[]])
        pooled[side] = {
            "p50_us": float(np.percentile(lat, 50)) if len(lat) else None,
            "p99_us": float(np.percentile(lat, 99)) if len(lat) else None,
            "samples": len(lat),
        }
    for r in by.values():
        r.pop("latencies_us", None)
    with_p99, without_p99 = pooled["with_stalled"]["p99_us"], pooled["without"]["p99_us"]
    return {
        "swapped": swap,
        "pooled": pooled,
        "p99_ratio": None if not with_p99 or not without_p99 else with_p99 / without_p99,
        "rate_hz": rate_hz,
        "frame_every": frame_every,
        "duration_s": duration_s,
        "sent": sent.get("sent"),
        "slow_bytes_per_s": slow_bytes_per_s,
        "clients": by,
    }


def run_latency(duration_s: float, rate_hz: float, workdir: Any = None) -> dict[str, Any]:
    """One stream, two paths in the same run: through the relay, and straight to a subscriber.

    Both are CURVE; the direct subscriber binds (as a robot does today) and the
    publisher connects to it and to the relay, sending each message on both,
    alternating which goes first.
    """
    import multiprocessing

    from deploy.fleet import Fleet

    fleet = Fleet(
        robots=["pub"],
        operators={"via_relay": "observer", "direct": "observer"},
        **({} if workdir is None else {"workdir": workdir}),
    )
    mp = multiprocessing.get_context("spawn")
    with fleet:
        fleet.start_relay()
        (direct_port,) = free_loopback_ports(1)
        direct = f"tcp://127.0.0.1:{direct_port}"
        relay_keys = {"mode": "curve", "secret_key_file": str(fleet.members["relay"].curve_secret)}
        clients = [
            ClientSpec("via_relay", fleet.ops_telemetry, None, fleet.client_security("via_relay")),
            ClientSpec("direct", direct, None, relay_keys, bind=True),
        ]
        time.sleep(1.0)
        result, sent = _run_pair(
            mp, clients, [fleet.robots_telemetry, direct], fleet, rate_hz, duration_s
        )
    by = {r["label"]: r for r in result}
    for r in by.values():
        r.pop("latencies_us", None)
    relay, straight = by.get("via_relay", {}), by.get("direct", {})

    def ratio(key: str) -> float | None:
        a, b = relay.get(key), straight.get(key)
        return None if not a or not b else a / b

    return {
        "rate_hz": rate_hz,
        "duration_s": duration_s,
        "sent": sent.get("sent"),
        "via_relay": relay,
        "direct": straight,
        "p50_ratio": ratio("p50_us"),
        "p99_ratio": ratio("p99_us"),
        "p50_added_us": None
        if relay.get("p50_us") is None or straight.get("p50_us") is None
        else relay["p50_us"] - straight["p50_us"],
    }


def _run_pair(
    mp: Any,
    clients: list[ClientSpec],
    endpoints: list[str],
    fleet: Any,
    rate_hz: float,
    duration_s: float,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    sw_parent, sw_child = mp.Pipe(duplex=False)
    pub_parent, pub_child = mp.Pipe(duplex=False)
    sw = mp.Process(
        target=swarm, args=(clients, "pub", duration_s + 3.0, 0.0, 8000.0, sw_child), daemon=True
    )
    sw.start()
    time.sleep(1.0)
    pub = mp.Process(
        target=publish,
        args=(endpoints, fleet.client_security("pub"), "pub", rate_hz, 4, duration_s, pub_child),
        daemon=True,
    )
    pub.start()
    sent = pub_parent.recv() if pub_parent.poll(duration_s + 60) else {}
    result = sw_parent.recv() if sw_parent.poll(duration_s + 60) else []
    pub.join(5)
    sw.join(5)
    return result, sent


def process_cpu_s(pid: int) -> float:
    """utime + stime of a process so far, seconds (/proc)."""
    import os

    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()  # noqa: SIM115
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_robot_cpu(
    counts: tuple[int, ...], warmup_s: float, measure_s: float, workdir: Any = None
) -> dict[str, Any]:
    """A robot node behind the relay, and 1, 4, 16 ... observers (signed, heartbeating at the
    observer rate): the robot's and the relay's CPU over the same window for each count.
    """
    import multiprocessing

    from deploy.fleet import Fleet
    from operator_side.config import OperatorLinkConfig

    n_max = max(counts)
    names = [f"obs{i}" for i in range(n_max)]
    fleet = Fleet(
        robots=["cell1"],
        operators=dict.fromkeys(names, "observer"),
        **({} if workdir is None else {"workdir": workdir}),
    )
    mp = multiprocessing.get_context("spawn")
    rows = []
    hb_hz = OperatorLinkConfig().observer_heartbeat_rate_hz
    with fleet:
        relay = fleet.start_relay()
        robot = fleet.start_robot("cell1", None)
        time.sleep(4.0)  # the robot node up and streaming
        for n in counts:
            clients = [
                ClientSpec(
                    name,
                    fleet.ops_telemetry,
                    fleet.ops_command,
                    fleet.client_security(name),
                    signing_secret=str(fleet.members[name].signing_secret),
                )
                for name in names[:n]
            ]
            parent, child = mp.Pipe(duplex=False)
            sw = mp.Process(
                target=swarm,
                args=(clients, "cell1", warmup_s + measure_s + 0.5, hb_hz, 8000.0, child),
                daemon=True,
            )
            sw.start()
            time.sleep(warmup_s)
            r0, q0, t0 = (
                process_cpu_s(robot.popen.pid),
                process_cpu_s(relay.popen.pid),
                time.monotonic(),
            )
            time.sleep(measure_s)
            r1, q1, t1 = (
                process_cpu_s(robot.popen.pid),
                process_cpu_s(relay.popen.pid),
                time.monotonic(),
            )
            out = parent.recv() if parent.poll(60) else []
            sw.join(5)
            got = [c["stimuli"] for c in out]
            rows.append(
                {
                    "observers": n,
                    "robot_cpu_percent": 100.0 * (r1 - r0) / (t1 - t0),
                    "relay_cpu_percent": 100.0 * (q1 - q0) / (t1 - t0),
                    "stimuli_per_observer_min": min(got) if got else 0,
                    "stimuli_per_observer_max": max(got) if got else 0,
                }
            )
    robot_stats = fleet.procs["cell1"].stats()
    base = rows[0]["robot_cpu_percent"] if rows else None
    for row in rows:
        row["robot_cpu_ratio"] = None if not base else row["robot_cpu_percent"] / base
    keep = ("stimuli_published", "messages_unknown_signer", "decode_errors", "frames_unwanted")
    return {
        "warmup_s": warmup_s,
        "measure_s": measure_s,
        "observer_heartbeat_hz": hb_hz,
        "rows": rows,
        "robot_stats": {k: v for k, v in robot_stats.items() if k in keep},
    }


TITLE = "Relay"

#: the issue's goal: the robot's CPU with 16 observers within this factor of its CPU with 1
CPU_RATIO_GOAL = 1.2
#: the issue's goal: a stalled subscriber moves no other subscriber's p99 by more than 10 %
ISOLATION_GOAL = 1.10


@dataclass(frozen=True)
class RelaySizes:
    latency_s: float
    latency_rate_hz: float
    observer_counts: tuple[int, ...]
    cpu_warmup_s: float
    cpu_measure_s: float
    isolation_s: float
    isolation_rate_hz: float


SIZES = {
    "full": RelaySizes(15.0, 100.0, (1, 4, 16), 3.0, 15.0, 20.0, 250.0),
    "quick": RelaySizes(6.0, 100.0, (1, 4, 16), 2.0, 5.0, 8.0, 250.0),
    "smallest": RelaySizes(1.5, 100.0, (1, 4), 0.5, 1.0, 1.5, 100.0),
}


def measure(ctx: Context, sizes: RelaySizes) -> dict[str, Any]:
    return {
        "latency": run_latency(sizes.latency_s, sizes.latency_rate_hz),
        "cpu": run_robot_cpu(sizes.observer_counts, sizes.cpu_warmup_s, sizes.cpu_measure_s),
        "isolation": run_isolation(sizes.isolation_s, sizes.isolation_rate_hz),
    }


def _cpu_ratio(s: dict[str, Any]) -> tuple[int, float] | None:
    rows = s.get("cpu", {}).get("rows", [])
    if len(rows) < 2 or rows[-1].get("robot_cpu_ratio") is None:
        return None
    return rows[-1]["observers"], rows[-1]["robot_cpu_ratio"]


def verdicts(results: Results) -> list[Verdict]:
    s = results_of(results, "relay")
    got = None if s is None else _cpu_ratio(s)
    if got is None:
        return [Verdict(f"robot CPU with many observers <= {CPU_RATIO_GOAL:g}x one", None, None)]
    n, ratio = got
    rows = [
        Verdict(
            f"relay: robot CPU with {n} observers <= {CPU_RATIO_GOAL:g}x with 1",
            f"{ratio:.2f}x",
            ratio <= CPU_RATIO_GOAL,
        )
    ]
    iso = s.get("isolation", {})
    r = iso.get("p99_ratio")
    rows.append(
        Verdict(
            f"relay: a stalled and a 64 kbit/s subscriber move others' p99 by <= "
            f"{ISOLATION_GOAL - 1:.0%}",
            None if r is None else f"{r:.2f}x",
            None if r is None else r <= ISOLATION_GOAL,
        )
    )
    return rows


def markdown(results: Results) -> list[str]:
    s = results_of(results, "relay")
    out = ["", f"## {TITLE}", ""]
    if s is None:
        return [*out, "Not run."]
    lat = s["latency"]
    out += [
        f"Added latency: the same stimulus stream ({lat['rate_hz']:g} Hz, a frame every 4th, "
        f"{lat['duration_s']:g} s) sent in one run through `deepxpalm relay` and straight to a "
        "subscriber that binds as a robot does today; CURVE on every hop; receive time minus "
        "send time on one machine's monotonic clock.",
        "",
    ]
    rows = []
    for label in ("direct", "via_relay"):
        r = lat.get(label, {})
        rows.append(
            [
                label.replace("_", " "),
                num(r.get("stimuli")),
                num(r.get("p50_us")),
                num(r.get("p99_us")),
            ]
        )
    rows.append(
        ["ratio (relay / direct)", "", num(lat.get("p50_ratio"), 2), num(lat.get("p99_ratio"), 2)]
    )
    out += table(["path", "stimuli", "p50 (us)", "p99 (us)"], rows, "|---|---:|---:|---:|")
    cpu = s["cpu"]
    out += [
        "",
        f"Robot CPU against observers: a robot node (scripted pads, 60 Hz stimuli, 15 Hz "
        f"frames) connected out to the relay; each observer a signed relay client with its "
        f"own keys, subscribed to the whole stream and heartbeating at "
        f"{cpu['observer_heartbeat_hz']:g} Hz (the observer rate). utime + stime from /proc "
        f"over {cpu['measure_s']:g} s after {cpu['warmup_s']:g} s.",
        "",
    ]
    out += table(
        ["observers", "robot CPU (%)", "ratio to 1", "relay CPU (%)", "stimuli per observer"],
        [
            [
                str(r["observers"]),
                num(r["robot_cpu_percent"]),
                num(r.get("robot_cpu_ratio"), 2),
                num(r["relay_cpu_percent"]),
                f"{r['stimuli_per_observer_min']}-{r['stimuli_per_observer_max']}",
            ]
            for r in cpu["rows"]
        ],
        "|---:|---:|---:|---:|---|",
    )
    iso = s.get("isolation")
    if not iso:
        return out
    c = iso["clients"]
    out += [
        "",
        f"Slow-subscriber isolation (libzmq #3280): the same stream ({iso['rate_hz']:g} Hz "
        f"stimuli and frames, {iso['duration_s']:g} s) into two relays; relay A also serves a "
        f"subscriber that never reads and one that reads at "
        f"{iso['slow_bytes_per_s'] * 8 / 1000:g} kbit/s, relay B two more that read "
        "everything (so B forwards at least as much as A). Two measured subscribers on each, "
        "read by one loop in one process in alternating order; pooled percentiles.",
        "",
    ]
    pooled = iso["pooled"]
    out += table(
        ["normal subscribers", "samples", "p50 (us)", "p99 (us)"],
        [
            [
                "beside a stalled and a slow one (A)",
                num(pooled["with_stalled"]["samples"]),
                num(pooled["with_stalled"]["p50_us"]),
                num(pooled["with_stalled"]["p99_us"]),
            ],
            [
                "beside two that read everything (B)",
                num(pooled["without"]["samples"]),
                num(pooled["without"]["p50_us"]),
                num(pooled["without"]["p99_us"]),
            ],
            ["ratio A / B", "", "", num(iso.get("p99_ratio"), 3)],
        ],
        "|---|---:|---:|---:|",
    )
    slow, stall = c.get("slow", {}), c.get("stall", {})
    out += [
        "",
        f"Of {num(iso.get('sent'))} stimuli sent, the stalled subscriber received "
        f"{num(stall.get('received'))} messages and the slow one {num(slow.get('stimuli'))} "
        f"stimuli, p50 {num((slow.get('p50_us') or 0) / 1e3, 0)} ms old: the relay drops for "
        "them instead of waiting, and a 64 kbit/s site gets a trickle of old data, which its "
        "palm's staleness rule (150 ms) lifts off rather than renders.",
    ]
    return out


SECTION = Section(
    name="relay",
    title=TITLE,
    sizes=SIZES,
    measure=measure,
    markdown=markdown,
    verdicts=verdicts,
    quick=False,
)
