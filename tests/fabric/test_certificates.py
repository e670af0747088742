"""The fabric's CA: one certificate per roster member, its name the common name, keys 0600."""

from __future__ import annotations

import stat

import pytest
from cryptography import x509

from common.errors import ConfigError
from common.fabric.certificates import CertFiles, common_name, issue, make_ca
from common.fabric.session import cert_files


def _mode(path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_a_member_certificate_names_the_member_and_is_signed_by_the_ca(tmp_path):
    ca = make_ca(tmp_path)
    files = issue(ca, tmp_path, "cell1")
    assert common_name(files.cert) == "cell1"
    cert = x509.load_pem_x509_certificate(files.cert.read_bytes())
    ca_cert = x509.load_pem_x509_certificate(ca.cert.read_bytes())
    cert.verify_directly_issued_by(ca_cert)  # raises if not
    assert _mode(files.key) == 0o600 and _mode(ca.key) == 0o600


def test_a_router_certificate_names_the_addresses_it_is_dialled_at(tmp_path):
    files = issue(make_ca(tmp_path), tmp_path, "router", ("127.0.0.1", "relay.lab.org"))
    cert = x509.load_pem_x509_certificate(files.cert.read_bytes())
    sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [str(a) for a in sans.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    assert sans.get_values_for_type(x509.DNSName) == ["relay.lab.org"]


def test_existing_certificates_are_kept_unless_forced(tmp_path):
    ca = make_ca(tmp_path)
    first = issue(ca, tmp_path, "alice").cert.read_bytes()
    assert make_ca(tmp_path).cert.read_bytes() == ca.cert.read_bytes()
    assert issue(ca, tmp_path, "alice").cert.read_bytes() == first
    assert issue(ca, tmp_path, "alice", force=True).cert.read_bytes() != first


def test_a_node_refuses_a_certificate_of_another_name_or_a_missing_one(tmp_path):
    ca = make_ca(tmp_path)
    issue(ca, tmp_path, "alice")
    (tmp_path / "alice.crt").replace(tmp_path / "bob.crt")
    (tmp_path / "alice.key").replace(tmp_path / "bob.key")
    with pytest.raises(ConfigError, match="'alice''s certificate, not 'bob''s"):
        cert_files(tmp_path, "bob", "operator link.fabric")
    with pytest.raises(ConfigError, match="keys certs"):
        cert_files(tmp_path, "carol", "operator link.fabric")
    with pytest.raises(ConfigError, match="cert_dir is unset"):
        cert_files(None, "carol", "operator link.fabric")
    assert CertFiles.in_dir(tmp_path, "x").ca == tmp_path / "ca.crt"
