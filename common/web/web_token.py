"""The secrets that open the local web sockets: the operator's page and the video signalling.

Any process on a machine can reach its loopback ports, so a port bound to
127.0.0.1 is not private: another user, or a browser tab on another site,
could steer the arm through the dashboard or watch the lab through the
video server. Each of them asks for a token, a random secret of the run (or
a fixed one from the config, for scripted setups), given as ``?token=`` in
the URL, an ``Authorization: Bearer`` header, or (the page) a cookie. Only
the standard library: the robot PC's video server and the operator's page
both use it.
"""

from __future__ import annotations

import hmac
import os
import secrets
from collections.abc import Mapping
from pathlib import Path
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

from common.errors import ConfigError

TOKEN_PARAM = "token"
MIN_TOKEN_CHARS = 16  # a fixed token shorter than this is guessable by a local process


def new_token() -> str:
    """192 random bits, URL-safe."""
    return secrets.token_urlsafe(24)


def check_token(token: str, where: str) -> str:
    """``token`` when it is long enough and URL-safe; a ``ConfigError`` naming ``where`` if not."""
    if len(token) < MIN_TOKEN_CHARS or any(c.isspace() or c in "&#?;,\"'" for c in token):
        raise ConfigError(
            f"{where}: a token needs at least {MIN_TOKEN_CHARS} characters and no spaces or "
            "&#?;,\"' (leave it empty for a fresh random one each run)"
        )
    return token


def configured_token(token: str, env_var: str, where: str) -> str:
    """The config's token, else ``$env_var``'s, else a fresh one for this run."""
    if token:
        return check_token(token, where)
    from_env = os.environ.get(env_var, "")
    if from_env:
        return check_token(from_env, f"${env_var}")
    return new_token()


def token_file(path: Path, where: str) -> str:
    """The token in ``path``, which is created (mode 0600) with a fresh one when missing."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        pass
    except OSError as e:
        raise ConfigError(f"{where} {path}: cannot create it: {e}") from None
    else:
        with os.fdopen(fd, "w") as f:
            f.write(new_token() + "\n")
    try:
        mode = path.stat().st_mode
        text = path.read_text().strip()
    except OSError as e:
        raise ConfigError(f"{where} {path}: cannot read it: {e}") from None
    if mode & 0o077:
        raise ConfigError(f"{where} {path} is open to other users: chmod 600 {path}")
    return check_token(text, f"{where} {path}")


def matches(given: str | None, token: str) -> bool:
    """Constant-time: a local process cannot learn the token by timing refusals."""
    return given is not None and hmac.compare_digest(given.encode(), token.encode())


def from_query(target: str) -> str | None:
    """The ``token`` in a request target's query (``/ws?token=...``), if any."""
    for key, value in parse_qsl(urlsplit(target).query, keep_blank_values=True):
        if key == TOKEN_PARAM:
            return value
    return None


def from_bearer(headers: Mapping[str, str]) -> str | None:
    value = headers.get("Authorization") or ""
    scheme, _, credentials = value.partition(" ")
    return credentials.strip() if scheme.lower() == "bearer" else None


def bearer_header(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def with_token(url: str, token: str) -> str:
    """``url`` with ``?token=`` set (any earlier token replaced)."""
    parts = urlsplit(url)
    query = [(k, v) for k, v in parse_qsl(parts.query, keep_blank_values=True) if k != TOKEN_PARAM]
    query.append((TOKEN_PARAM, token))
    return urlunsplit(parts._replace(query=urlencode(query)))


def without_token(url: str) -> str:
    """``url`` without its token: what a log line or an error message may show."""
    parts = urlsplit(url)
    query = [(k, v) for k, v in parse_qsl(parts.query, keep_blank_values=True) if k != TOKEN_PARAM]
    return urlunsplit(parts._replace(query=urlencode(query)))
