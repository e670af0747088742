"""What a device can check about its hardware before its driver opens it.

``deepxpalm doctor`` asks every configured device for ``preflight()``
findings; a device kind answers with the helpers here (a serial port that
must exist and be openable, TCP ports that must accept a connection), so
the doctor never needs to know which kinds have a port, a host or a URCap.
Each finding says what is wrong and what to do about it.
"""

from __future__ import annotations

import glob
import os
import pwd
import socket
import stat
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

PASS, WARN, FAIL, SKIP = "pass", "warn", "fail", "skip"


@dataclass(frozen=True)
class Finding:
    """A problem found before the driver opened: what, and the fix."""

    status: str  # warn | fail (pass and skip are the doctor's own lines)
    detail: str
    fix: str = ""


@dataclass(frozen=True)
class PreflightContext:
    """What a device's preflight needs to know about the run and the machine."""

    #: the config table the device came from ("robot.tactile"), named in fixes
    where: str = "device"
    tcp_timeout_s: float = 1.0
    #: the user the systemd units run as: it, too, must be able to open a port
    service_user: str | None = None
    #: the groups the units add to that user (SupplementaryGroups=)
    service_groups: tuple[str, ...] = ()


# ------------------------------------------------------------------ users, files
def user_named(name: str | None) -> pwd.struct_passwd | None:
    """None for no name or a user this machine does not have."""
    if name is None:
        return None
    try:
        return pwd.getpwnam(name)
    except KeyError:
        return None


def current_user_name() -> str:
    return pwd.getpwuid(os.geteuid()).pw_name


def groups_of(user: pwd.struct_passwd, extra: Iterable[str] = ()) -> set[int]:
    """The user's groups plus ``extra``: what a unit's SupplementaryGroups= gives it."""
    import grp

    extra = tuple(extra)
    gids = {user.pw_gid}
    for g in grp.getgrall():
        if user.pw_name in g.gr_mem or g.gr_name in extra:
            gids.add(g.gr_gid)
    return gids


def permits(st: os.stat_result, uid: int, gids: set[int], want: int) -> bool:
    """Whether uid/gids get ``want`` (an R_OK|W_OK mask) on a file with this stat."""
    if uid == 0:
        return True
    if st.st_uid == uid:
        bits = (st.st_mode >> 6) & 7
    elif st.st_gid in gids:
        bits = (st.st_mode >> 3) & 7
    else:
        bits = st.st_mode & 7
    return (bits & want) == want


def owner_text(st: os.stat_result) -> str:
    """``user:group -rw-------``, the way ``ls -l`` would show who may open it."""
    import grp

    try:
        user = pwd.getpwuid(st.st_uid).pw_name
    except KeyError:
        user = str(st.st_uid)
    try:
        group = grp.getgrgid(st.st_gid).gr_name
    except KeyError:
        group = str(st.st_gid)
    return f"{user}:{group} {stat.filemode(st.st_mode)}"


def service_user_can(
    st: os.stat_result, context: PreflightContext, want: int
) -> tuple[bool, pwd.struct_passwd | None]:
    """(allowed, the service user); allowed when there is no such user on this machine."""
    service = user_named(context.service_user)
    if service is None:
        return True, None
    return permits(st, service.pw_uid, groups_of(service, context.service_groups), want), service


def cmdline(pid: int) -> str:
    """A process by its command line, for naming who holds a port or a device."""
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return "?"
    return raw.replace(b"\0", b" ").decode(errors="replace").strip()


def processes_holding(targets: set[str], skip_self: bool = True) -> list[tuple[int, str]]:
    """(pid, command line) of processes with an fd whose link is one of ``targets``."""
    found = []
    if not targets:
        return found
    for fd_dir in glob.glob("/proc/[0-9]*/fd"):
        pid = int(fd_dir.split("/")[2])
        if skip_self and pid == os.getpid():
            continue
        try:
            fds = os.listdir(fd_dir)
        except OSError:
            continue
        for fd in fds:
            try:
                if os.readlink(f"{fd_dir}/{fd}") in targets:
                    found.append((pid, cmdline(pid)))
                    break
            except OSError:
                continue
    return found


# ------------------------------------------------------------------ network
def tcp_probe(host: str, port: int, timeout_s: float) -> str | None:
    """None when something accepts a TCP connection; otherwise why not, in words."""
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return None
    except ConnectionRefusedError:
        return f"{host}:{port} refused the connection (the host is up; nothing listens there)"
    except TimeoutError:
        return (
            f"no answer from {host}:{port} within {timeout_s:.1f} s (wrong address, host off, "
            "cable, or a firewall dropping packets)"
        )
    except socket.gaierror as e:
        return f"cannot resolve {host!r}: {e.strerror}"
    except OSError as e:
        return f"{host}:{port}: {e.strerror or e}"


def tcp_findings(
    host: str, ports: Iterable[int], context: PreflightContext, hint: str = ""
) -> list[Finding]:
    """One failure naming every port of ``host`` that does not accept a connection.

    ``hint`` is what the device kind adds to the fix (where to look on the
    controller, which add-on must run there).
    """
    problems = [
        p for p in (tcp_probe(host, n, context.tcp_timeout_s) for n in ports) if p is not None
    ]
    if not problems:
        return []
    fix = (
        f"check {context.where}.host, the Ethernet cable and this PC's address on the "
        f"robot's subnet (`ping {host}`)"
    )
    return [Finding(FAIL, "; ".join(problems), fix + (f"; {hint}" if hint else ""))]


# ------------------------------------------------------------------ serial
def serial_findings(port: str, baudrate: int | None, context: PreflightContext) -> list[Finding]:
    """Is ``port`` there, openable by us and by the service user, free, and at ``baudrate``?"""
    where = context.where
    try:
        st = os.stat(port)
    except FileNotFoundError:
        dangling = os.path.islink(port)
        return [
            Finding(
                FAIL,
                f"serial port {port} does not exist"
                + (" (the udev link is there but its device is gone)" if dangling else ""),
                "plug the device in and power it; `ls -l /dev/serial/by-id/` lists what is "
                f"connected; install deploy/udev/99-deepxpalm.rules with its serial number "
                f"(docs/bring-up.md) or set {where}.port to its /dev/serial/by-id/ name",
            )
        ]
    if not stat.S_ISCHR(st.st_mode):
        return [
            Finding(
                FAIL,
                f"{port} is not a character device (a regular file or directory?)",
                f"set {where}.port to the serial device",
            )
        ]
    if not os.access(port, os.R_OK | os.W_OK):
        return [
            Finding(
                FAIL,
                f"no permission to open {port} ({owner_text(st)}) as {current_user_name()}",
                "add the user to dialout (`sudo usermod -aG dialout $USER`, then log in again); "
                "the udev rules give the device GROUP=dialout MODE=0660",
            )
        ]
    allowed, _service = service_user_can(st, context, os.R_OK | os.W_OK)
    if not allowed:
        return [
            Finding(
                FAIL,
                f"the service user {context.service_user} (with dialout) cannot open {port} "
                f"({owner_text(st)})",
                "install deploy/udev/99-deepxpalm.rules (GROUP=dialout, MODE=0660) and replug",
            )
        ]
    users = processes_holding({os.path.realpath(port)})
    if users:
        pid, cmd = users[0]
        return [
            Finding(
                WARN,
                f"{port} is open in pid {pid} ({cmd[:80]}); not touching it",
                "if that is the node, it owns the device: stop it (`systemctl stop "
                "deepxpalm-robot` / `deepxpalm-operator`) for a full check; otherwise stop "
                "that process (two readers corrupt each other's bytes)",
            )
        ]
    try:
        import serial

        with serial.Serial(port, baudrate=baudrate or 9600, timeout=0):
            pass
    except (OSError, ValueError) as e:  # SerialException is an OSError
        return [
            Finding(
                FAIL,
                f"{port} exists but does not open at {baudrate} baud: {e}",
                "check the adapter (dmesg | tail), and that no other program holds it",
            )
        ]
    return []
