"""Ed25519 signatures end to end, operator to robot (docs/security.md).

CURVE or TLS protects each hop; a router in the middle terminates the
connections and sees every message in clear. So the operator also signs what
it sends with a key only it holds, and the robot checks the signature
against its roster: a router (or anything else on the path) can then drop or
delay a command, never make or change one. The library is PyNaCl
(libsodium's Ed25519, RFC 8032: the same signatures as any other
implementation); this module only stores keys and wraps its two calls.
libsodium verifies in about half OpenSSL's time (54 against 102 us), and
an operator on the fabric verifies every stimulus, keyframe and heartbeat
its robot sends: the largest single cost of its loop.

Key files are text: ``NAME.sign`` holds the public key as 64 hex digits (it
goes into rosters), ``NAME.sign_secret`` the 32-byte seed as hex (mode 0600,
it never leaves the machine it was made on).
"""

from __future__ import annotations

import os
from pathlib import Path

from common.errors import ConfigError

PUBLIC_KEY_BYTES = 32
SIGNATURE_BYTES = 64


class Signer:
    """A private signing key: ``sign(data)`` gives 64 bytes; ``public`` is its 32-byte key."""

    def __init__(self, seed: bytes) -> None:
        from nacl.signing import SigningKey

        if len(seed) != 32:
            raise ConfigError(f"an Ed25519 seed is 32 bytes, not {len(seed)}")
        self._key = SigningKey(seed)
        self.public = bytes(self._key.verify_key)

    @classmethod
    def generate(cls) -> Signer:
        return cls(os.urandom(32))

    def sign(self, data: bytes) -> bytes:
        return self._key.sign(data).signature


_VERIFIERS: dict[bytes, object] = {}  # public key -> its loaded key object (a roster is small)


def verify(public: bytes, signature: bytes, data: bytes) -> bool:
    """Whether ``signature`` is ``public``'s over ``data``."""
    from nacl.exceptions import BadSignatureError, CryptoError
    from nacl.signing import VerifyKey

    key = _VERIFIERS.get(public)
    if key is None:
        try:
            key = VerifyKey(public)
        except (ValueError, TypeError, CryptoError):
            return False
        if len(_VERIFIERS) < 1024:
            _VERIFIERS[public] = key
    try:
        key.verify(data, signature)
    except (BadSignatureError, ValueError, TypeError):
        return False
    return True


def parse_public_key(text: str, where: str = "signing key") -> bytes:
    """A public key written as 64 hex digits; ``ConfigError`` otherwise."""
    try:
        raw = bytes.fromhex(text.strip())
    except ValueError:
        raw = b""
    if len(raw) != PUBLIC_KEY_BYTES:
        raise ConfigError(f"{where} must be {2 * PUBLIC_KEY_BYTES} hex digits, not {text!r:.80}")
    return raw


def write_secret_file(path: Path, text: str) -> None:
    """``text`` into ``path``, a file that is mode 0600 from its first byte to its last.

    Written to a fresh file created 0600 (``O_EXCL``: never one someone else
    made or opened) beside ``path``, then renamed over it: an existing file
    of a wider mode is replaced, not reused, and no other user can open the
    secret between its creation and a later ``chmod``, whatever the umask.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{os.urandom(4).hex()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    try:
        with os.fdopen(fd, "w") as f:
            os.fchmod(f.fileno(), 0o600)  # a umask can only narrow it; this says it
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def generate_key_files(directory: Path, name: str, force: bool = False) -> tuple[Path, Path]:
    """Write ``NAME.sign`` (public, hex) and ``NAME.sign_secret`` (seed, hex, mode 0600)."""
    directory.mkdir(parents=True, exist_ok=True)
    public, secret = directory / f"{name}.sign", directory / f"{name}.sign_secret"
    if not force and (public.exists() or secret.exists()):
        raise ConfigError(f"{public} or {secret} exists; pass --force to replace them")
    seed = os.urandom(32)
    write_secret_file(secret, seed.hex() + "\n")
    public.write_text(Signer(seed).public.hex() + "\n")
    return public, secret


def load_signer(path: Path) -> Signer:
    """The signing key in a ``NAME.sign_secret`` file."""
    try:
        text = Path(path).read_text()
    except OSError as e:
        raise ConfigError(f"cannot read signing key {path}: {e}") from None
    try:
        seed = bytes.fromhex(text.strip())
    except ValueError:
        raise ConfigError(f"{path} is not a NAME.sign_secret file (64 hex digits)") from None
    return Signer(seed)


def load_public_key(path: Path) -> bytes:
    """The public key in a ``NAME.sign`` file."""
    try:
        text = Path(path).read_text()
    except OSError as e:
        raise ConfigError(f"cannot read public signing key {path}: {e}") from None
    return parse_public_key(text, str(path))
