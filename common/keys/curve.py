"""CURVE on every link that leaves the machine (pyzmq's "ironhouse" pattern).

The robot is the CURVE server on both of its sockets: it holds its own key
pair and a directory of the operator public keys it accepts; a peer whose
key is not there never completes the handshake, so it reads nothing and
commands nothing. The operator is a CURVE client that knows the robot's
public key. Keys are pyzmq certificate files (``NAME.key`` public,
``NAME.key_secret`` secret), made by ``deepxpalm keys``.

Plain TCP is allowed on loopback (the demo); to any other address it is
refused unless the config says ``allow_insecure = true``, and then warned.
"""

from __future__ import annotations

import ipaddress
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

import zmq
import zmq.auth

from common.config.typed import param
from common.errors import ConfigError, LinkError
from common.logs import BurstLog

log = logging.getLogger(__name__)


@dataclass
class SecurityConfig:
    mode: Literal["plain", "curve"] = param(
        "plain", "curve encrypts and authenticates; plain only on loopback unless allow_insecure"
    )
    secret_key_file: Path | None = param(
        None, "this node's key pair: the NAME.key_secret file from `deepxpalm keys generate`"
    )
    server_public_key_file: Path | None = param(
        None, "operator only: the robot's NAME.key public key file"
    )
    authorized_keys_dir: Path | None = param(
        None, "robot only: directory of operator public keys (*.key) allowed to connect"
    )
    allow_insecure: bool = param(
        False, "allow plain TCP to a non-loopback address (the stream is then readable by anyone)"
    )


def is_loopback_endpoint(endpoint: str) -> bool:
    """inproc/ipc, and tcp to 127.0.0.0/8, ::1 or localhost."""
    if endpoint.startswith(("inproc://", "ipc://")):
        return True
    host = urlsplit(endpoint).hostname or ""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # "*", an interface name or a DNS name: it may leave the machine


def check_endpoint(endpoint: str, security: SecurityConfig) -> None:
    """Refuse plain TCP off this machine unless explicitly allowed."""
    if security.mode == "curve" or is_loopback_endpoint(endpoint):
        return
    if not security.allow_insecure:
        raise LinkError(
            f"{endpoint} may leave this machine but security.mode is 'plain': set "
            "security.mode = 'curve' with keys from `deepxpalm keys` (or, on a trusted "
            "network only, security.allow_insecure = true)"
        )
    log.warning("plain TCP on %s: anyone on the path can read and inject messages", endpoint)


def _load_keys(path: Path | None, what: str, need_secret: bool) -> tuple[bytes, bytes | None]:
    if path is None:
        raise ConfigError(f"security.mode = 'curve' needs {what}")
    try:
        public, secret = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as e:
        raise ConfigError(f"cannot read {what} {path}: {e}") from None
    if need_secret and secret is None:
        raise ConfigError(f"{path} holds no secret key; use the NAME.key_secret file")
    return public, secret


def server_options(security: SecurityConfig) -> dict[int, Any]:
    """Socket options for the robot's sockets."""
    if security.mode != "curve":
        return {}
    public, secret = _load_keys(security.secret_key_file, "security.secret_key_file", True)
    return {zmq.CURVE_SERVER: 1, zmq.CURVE_PUBLICKEY: public, zmq.CURVE_SECRETKEY: secret}


def client_options(security: SecurityConfig) -> dict[int, Any]:
    """Socket options for the operator's sockets."""
    if security.mode != "curve":
        return {}
    public, secret = _load_keys(security.secret_key_file, "security.secret_key_file", True)
    server, _ = _load_keys(
        security.server_public_key_file, "security.server_public_key_file", False
    )
    return {
        zmq.CURVE_SERVERKEY: server,
        zmq.CURVE_PUBLICKEY: public,
        zmq.CURVE_SECRETKEY: secret,
    }


class _Allowlist:
    """The operator keys a robot accepts; every refusal is counted and logged (rate-limited).

    Given to pyzmq's authenticator as its CURVE credentials provider (its
    public callback hook), so a refused handshake is seen here rather than
    only in pyzmq's debug log.
    """

    MAX_REMEMBERED = 32

    def __init__(self, directory: Path) -> None:
        self.directory = Path(directory)
        self.keys: frozenset[bytes] = frozenset()
        self.refused = 0
        #: z85 public keys refused so far, oldest first (at most MAX_REMEMBERED)
        self.refused_keys: list[str] = []
        self._log = BurstLog(log, "CURVE handshake refused")
        self.load()

    def load(self) -> None:
        keys = set()
        for path in sorted(self.directory.glob("*.key")):
            try:
                public, _ = zmq.auth.load_certificate(path)
            except (OSError, ValueError) as e:
                log.error("cannot read operator key %s: %s; it is not allowed", path, e)
                continue
            keys.add(public)
        if not keys:
            log.warning("no operator key in %s: nobody can connect", self.directory)
        self.keys = frozenset(keys)

    def callback(self, domain: str, z85_client_key: bytes) -> bool:
        if z85_client_key in self.keys:
            return True
        self.refused += 1
        key = z85_client_key.decode("ascii", "replace")
        if key not in self.refused_keys:
            self.refused_keys.append(key)
            del self.refused_keys[: -self.MAX_REMEMBERED]
        self._log(f"key {key} is not in {self.directory} (see `deepxpalm keys allow`)")
        return False


class Authenticator:
    """The robot's allowlist: only operator keys in ``authorized_keys_dir`` get in."""

    def __init__(self, ctx: zmq.Context, security: SecurityConfig) -> None:
        self._auth = None
        self._allowlist: _Allowlist | None = None
        if security.mode != "curve":
            return
        directory = security.authorized_keys_dir
        if directory is None or not Path(directory).is_dir():
            raise ConfigError(
                f"security.authorized_keys_dir {directory} is not a directory of operator "
                "public keys (see `deepxpalm keys allow`)"
            )
        from zmq.auth.thread import ThreadAuthenticator

        self._allowlist = _Allowlist(Path(directory))
        self._auth = ThreadAuthenticator(ctx, log=logging.getLogger("deepxpalm.auth"))
        self._auth.start()
        self._auth.configure_curve_callback(domain="*", credentials_provider=self._allowlist)

    @property
    def refused(self) -> int:
        """CURVE handshakes refused because the client's key is not allowed."""
        return 0 if self._allowlist is None else self._allowlist.refused

    @property
    def refused_keys(self) -> list[str]:
        """The z85 public keys refused so far (the newest few)."""
        return [] if self._allowlist is None else list(self._allowlist.refused_keys)

    def reload(self, security: SecurityConfig) -> None:
        """Re-read the allowlist (after `deepxpalm keys allow`)."""
        if self._allowlist is not None:
            self._allowlist.directory = Path(security.authorized_keys_dir)
            self._allowlist.load()

    def stop(self) -> None:
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
