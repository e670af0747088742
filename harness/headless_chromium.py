"""Drive Debian's chromium headless over the DevTools protocol, with no extra dependency.

Chromium is started with ``--remote-debugging-port=0`` and writes the port it
chose to ``DevToolsActivePort`` in its profile directory; the page's DevTools
WebSocket is then driven with the ``websockets`` sync client. Every wait has a
timeout and ``close()`` kills the browser's whole process group, so a test
never hangs on a browser.

Also a tool: ``python -m harness.headless_chromium URL OUT.png``
screenshots a page (docs/img/dashboard.png was made this way).
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Callable
from contextlib import ExitStack, suppress
from pathlib import Path
from typing import Any

from websockets.sync.client import connect

from deploy.units.policy import share_group_weight
from deploy.units.process import stop
from harness.processes import in_session, raise_threads

CHROMIUM = "/usr/bin/chromium"
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--disable-default-apps",
    "--mute-audio",
    # a page no window shows counts as hidden: chromium then runs its renderer at nice +5 and
    # its timers at most once a second (the jog's 20 Hz renewals, the page's polls); a user's
    # page is in view
    "--disable-renderer-backgrounding",
    "--disable-background-timer-throttling",
    "--disable-backgrounding-occluded-windows",
    "--remote-debugging-address=127.0.0.1",
    "--remote-debugging-port=0",
)


def chromium_path() -> str | None:
    if os.access(CHROMIUM, os.X_OK):
        return CHROMIUM
    return shutil.which("chromium")


#: what a page is given to answer or to show something, unless the test bounds it itself (a
#: product limit, such as the STALE badge within the staleness, is always passed explicitly):
#: beside two deployments on two saturated cores a page once answered nothing for over 5 s
PAGE_WAIT_S = 15.0
#: a poll's evaluation may take what is left of its wait, and at least this: a renderer held
#: up by a busy machine answered one poll after more than 5 s, inside the wait's 10
_POLL_ANSWER_S = 1.0

#: what DevTools answers an evaluation whose page navigated away meanwhile
_NAVIGATED = (
    "Inspected target navigated or closed",
    "Execution context was destroyed",
    "Cannot find context with specified id",
)


class BrowserError(RuntimeError):
    pass


class Chromium:
    """One headless chromium with one page; a context manager."""

    def __init__(
        self,
        width: int = 1280,
        height: int = 900,
        timeout_s: float = 60.0,
        flags: tuple[str, ...] = (),
    ) -> None:
        """``flags``: more command-line switches (``--host-resolver-rules=...``).

        ``timeout_s`` bounds chromium's own start (its DevTools port, its first page): no
        product limit, so it is generous; beside two busy loops and three deployments the
        browser took over 15 s to open its port."""
        exe = chromium_path()
        if exe is None:
            raise BrowserError(
                "chromium is not installed (scripts/install-test-system-packages.sh)"
            )
        self.profile = Path(tempfile.mkdtemp(prefix="dxp-chromium-"))
        self.log_path = self.profile / "chromium.log"
        self._log = self.log_path.open("wb")
        self.proc = subprocess.Popen(
            [
                exe,
                *FLAGS,
                *flags,
                f"--user-data-dir={self.profile}",
                f"--window-size={width},{height}",
                "about:blank",
            ],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        # a session of its own is a scheduling group of its own at nice 0: beside the test
        # lanes' group (-20) every page process together got a 87th of a busy machine and
        # answered nothing for 15 s; a person's browser weighs as much as the work beside it
        share_group_weight(os.getpid(), self.proc.pid)
        self.ws = None
        self._stack = ExitStack()
        self._id = 0
        self.events: list[dict[str, Any]] = []
        try:
            port = self._wait_port(timeout_s)
            self.ws = self._stack.enter_context(
                # close_timeout: a browser that never answers the closing handshake (seen
                # after a page on another origin) held every close() for websockets' 10 s
                # open_timeout: the DevTools handshake is part of the browser's start (a busy
                # machine held it past websockets' default 10 s)
                connect(
                    self._page_ws(port, timeout_s),
                    max_size=64 * 1024 * 1024,
                    open_timeout=timeout_s,
                    close_timeout=1.0,
                )
            )
            for domain in ("Page", "Runtime", "Network"):  # a starting browser, on a busy
                self.call(f"{domain}.enable", timeout_s=timeout_s)  # machine: its start's time
            self.call(
                "Emulation.setDeviceMetricsOverride",
                width=width,
                height=height,
                deviceScaleFactor=1,
                mobile=False,
            )
        except BaseException:
            self.close()
            raise

    def _wait_port(self, timeout_s: float) -> int:
        marker = self.profile / "DevToolsActivePort"
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise BrowserError(f"chromium exited with {self.proc.returncode}: {self._tail()}")
            try:
                return int(marker.read_text().split()[0])
            except (FileNotFoundError, IndexError, ValueError):
                time.sleep(0.05)
        raise BrowserError(f"chromium did not open its DevTools port in {timeout_s} s")

    def _page_ws(self, port: int, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                    pages = [t for t in json.load(r) if t.get("type") == "page"]
            except OSError:  # still starting up (a loaded machine is slow to answer)
                pages = []
            if pages:
                return pages[0]["webSocketDebuggerUrl"]
            time.sleep(0.1)
        raise BrowserError("chromium opened no page")

    def _tail(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")[-2000:]

    # ----------------------------------------------------------- protocol
    def call(self, method: str, timeout_s: float = 10.0, **params: Any) -> dict[str, Any]:
        """One DevTools command; events that arrive meanwhile are kept in ``events``."""
        assert self.ws is not None
        self._id += 1
        ident = self._id
        self.ws.send(json.dumps({"id": ident, "method": method, "params": params}))
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError(f"{method}: no answer in {timeout_s} s")
            try:
                msg = json.loads(self.ws.recv(timeout=left))
            except TimeoutError:
                raise BrowserError(f"{method}: no answer in {timeout_s} s") from None
            if msg.get("id") == ident:
                if "error" in msg:
                    raise BrowserError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            if "method" in msg:
                self.events.append(msg)

    def navigate(self, url: str, timeout_s: float = 20.0) -> None:
        """Open ``url`` and wait until it has loaded (20 s: beside two busy loops and the
        deployment lane, a second browser started at the same time took over 10)."""
        self.call("Page.navigate", url=url)
        self.wait_for("document.readyState === 'complete'", timeout_s)
        self.at_our_priority()

    def at_our_priority(self) -> list[int]:
        """The browser's threads at this process's niceness at least; the thread ids raised.

        Chromium sets its renderers' niceness itself (0 for a page in view) whatever it
        was started with: inside the test lanes that put the page below the tests (-5)
        and the nodes (-10), and beside other deployments on a saturated machine a page
        took over 5 s to show a reply its server had sent. A person's browser competes
        with what else runs on the operator's PC as an equal; so does the page here.
        Where raising a priority is not allowed, the page keeps the one it has.
        """
        ours = os.nice(0)
        return [tid for pid in in_session(self.proc.pid) for tid in raise_threads(pid, ours)]

    def evaluate(self, expression: str, timeout_s: float = PAGE_WAIT_S) -> Any:
        res = self.call(
            "Runtime.evaluate",
            timeout_s=timeout_s,
            expression=expression,
            returnByValue=True,
            awaitPromise=True,
        )
        if "exceptionDetails" in res:
            raise BrowserError(f"{expression!r} threw: {res['exceptionDetails']}")
        return res["result"].get("value")

    def wait_for(
        self, expression: str, timeout_s: float = PAGE_WAIT_S, poll_s: float = 0.03
    ) -> Any:
        """Evaluate until truthy; the last value (or the failure) in the error on timeout."""
        return self.wait_until(expression, bool, timeout_s, poll_s)

    def wait_until(
        self,
        expression: str,
        predicate: Callable[[Any], bool],
        timeout_s: float = PAGE_WAIT_S,
        poll_s: float = 0.03,
    ) -> Any:
        """Evaluate until ``predicate(value)`` holds in Python; the last value on timeout.

        A poll that meets a navigation (the page the expression was sent to went away under
        it, as when the expression waits for the next page) is tried again on the next one.
        """
        deadline = time.monotonic() + timeout_s
        value: Any = None
        while (left := deadline - time.monotonic()) > 0:
            try:
                value = self.evaluate(expression, timeout_s=max(left, _POLL_ANSWER_S))
            except BrowserError as e:
                if not any(m in str(e) for m in _NAVIGATED):
                    raise
                value = None
            else:
                if predicate(value):
                    return value
            time.sleep(poll_s)
        raise BrowserError(f"timed out after {timeout_s} s waiting on {expression!r} ({value!r})")

    def click(self, selector: str, timeout_s: float = PAGE_WAIT_S) -> None:
        """A real mouse click at the element's centre, as a person would: scrolled into view,
        and only once nothing else (a banner that just appeared, a moving layout) covers it.
        """
        js = (
            f"(() => {{ const el = document.querySelector({json.dumps(selector)});"
            " if (!el) return null; el.scrollIntoView({block: 'center', inline: 'center'});"
            " const r = el.getBoundingClientRect();"
            " const x = r.x + r.width / 2, y = r.y + r.height / 2;"
            " const hit = document.elementFromPoint(x, y);"
            " return [x, y, hit !== null && (hit === el || el.contains(hit))]; })()"
        )
        deadline = time.monotonic() + timeout_s
        while True:
            box = self.evaluate(js)
            if box is not None and box[2]:
                break
            if time.monotonic() > deadline:
                what = "not on the page" if box is None else "covered by another element"
                raise BrowserError(f"cannot click {selector}: {what} for {timeout_s} s")
            time.sleep(0.05)
        for kind in ("mousePressed", "mouseReleased"):
            self.call(
                "Input.dispatchMouseEvent",
                type=kind,
                x=box[0],
                y=box[1],
                button="left",
                clickCount=1,
            )

    def screenshot(self, path: Path) -> None:
        data = self.call("Page.captureScreenshot", format="png")["data"]
        Path(path).write_bytes(base64.b64decode(data))

    def requested_urls(self) -> list[str]:
        return [
            e["params"]["request"]["url"]
            for e in self.events
            if e.get("method") == "Network.requestWillBeSent"
        ]

    def page_errors(self) -> list[str]:
        return [
            json.dumps(e["params"])[:500]
            for e in self.events
            if e.get("method") == "Runtime.exceptionThrown"
            or (
                e.get("method") == "Runtime.consoleAPICalled"
                and e["params"].get("type") in ("error", "assert")
            )
        ]

    # ----------------------------------------------------------- lifetime
    def close(self) -> None:
        with suppress(Exception):  # the browser may already be gone
            self._stack.close()
        self.ws = None
        stop(self.proc, 5, group=True)  # the browser and its helper processes
        self._log.close()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: list[str]) -> int:
    if not 2 <= len(argv) <= 5:
        print(
            "usage: headless_chromium.py URL OUT.png [WAIT_S [UNTIL_JS [WIDTHxHEIGHT]]]",
            file=sys.stderr,
        )
        return 2
    url, out = argv[0], Path(argv[1])
    wait_s = float(argv[2]) if len(argv) >= 3 else 3.0
    width, height = (int(v) for v in argv[4].split("x")) if len(argv) == 5 else (1280, 760)
    with Chromium(width=width, height=height) as browser:
        browser.navigate(url)
        time.sleep(wait_s)
        if len(argv) >= 4 and argv[3]:
            browser.wait_for(argv[3], timeout_s=30)
            time.sleep(0.2)
        browser.screenshot(out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
