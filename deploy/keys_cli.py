"""``deepxpalm keys``: make key pairs, allow an operator on the robot, write roster entries.

    deepxpalm keys generate --dir keys --name robot       # on the robot PC
    deepxpalm keys generate --dir keys --name operator    # on the operator PC
    deepxpalm keys allow keys/operator.key --authorized /etc/deepxpalm/operators

    deepxpalm keys generate-signing --dir keys --name operator-alice   # Ed25519, signs commands

For a fleet, one command per machine makes both pairs (or keeps the ones
there) and prints the machine's roster entry, to paste into roster.toml:

    deepxpalm keys robot --dir /etc/deepxpalm/keys --name cell1        # on robot PC cell1
    deepxpalm keys operator --dir /etc/deepxpalm/keys --name alice --role controller

Across sites through Zenoh routers, one command on the machine that keeps the
fabric's certificate authority makes a certificate per roster member (its roster
name is the common name) and the router's:

    deepxpalm keys certs --roster roster.toml --dir fabric --router-host router.lab.org

Copy each member's NAME.crt, NAME.key and ca.crt to that member's machine only.

Copy only public ``.key`` and ``.sign`` files between machines; ``.key_secret`` files
never leave the machine they were made on (they are written mode 0600).
"""

from __future__ import annotations

import argparse
import datetime
import shutil
import sys
from pathlib import Path

import zmq.auth
from zmq.utils import z85

from common.errors import ConfigError
from common.wire.messages import ROLES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = __doc__
    sub = parser.add_subparsers(dest="keys_command", required=True)
    gen = sub.add_parser("generate", help="make a key pair NAME.key / NAME.key_secret")
    gen.add_argument("--dir", type=Path, required=True, help="where to write the files")
    gen.add_argument("--name", required=True, help="e.g. robot or operator-alice")
    gen.add_argument("--force", action="store_true", help="overwrite an existing pair")
    allow = sub.add_parser("allow", help="add an operator's public key to the robot's allowlist")
    allow.add_argument("public_key", type=Path, help="the operator's NAME.key file")
    allow.add_argument(
        "--authorized", type=Path, required=True, help="the robot's authorized_keys_dir"
    )
    sign = sub.add_parser(
        "generate-signing",
        help="make an Ed25519 signing key NAME.sign / NAME.sign_secret (roster signing_key)",
    )
    sign.add_argument("--dir", type=Path, required=True, help="where to write the files")
    sign.add_argument("--name", required=True, help="e.g. operator-alice")
    sign.add_argument("--force", action="store_true", help="overwrite an existing pair")
    robot = sub.add_parser(
        "robot",
        help="a robot PC's CURVE and stream-signing pairs (kept if there) and its [[robot]] entry",
    )
    robot.add_argument("--dir", type=Path, required=True, help="where the key files are")
    robot.add_argument("--name", required=True, help="the robot's name (link.robot_name)")
    robot.add_argument(
        "--names",
        nargs="+",
        default=(),
        help="more robot names this PC's key may publish and receive under (default: --name)",
    )
    operator = sub.add_parser(
        "operator",
        help="an operator PC's CURVE and signing pairs (kept if there) and its [[operator]] entry",
    )
    operator.add_argument("--dir", type=Path, required=True, help="where the key files are")
    operator.add_argument("--name", required=True, help="the operator's name in the roster")
    operator.add_argument("--role", required=True, choices=ROLES)
    certs = sub.add_parser(
        "certs",
        help="the fabric's CA (kept if there) and a certificate per roster member and router",
    )
    certs.add_argument("--roster", type=Path, required=True, help="the roster (roster.toml)")
    certs.add_argument("--dir", type=Path, required=True, help="where the CA and certificates go")
    certs.add_argument(
        "--router-name", default="router", help="the router's certificate name (its config's name)"
    )
    certs.add_argument(
        "--router-host",
        nargs="+",
        default=["127.0.0.1", "localhost"],
        help="names and addresses nodes dial the router at (its certificate must name them)",
    )
    certs.add_argument("--force", action="store_true", help="renew every member's certificate")
    show = sub.add_parser(
        "show",
        help="print a key file's public key: a CURVE pair's (Z85) or a signing key's (hex)",
    )
    show.add_argument("key_file", type=Path)


def generate(directory: Path, name: str, force: bool = False) -> tuple[Path, Path]:
    """``NAME.key`` and ``NAME.key_secret`` (pyzmq's certificate format); the secret 0600.

    Not ``zmq.auth.create_certificates``: it writes the secret under the
    process umask (often 0644) and leaves a chmod to the caller, a window in
    which another user can open it. Here it is never on disk in another mode.
    """
    from common.wire.signing import write_secret_file

    directory.mkdir(parents=True, exist_ok=True)
    public, secret = directory / f"{name}.key", directory / f"{name}.key_secret"
    if not force and (public.exists() or secret.exists()):
        raise ConfigError(f"{public} or {secret} exists; pass --force to replace the pair")
    public_key, secret_key = zmq.curve_keypair()
    made = datetime.datetime.now()
    write_secret_file(
        secret,
        _certificate(_SECRET_BANNER.format(made), public_key, secret_key),
    )
    public.write_text(_certificate(_PUBLIC_BANNER.format(made), public_key))
    return public, secret


_PUBLIC_BANNER = """#   ****  Generated on {0} by deepxpalm keys  ****
#   ZeroMQ CURVE Public Certificate
#   Copy it to the machines that must know this key.

"""
_SECRET_BANNER = """#   ****  Generated on {0} by deepxpalm keys  ****
#   ZeroMQ CURVE **Secret** Certificate
#   DO NOT PROVIDE THIS FILE TO OTHER USERS nor change its permissions.

"""


def _certificate(banner: str, public_key: bytes, secret_key: bytes | None = None) -> str:
    """A certificate file as pyzmq writes it (``zmq.auth.load_certificate`` reads it)."""
    text = banner + "metadata\ncurve\n" + f'    public-key = "{public_key.decode()}"\n'
    if secret_key is not None:
        text += f'    secret-key = "{secret_key.decode()}"\n'
    return text


def allow(public_key: Path, authorized: Path) -> Path:
    try:
        _, secret = zmq.auth.load_certificate(public_key)
    except (OSError, ValueError) as e:
        raise ConfigError(f"{public_key} is not a key file: {e}") from None
    if secret is not None:
        raise ConfigError(f"{public_key} holds a secret key: give the public NAME.key file")
    authorized.mkdir(parents=True, exist_ok=True)
    target = authorized / public_key.name
    shutil.copyfile(public_key, target)
    return target


def machine_keys(directory: Path, name: str) -> dict[str, Path]:
    """A machine's CURVE pair and Ed25519 pair under ``directory``, made only where missing.

    Never replaces an existing pair (other machines hold its public half);
    half a pair on disk is an error to resolve by hand.
    """
    from common.wire.signing import generate_key_files

    files = {
        "curve_public": directory / f"{name}.key",
        "curve_secret": directory / f"{name}.key_secret",
        "signing_public": directory / f"{name}.sign",
        "signing_secret": directory / f"{name}.sign_secret",
    }
    for make, public, secret in (
        (generate, files["curve_public"], files["curve_secret"]),
        (generate_key_files, files["signing_public"], files["signing_secret"]),
    ):
        if public.exists() != secret.exists():
            raise ConfigError(f"only one of {public} and {secret} exists: restore or remove it")
        if not public.exists():
            make(directory, name)
    return files


def fabric_certificates(
    roster_file: Path, directory: Path, router: str, hosts: tuple[str, ...], force: bool
) -> list[str]:
    """The CA (made once) and a certificate for the router and each roster member."""
    from common.fabric.certificates import issue, make_ca
    from common.fabric.keyexprs import check_operator_name
    from common.keys.roster import load_roster

    roster = load_roster(roster_file)
    for op in roster.operators:
        check_operator_name(op.name)
    ca = make_ca(directory)
    made = [issue(ca, directory, router, hosts, force)]
    for name in [r.name for r in roster.robots] + [op.name for op in roster.operators]:
        made.append(issue(ca, directory, name, (), force))
    lines = [f"CA: {ca.cert} (its key {ca.key} stays on this machine)"]
    lines += [f"{files.cert.stem}: {files.cert} {files.key}" for files in made]
    lines.append("copy each member's NAME.crt, NAME.key and ca.crt to its machine only")
    return lines


def run(args: argparse.Namespace) -> int:
    if args.keys_command == "generate":
        public, secret = generate(args.dir, args.name, args.force)
        print(f"public key: {public}  (copy this one to the other machine)")
        print(f"secret key: {secret}  (keep it here; mode 0600)")
    elif args.keys_command == "generate-signing":
        from common.wire.signing import generate_key_files

        public, secret = generate_key_files(args.dir, args.name, args.force)
        print(f"public key: {public}  (its hex goes into the rosters as signing_key)")
        print(f"secret key: {secret}  (keep it here; mode 0600)")
    elif args.keys_command in ("robot", "operator"):
        from common.keys.roster import operator_entry, robot_entry
        from common.wire.signing import load_public_key

        files = machine_keys(args.dir.resolve(), args.name)
        curve, _ = zmq.auth.load_certificate(files["curve_public"])
        if args.keys_command == "robot":
            entry = robot_entry(args.name, curve, tuple(args.names))
            print(f'# robot.toml here: [robot.link] signing_key_file = "{files["signing_secret"]}"')
            print(f'#   and [robot.link.security] secret_key_file = "{files["curve_secret"]}"')
            print(f"# each operator following {args.name}: a copy of {files['signing_public']}")
            print("#   as its [operator.link] robot_key_file (its stream is signed)")
        else:
            signing = load_public_key(files["signing_public"])
            entry = operator_entry(args.name, args.role, curve, signing)
            print("# operator.toml here: [operator.link] signing_key_file = ", end="")
            print(f'"{files["signing_secret"]}"')
            print(f'#   and [operator.link.security] secret_key_file = "{files["curve_secret"]}"')
        print("# the roster (router host and every robot PC; robots last) gets this entry:")
        print(entry, end="")
    elif args.keys_command == "certs":
        for line in fabric_certificates(
            args.roster, args.dir, args.router_name, tuple(args.router_host), args.force
        ):
            print(line)
    elif args.keys_command == "allow":
        target = allow(args.public_key, args.authorized)
        print(f"allowed: {target}; restart the robot node to take it in")
    else:
        try:
            print(public_key_text(args.key_file))
        except ConfigError as e:  # bad input: one line, as argparse says a bad option
            print(f"deepxpalm keys show: error: {e}", file=sys.stderr)
            return 2
    return 0


def public_key_text(path: Path) -> str:
    """A key file's public key: a CURVE pair's (``NAME.key`` or ``NAME.key_secret``, as Z85) or
    a signing key's (``NAME.sign``, as hex); ``ConfigError`` naming what is wrong otherwise."""
    from common.wire.signing import Signer, parse_public_key

    try:
        data = path.read_bytes()
    except OSError as e:
        raise ConfigError(f"cannot read {path}: {e.strerror or e}") from None
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError:
        text = ""
    if text and not text.lstrip().startswith("#") and "=" not in text:
        try:  # NAME.sign: 64 hex digits; NAME.sign_secret the same, a seed whose key is shown
            key = parse_public_key(text.strip(), str(path))
        except ConfigError:
            pass
        else:
            return Signer(key).public.hex() if path.suffix == ".sign_secret" else key.hex()
    try:
        public, _ = zmq.auth.load_certificate(path)
        if len(public) != 40 or len(z85.decode(public)) != 32:
            raise ValueError("its public-key is not 40 Z85 characters")
    except (OSError, ValueError) as e:
        raise ConfigError(
            f"{path} is not a key file (a CURVE NAME.key or NAME.key_secret, or a signing "
            f"NAME.sign): {e}"
        ) from None
    return public.decode()
