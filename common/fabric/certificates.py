"""A small certificate authority for the fabric: one certificate per roster member.

The Zenoh router across sites admits a connection only with a certificate its
CA signed (mutual TLS on QUIC), and its access control knows each peer by the
certificate's common name: the roster name of a robot or an operator, or the
router's own name. So the roster is the identity, and this module turns it
into files:

    ca.crt / ca.key                the authority (ca.key never leaves the machine that made it)
    NAME.crt / NAME.key            one member (NAME = its roster name, the common name)

Private keys are written mode 0600 from their first byte (``write_secret_file``).
The keys are ECDSA P-256, which every TLS stack Zenoh uses accepts.

Simplified on purpose: the CA's machine makes every member's private key and
the member's files are then copied to its machine (as with the CURVE keys).
A member that must never let its key leave its machine needs a signing
request flow this module does not have.
"""

from __future__ import annotations

import datetime
import ipaddress
from dataclasses import dataclass
from pathlib import Path

from common.errors import ConfigError
from common.wire.signing import write_secret_file

#: how long a certificate is valid; renew with ``deepxpalm keys certs --force``
VALID_DAYS = 825
CA_NAME = "ca"


@dataclass(frozen=True)
class CertFiles:
    """One member's certificate and private key, and the CA certificate that signed it."""

    cert: Path
    key: Path
    ca: Path

    @classmethod
    def in_dir(cls, directory: Path, name: str) -> CertFiles:
        directory = Path(directory)
        return cls(directory / f"{name}.crt", directory / f"{name}.key", directory / "ca.crt")

    def check(self, where: str) -> None:
        """ConfigError naming the missing file and the command that makes it."""
        for path in (self.cert, self.key, self.ca):
            if not path.is_file():
                raise ConfigError(
                    f"{where}: {path} does not exist (`deepxpalm keys certs --roster ROSTER "
                    "--dir DIR` makes every member's certificate)"
                )


def _x509():
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    return x509, hashes, serialization, ec, ExtendedKeyUsageOID, NameOID


def _write_key(path: Path, key) -> None:
    _, _, serialization, _, _, _ = _x509()
    pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    write_secret_file(path, pem.decode("ascii"))


def make_ca(directory: Path, force: bool = False) -> CertFiles:
    """``ca.crt`` and ``ca.key`` in ``directory``; kept as they are unless ``force``."""
    x509, hashes, serialization, ec, _, name_oid = _x509()
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    files = CertFiles(directory / "ca.crt", directory / "ca.key", directory / "ca.crt")
    if files.cert.exists() and files.key.exists() and not force:
        return files
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(name_oid.COMMON_NAME, "deepxpalm fabric CA")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .sign(key, hashes.SHA256())
    )
    _write_key(files.key, key)
    files.cert.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return files


def _load_ca(ca: CertFiles):
    x509, _, serialization, _, _, _ = _x509()
    try:
        cert = x509.load_pem_x509_certificate(ca.cert.read_bytes())
        key = serialization.load_pem_private_key(ca.key.read_bytes(), password=None)
    except (OSError, ValueError) as e:
        raise ConfigError(f"cannot read the CA in {ca.cert.parent}: {e}") from None
    return cert, key


def issue(
    ca: CertFiles, directory: Path, name: str, hosts: tuple[str, ...] = (), force: bool = False
) -> CertFiles:
    """``NAME.crt`` and ``NAME.key`` signed by ``ca``, with ``name`` as the common name.

    ``hosts``: the DNS names and IP addresses the member is reached at (a
    router's listening address): clients check the router's certificate
    against the address they dialled. Members that only connect out need none.
    """
    x509, hashes, serialization, ec, eku, name_oid = _x509()
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    files = CertFiles.in_dir(directory, name)
    if files.cert.exists() and files.key.exists() and not force:
        return files
    ca_cert, ca_key = _load_ca(ca)
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    sans: list = []
    for host in hosts:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            sans.append(x509.DNSName(host))
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(name_oid.COMMON_NAME, name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([eku.CLIENT_AUTH, eku.SERVER_AUTH]), critical=False)
    )
    # a name the certificate can be dialled by: the member's name at least (rustls needs one)
    names = sans or [x509.DNSName(name)]
    builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    cert = builder.sign(ca_key, hashes.SHA256())
    _write_key(files.key, key)
    files.cert.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    if ca.cert.resolve() != files.ca.resolve():
        files.ca.write_bytes(ca.cert.read_bytes())
    return files


def common_name(cert_path: Path) -> str:
    """The common name in a certificate file: a member's roster name."""
    x509, _, _, _, _, name_oid = _x509()
    try:
        cert = x509.load_pem_x509_certificate(Path(cert_path).read_bytes())
    except (OSError, ValueError) as e:
        raise ConfigError(f"cannot read certificate {cert_path}: {e}") from None
    names = cert.subject.get_attributes_for_oid(name_oid.COMMON_NAME)
    if not names:
        raise ConfigError(f"certificate {cert_path} has no common name")
    return str(names[0].value)
