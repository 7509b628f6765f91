"""Certificates of a deployment: one CA, and per host a certificate for its router, for each of its
services and for an operator (the experiment runner and CLI tools run there). Mutual TLS between
every session and its router, and between routers, is Zenoh's own; access control matches these
certificates' common names (deploy/access.py).

Layout under the manifest's certs_dir: ca.pem, ca.key (keep the CA key off the robots), and
<host>/<role>.pem, <host>/<role>.key for each role; copy ca.pem and <host>/ to that host.
"""
from __future__ import annotations

import datetime
import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from deploy.manifest import Manifest, parse_endpoint

ROUTER = "router"
OPERATOR = "operator"
VALID_DAYS = 825        # what browsers accept for leaf certificates; renew by running the command again


def common_name(host: str, role: str) -> str:
    return f"lbc-{host}-{role}"


def roles(m: Manifest, host: str) -> list[str]:
    return [ROUTER, OPERATOR, *m.host(host).services]


@dataclass(frozen=True)
class CertFiles:
    ca: Path
    cert: Path
    key: Path


def cert_files(m: Manifest, host: str, role: str) -> CertFiles:
    base = Path(m.certs_dir)
    return CertFiles(base / "ca.pem", base / host / f"{role}.pem", base / host / f"{role}.key")


def _write(path: Path, data: bytes, private: bool) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)
    os.replace(tmp, path)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _load_or_make_ca(base: Path, name: str) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """Reuse an existing CA, so adding a host does not invalidate the others' certificates."""
    ca_pem, ca_key = base / "ca.pem", base / "ca.key"
    if ca_pem.exists() and ca_key.exists():
        return (x509.load_pem_x509_certificate(ca_pem.read_bytes()),
                serialization.load_pem_private_key(ca_key.read_bytes(), password=None))
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"lbc {name} CA")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=3650))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, encipher_only=False,
                                         decipher_only=False), critical=True)
            .sign(key, hashes.SHA256()))
    _write(ca_key, _key_pem(key), private=True)
    _write(ca_pem, cert.public_bytes(serialization.Encoding.PEM), private=False)
    return cert, key


def _san(address: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(address))
    except ValueError:
        return x509.DNSName(address)


def _issue(ca: x509.Certificate, ca_key, cn: str, address: str) -> tuple[bytes, bytes]:
    """A leaf certificate for both ends of a TLS link: routers listen and connect, services connect.
    Its subject alternative name is the host's router address, which connecting sessions verify."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
            .issuer_name(ca.subject).public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
            .add_extension(x509.SubjectAlternativeName([_san(address)]), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .sign(ca_key, hashes.SHA256()))
    return cert.public_bytes(serialization.Encoding.PEM), _key_pem(key)


def make_certs(m: Manifest) -> list[Path]:
    """Issue (or re-issue) every host's certificates; returns the certificate files written."""
    base = Path(m.certs_dir)
    ca, ca_key = _load_or_make_ca(base, m.name)
    written = []
    for host, spec in m.hosts.items():
        address = parse_endpoint(spec.listen, f"hosts.{host}.listen").address
        for role in roles(m, host):
            files = cert_files(m, host, role)
            cert, key = _issue(ca, ca_key, common_name(host, role), address)
            _write(files.key, key, private=True)
            _write(files.cert, cert, private=False)
            written.append(files.cert)
    return written


def missing_certs(m: Manifest, host: str) -> list[Path]:
    out = []
    for role in roles(m, host):
        f = cert_files(m, host, role)
        out.extend(p for p in (f.ca, f.cert, f.key) if not p.exists())
    return sorted(set(out))
