"""The UR simulator in a child process, remote-controlled over its stdin/stdout.

Why a process: ur-rtde's interface constructors hold the GIL while they wait
for the controller's replies, so a simulator served by threads of the same
interpreter can never answer them (measured: the constructor deadlocks).
A child process also makes "the controller vanished" real: :meth:`kill`
takes it away as abruptly as a pulled cable.

Why ``subprocess`` and not ``multiprocessing``: spawn re-imports the
caller's main script, which breaks any script without a ``__main__`` guard.
The child (``python -m robot_side.arm.sim --stdio``) reads one JSON request
per line and answers one JSON line; it exits when its stdin closes, so a
crashed parent leaves no server behind.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import subprocess
import sys
from typing import IO, Any

import numpy as np

from common.config import to_dict
from common.errors import DeviceError, DeviceTimeoutError
from robot_side.arm.sim.server import URSimConfig, URSimulator

log = logging.getLogger(__name__)

#: Simulator methods the parent may call through the pipe.
REMOTE_METHODS = frozenset(
    {
        "freeze",
        "protective_stop",
        "unlock_protective_stop",
        "tcp_pose",
        "tcp_speed",
        "mode_name",
        "commands_seen",
        "stats",
        "client_count",
    }
)


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def serve_stdio(sim: URSimulator, stdin: IO[str], stdout: IO[str]) -> None:
    """The child's side: answer requests until stdin closes or "stop" arrives."""

    def reply(obj: dict[str, Any]) -> None:
        stdout.write(json.dumps(obj) + "\n")
        stdout.flush()

    reply({"ready": sim.host})
    try:
        for line in stdin:
            req = json.loads(line)
            method, args = req.get("method"), req.get("args", [])
            if method == "stop":
                break
            try:
                if method not in REMOTE_METHODS:
                    raise AttributeError(f"simulator has no remote method {method!r}")
                reply({"ok": _jsonable(getattr(sim, method)(*args))})
            except Exception as e:  # reported to the parent, which raises it
                reply({"error": f"{type(e).__name__}: {e}"})
    finally:
        sim.stop()
    with contextlib.suppress(OSError):  # the parent may have stopped listening
        reply({"ok": None})


class URSimProcess:
    """Start with :meth:`start`; ``host`` is then the address the simulator serves."""

    def __init__(self, config: URSimConfig | None = None, log_level: int = logging.WARNING):
        self.config = config or URSimConfig()
        self.log_level = log_level
        self.host: str | None = None
        self._proc: subprocess.Popen[str] | None = None

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def start(self, timeout_s: float = 15.0) -> URSimProcess:
        cmd = [
            sys.executable,
            "-m",
            "robot_side.arm.sim",
            "--stdio",
            "--config-json",
            json.dumps(to_dict(self.config)),
            "--log-level",
            str(self.log_level),
        ]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self._proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
        )
        try:
            msg = self._read(timeout_s, "start")
        except DeviceError:
            self.kill()
            raise
        if "ready" not in msg:
            self.kill()
            raise DeviceError(f"UR simulator failed to start: {msg.get('error', msg)}")
        self.host = msg["ready"]
        log.info("UR simulator process %d serving on %s", self._proc.pid, self.host)
        return self

    def _read(self, timeout_s: float, what: str) -> dict[str, Any]:
        proc = self._proc
        assert proc is not None and proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
        if not ready:
            raise DeviceTimeoutError(f"UR simulator did not answer {what} in {timeout_s:.0f} s")
        line = proc.stdout.readline()
        if not line:
            raise DeviceError(
                f"UR simulator process exited during {what} (code {proc.poll()}); "
                "see its log on stderr"
            )
        return json.loads(line)

    def call(self, method: str, *args: Any, timeout_s: float = 5.0) -> Any:
        proc = self._proc
        if proc is None or proc.stdin is None or not self.running:
            raise DeviceError("UR simulator process is not running: call start() first")
        proc.stdin.write(json.dumps({"method": method, "args": [_jsonable(a) for a in args]}))
        proc.stdin.write("\n")
        proc.stdin.flush()
        msg = self._read(timeout_s, method)
        if "error" in msg:
            raise DeviceError(f"UR simulator {method}: {msg['error']}")
        return msg.get("ok")

    # convenience wrappers for tests and the demo
    def freeze(self, frozen: bool = True) -> None:
        self.call("freeze", frozen)

    def protective_stop(self) -> None:
        self.call("protective_stop")

    def unlock_protective_stop(self) -> None:
        self.call("unlock_protective_stop")

    def tcp_pose(self) -> np.ndarray:
        return np.asarray(self.call("tcp_pose"))

    def tcp_speed(self) -> np.ndarray:
        return np.asarray(self.call("tcp_speed"))

    def mode_name(self) -> str:
        return self.call("mode_name")

    def commands_seen(self) -> list[int]:
        return self.call("commands_seen")

    def stats(self) -> dict[str, Any]:
        return self.call("stats")

    def stop(self, timeout_s: float = 5.0) -> None:
        """Close the simulator's sockets and end the process."""
        proc = self._proc
        if proc is None:
            return
        try:
            if self.running:
                self.call("stop", timeout_s=timeout_s)
        except (DeviceError, OSError, ValueError) as e:
            log.debug("UR simulator stop: %s", e)
        finally:
            self._close(timeout_s)

    def kill(self) -> None:
        """Take the controller away at once (SIGKILL): no goodbye on any socket."""
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
        self._close(5.0)

    def _close(self, timeout_s: float) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        for f in (proc.stdin, proc.stdout):
            if f is not None:
                with contextlib.suppress(OSError):
                    f.close()
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=2)

    def __enter__(self) -> URSimProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
