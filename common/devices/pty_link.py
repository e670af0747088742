"""A pseudo-terminal behind a stable name: the wire a simulated serial device sits on.

The name is a symlink to the current pty slave, like /dev/serial/by-id:
unplugging closes the pty and removes the name, plugging in again makes a new
pty behind the same name, so a driver's reopen-by-name is tested as on a USB
replug. The slave fd stays open here, or the master reads EIO whenever the
driver closes its end and the line settings reset.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import termios
from pathlib import Path


class PtyLink:
    def __init__(self, name: str, link_dir: Path | None = None) -> None:
        if link_dir is None:
            self._own_dir: str | None = tempfile.mkdtemp(prefix=f"deepxpalm-{name}-")
            self.path = Path(self._own_dir) / name
        else:
            link_dir.mkdir(parents=True, exist_ok=True)
            self._own_dir = None
            self.path = link_dir / name
        self.master: int | None = None
        self.slave: int | None = None
        self.slave_path: str | None = None

    @property
    def plugged_in(self) -> bool:
        return self.master is not None

    def plug(self) -> None:
        master, slave = os.openpty()
        os.set_blocking(master, False)  # a stalled reader must never stall the device
        attrs = termios.tcgetattr(slave)
        attrs[0] = attrs[1] = attrs[3] = 0  # raw: no echo, no CR/LF translation
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        self.master, self.slave, self.slave_path = master, slave, os.ttyname(slave)
        tmp = self.path.with_name(self.path.name + ".new")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        tmp.symlink_to(self.slave_path)
        os.replace(tmp, self.path)

    def unplug(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        for fd in (self.master, self.slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.master = self.slave = None

    def close(self) -> None:
        self.unplug()
        if self._own_dir is not None:
            with contextlib.suppress(OSError):
                os.rmdir(self._own_dir)
            self._own_dir = None

    def line_speed_is(self, baud: int) -> bool:
        """Does the driver's end run at ``baud``? (The master sees the slave's settings.)"""
        want = getattr(termios, f"B{baud}", None)
        if want is None or self.master is None:
            return True
        try:
            return termios.tcgetattr(self.master)[5] == want
        except termios.error:
            return True

    def write(self, data: bytes) -> int:
        """Write what fits; bytes nobody reads are lost, as on a real wire."""
        if self.master is None:
            return 0
        try:
            return os.write(self.master, data)
        except (BlockingIOError, OSError):
            return 0
