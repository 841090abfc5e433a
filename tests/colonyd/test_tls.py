"""Zenoh's mutual TLS between daemons through `zenoh_config`, with certificates made here."""

from __future__ import annotations

import datetime
import ipaddress
import json
import time
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from colonyd.runtime import open_session, zenoh_config
from colonyd.status import alive_members


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def make_pki(directory: Path, ca_name: str, member: str) -> Path:
    """A CA and one certificate it signs (for 127.0.0.1 and localhost, server and client use);
    returns a Zenoh JSON5 config enabling mutual TLS with them."""
    directory.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.UTC)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = (
        x509.CertificateBuilder()
        .subject_name(_name(ca_name))
        .issuer_name(_name(ca_name))
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_cert_sign=True,
                crl_sign=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(member))
        .issuer_name(ca.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
            ),
            critical=False,
        )
        .add_extension(
            x509.ExtendedKeyUsage(
                [x509.oid.ExtendedKeyUsageOID.SERVER_AUTH, x509.oid.ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .sign(ca_key, hashes.SHA256())
    )
    (directory / "ca.pem").write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    (directory / "cert.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    (directory / "key.pem").write_bytes(_pem_key(key))
    (directory / "key.pem").chmod(0o600)
    tls = {
        "root_ca_certificate": str(directory / "ca.pem"),
        "enable_mtls": True,
        "verify_name_on_connect": True,
        "listen_certificate": str(directory / "cert.pem"),
        "listen_private_key": str(directory / "key.pem"),
        "connect_certificate": str(directory / "cert.pem"),
        "connect_private_key": str(directory / "key.pem"),
    }
    conf = directory / "zenoh-tls.json5"
    conf.write_text(json.dumps({"transport": {"link": {"tls": tls}}}, indent=1))
    return conf


def test_mutual_tls_between_daemons(make_colony, tmp_path):
    conf = make_pki(tmp_path / "pki", "colony-ca", "member")
    colony = make_colony("tls", transport="tls", zenoh_config=conf)
    a = colony.add("a", ["synthetic:scans=4,rate=4,points=150,seed=1"])
    colony.add("b")
    assert a.endpoint.startswith("tls/")
    colony.wait_converged(30)

    def members_seen_with(extra_file: Path) -> list[str]:
        session = open_session(
            zenoh_config(
                mode="peer",
                listen=["tls/127.0.0.1:0"],
                connect=[a.endpoint],
                multicast=False,
                gossip=True,
                extra_file=extra_file,
            )
        )
        try:
            time.sleep(1.0)
            return alive_members(session, colony.namespace, timeout=1.0)
        finally:
            session.close()

    # The control: a member's certificate sees the colony within the same window...
    assert members_seen_with(conf) == ["a", "b"]
    # ...someone whose certificate another CA signed gets no link: no member is visible to it.
    assert members_seen_with(make_pki(tmp_path / "rogue", "rogue-ca", "member")) == []
    # Nor does a plain TCP session on the same port.
    plain = open_session(
        zenoh_config(
            mode="peer",
            connect=[f"tcp/127.0.0.1:{a.port}"],
            listen=["tcp/127.0.0.1:0"],
            multicast=False,
        )
    )
    try:
        time.sleep(0.5)
        assert alive_members(plain, colony.namespace, timeout=1.0) == []
    finally:
        plain.close()
    assert "tls" in a.log_path.read_text()
