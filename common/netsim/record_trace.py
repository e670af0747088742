"""Record a link as a one-way delay trace the simulator can replay.

On the far machine: ``python -m common.netsim.record_trace --serve 0.0.0.0:7070``
(a TCP echo). Here: ``python -m common.netsim.record_trace --target HOST:7070
--seconds 60 --out my_link.delays``. Each probe's one-way delay is taken as
half its round trip (no clock offset needed; a fixed asymmetry of the path
is not visible, as for the clock offset). ``--loopback`` runs the echo in a
child process on 127.0.0.1: how the shipped ``loopback_vm.delays`` was made.
"""

from __future__ import annotations

import argparse
import datetime
import platform
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

_PROBE = struct.Struct("<Q")


def serve(host: str, port: int) -> None:
    """Echo every byte back, one client at a time, until killed."""
    with socket.create_server((host, port)) as server:
        print(f"echo on {server.getsockname()[0]}:{server.getsockname()[1]}", flush=True)
        while True:
            conn, _ = server.accept()
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with conn:
                while data := conn.recv(4096):
                    conn.sendall(data)


def record(host: str, port: int, seconds: float, rate_hz: float) -> list[tuple[float, float]]:
    """``(t_s, one-way delay ms)`` per probe, ``rate_hz`` probes a second."""
    out: list[tuple[float, float]] = []
    with socket.create_connection((host, port), timeout=5) as conn:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        period = 1.0 / rate_hz
        t0 = time.monotonic()
        for i in range(round(seconds * rate_hz)):
            target = t0 + i * period
            time.sleep(max(0.0, target - time.monotonic()))
            sent = time.monotonic_ns()
            conn.sendall(_PROBE.pack(sent))
            echo = b""
            while len(echo) < _PROBE.size:
                echo += conn.recv(_PROBE.size - len(echo))
            rtt_ns = time.monotonic_ns() - _PROBE.unpack(echo)[0]
            out.append((round(target - t0, 6), round(rtt_ns / 2e6, 4)))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--serve", metavar="HOST:PORT", help="run the echo end")
    parser.add_argument("--target", metavar="HOST:PORT", help="record against this echo")
    parser.add_argument("--loopback", action="store_true", help="record against a local echo")
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--rate-hz", type=float, default=50.0)
    parser.add_argument("--out", type=Path, help="trace file to write (default: stdout)")
    args = parser.parse_args(argv)
    if args.serve:
        host, port = args.serve.rsplit(":", 1)
        serve(host, int(port))
        return 0
    child = None
    if args.loopback:
        child = subprocess.Popen(
            [sys.executable, "-m", "common.netsim.record_trace", "--serve", "127.0.0.1:0"],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert child.stdout is not None
        said = child.stdout.readline()  # "echo on HOST:PORT": listening, on the port it bound
        host, _, port_text = said.split()[-1].rpartition(":")
        port = int(port_text)
    elif args.target:
        host, port_text = args.target.rsplit(":", 1)
        port = int(port_text)
    else:
        parser.error("give --serve, --target or --loopback")
    try:
        samples = record(host, port, args.seconds, args.rate_hz)
    finally:
        if child is not None:
            child.kill()
            child.wait()
    where = "a loopback echo in a child process" if args.loopback else f"{host}:{port}"
    lines = [
        "# one-way delay trace: t_s delay_ms (half the TCP round trip of an 8-byte probe)",
        f"# recorded {datetime.date.today()} on {platform.machine()} ({platform.node()}) "
        f"against {where},",
        f"# {args.rate_hz:g} probes/s for {args.seconds:g} s: python -m "
        "common.netsim.record_trace " + " ".join(argv if argv is not None else sys.argv[1:]),
        *(f"{t:.3f} {d:.4f}" for t, d in samples),
    ]
    text = "\n".join(lines) + "\n"
    if args.out:
        args.out.write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
