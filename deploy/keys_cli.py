"""``deepxpalm keys``: make CURVE key pairs and allow an operator on the robot.

    deepxpalm keys generate --dir keys --name robot       # on the robot PC
    deepxpalm keys generate --dir keys --name operator    # on the operator PC
    deepxpalm keys allow keys/operator.key --authorized /etc/deepxpalm/operators

    deepxpalm keys generate-signing --dir keys --name operator-alice   # Ed25519, signs commands

Copy only public ``.key`` and ``.sign`` files between machines; ``.key_secret`` files
never leave the machine they were made on (they are written mode 0600).
"""

from __future__ import annotations

import argparse
import os
import shutil
from pathlib import Path

import zmq.auth

from common.errors import ConfigError


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
    show = sub.add_parser("show", help="print a key file's public key (Z85)")
    show.add_argument("key_file", type=Path)


def generate(directory: Path, name: str, force: bool = False) -> tuple[Path, Path]:
    directory.mkdir(parents=True, exist_ok=True)
    public, secret = directory / f"{name}.key", directory / f"{name}.key_secret"
    if not force and (public.exists() or secret.exists()):
        raise ConfigError(f"{public} or {secret} exists; pass --force to replace the pair")
    made_public, made_secret = zmq.auth.create_certificates(str(directory), name)
    os.chmod(made_secret, 0o600)
    return Path(made_public), Path(made_secret)


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


def run(args: argparse.Namespace) -> int:
    if args.keys_command == "generate":
        public, secret = generate(args.dir, args.name, args.force)
        print(f"public key: {public}  (copy this one to the other machine)")
        print(f"secret key: {secret}  (keep it here; mode 0600)")
    elif args.keys_command == "generate-signing":
        from common.signing import generate_key_files

        public, secret = generate_key_files(args.dir, args.name, args.force)
        print(f"public key: {public}  (its hex goes into the rosters as signing_key)")
        print(f"secret key: {secret}  (keep it here; mode 0600)")
    elif args.keys_command == "allow":
        target = allow(args.public_key, args.authorized)
        print(f"allowed: {target}; restart the robot node to take it in")
    else:
        public, _ = zmq.auth.load_certificate(args.key_file)
        print(public.decode())
    return 0
