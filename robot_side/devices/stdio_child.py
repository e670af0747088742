"""A simulator in a child process, asked questions over its stdin/stdout.

Simulators whose clients are C++ libraries run in a process of their own:
ur-rtde's constructors hold the GIL while they wait for the controller, so a
simulator served by threads of the same interpreter could never answer them.
A process also makes "the controller vanished" real (:meth:`StdioChild.kill`)
and gives physics a core of its own.

Why ``subprocess`` and not ``multiprocessing``: spawn re-imports the caller's
main script, which breaks any script without a ``__main__`` guard. The child
(``python -m <module> --stdio --config-json ...``) writes one ready line,
then answers one JSON line per JSON request line; it exits when its stdin
closes, so a crashed parent leaves no server behind.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Collection
from typing import IO, Any

import numpy as np

from common.config.typed import to_dict
from common.errors import DeviceError, DeviceTimeoutError

log = logging.getLogger(__name__)


def jsonable(value: Any) -> Any:
    """NumPy arrays and scalars as the plain values JSON carries."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def serve_stdio(
    target: Any,
    methods: Collection[str],
    ready: Any,
    stdin: IO[str],
    stdout: IO[str],
    on_exit: Callable[[], None],
) -> None:
    """The child's side: announce ``ready``, then call ``target``'s ``methods`` on request.

    Runs until stdin closes or "stop" arrives, then calls ``on_exit``. A
    method's exception goes back to the parent, which raises it.
    """

    def reply(obj: dict[str, Any]) -> None:
        stdout.write(json.dumps(obj) + "\n")
        stdout.flush()

    reply({"ready": ready})
    try:
        for line in stdin:
            req = json.loads(line)
            method, args = req.get("method"), req.get("args", [])
            if method == "stop":
                break
            try:
                if method not in methods:
                    raise AttributeError(f"no remote method {method!r}")
                reply({"ok": jsonable(getattr(target, method)(*args))})
            except Exception as e:  # reported to the parent, which raises it
                reply({"error": f"{type(e).__name__}: {e}"})
    finally:
        on_exit()
    with contextlib.suppress(OSError):  # the parent may have stopped listening
        reply({"ok": None})


class StdioChild:
    """The parent's side: start the child, call its methods, stop or kill it.

    ``what`` names the child in every error ("UR simulator", "lab world").
    """

    def __init__(
        self,
        module: str,
        config: Any,
        what: str,
        log_level: int,
        nice: int | None = None,
        env: dict[str, str] | None = None,
    ) -> None:
        self.module = module
        self.config = config
        self.what = what
        self.log_level = log_level
        self.nice = nice
        self.env = dict(env or {})  # over this process's environment
        self._proc: subprocess.Popen[str] | None = None
        self._lock = threading.Lock()  # one request in flight: the pipe is a conversation

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def how_it_ended(self) -> str:
        """ "exit code N" or "killed by SIGNAME" once the child is gone; "" while it runs (or
        was never started, or was closed by this side)."""
        code = None if self._proc is None else self._proc.poll()
        if code is None:
            return ""
        if code < 0:
            with contextlib.suppress(ValueError):
                return f"killed by {signal.Signals(-code).name}"
            return f"killed by signal {-code}"
        return f"exit code {code}"

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def start_child(self, timeout_s: float) -> Any:
        """Start the child and return what its ready line announced."""
        cmd = [
            sys.executable,
            "-m",
            self.module,
            "--stdio",
            "--config-json",
            json.dumps(to_dict(self.config)),
            "--log-level",
            str(self.log_level),
        ]
        env = dict(os.environ, PYTHONUNBUFFERED="1", **self.env)
        self._proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
        )
        if self.nice is not None:  # where this process may raise it (root, CAP_SYS_NICE)
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, self._proc.pid, self.nice)
        try:
            msg = self._read(self._proc, timeout_s, "start")
        except DeviceError:
            self.kill()
            raise
        if "ready" not in msg:
            self.kill()
            raise DeviceError(f"{self.what} failed to start: {msg.get('error', msg)}")
        return msg["ready"]

    def _read(self, proc: subprocess.Popen, timeout_s: float, what: str) -> dict[str, Any]:
        """One reply from ``proc``, the process the request went to.

        ``kill()`` does not wait for a call under way (a kill is meant to be
        at once): it may close this pipe mid-read, which is the child gone.
        """
        try:
            ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
            if not ready:
                raise DeviceTimeoutError(f"{self.what} did not answer {what} in {timeout_s:.0f} s")
            line = proc.stdout.readline()
        except (ValueError, OSError) as e:  # the pipe closed under us by kill()
            raise DeviceError(f"{self.what} process was stopped during {what}: {e}") from e
        if not line:
            raise DeviceError(
                f"{self.what} process exited during {what} (code {proc.poll()}); "
                "see its log on stderr"
            )
        return json.loads(line)

    def call(self, method: str, *args: Any, timeout_s: float = 5.0) -> Any:
        with self._lock:
            proc = self._proc
            if proc is None or proc.stdin is None or not self.running:
                raise DeviceError(f"{self.what} process is not running: call start() first")
            request = {"method": method, "args": [jsonable(a) for a in args]}
            try:
                proc.stdin.write(json.dumps(request) + "\n")
                proc.stdin.flush()
            except (ValueError, OSError) as e:  # killed meanwhile: its pipe is closed
                raise DeviceError(f"{self.what} process was stopped before {method}: {e}") from e
            msg = self._read(proc, timeout_s, method)
        if "error" in msg:
            raise DeviceError(f"{self.what} {method}: {msg['error']}")
        return msg.get("ok")

    def stop(self, timeout_s: float = 5.0) -> None:
        """Ask the child to close its servers, then end the process."""
        if self._proc is None:
            return
        try:
            if self.running:
                self.call("stop", timeout_s=timeout_s)
        except (DeviceError, OSError, ValueError) as e:
            log.debug("%s stop: %s", self.what, e)
        finally:
            self._close(timeout_s)

    def kill(self) -> None:
        """End the child at once (SIGKILL): no goodbye on any socket."""
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
