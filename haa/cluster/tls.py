"""A cluster's certificate authority and the certificates of its hosts and of haactl (`haactl cluster up --tls`).

Made with the `cryptography` package, all on this machine, nothing fetched. The layout under a cluster's TLS
directory (`<cluster root>/tls` for a local cluster, `compose/tls` for the compose cluster):

    ca.pem, ca.key          the cluster CA (ECDSA P-256, self-signed, 10 years, path length 0)
    hosts/<name>/           one directory per host, mounted or given to that host alone (`--tls-dir`):
        ca.pem                  the CA certificate (to check its peers)
        host.pem, host.key      its certificate: CN <name>, subjectAltName DNS:<name> and
                                URI urn:haa:host:<name>, server and client authentication, 1 year
    client/                 haactl's: ca.pem, client.pem, client.key (CN haactl, URI urn:haa:client:haactl)

Directories are 0700, keys 0600, certificates 0644 (haa-hostd in the image runs as root and reads them
through a read-only bind mount of its own directory). A host added later (`haactl host add`) gets its
certificate from the CA on the spot (`ClusterCA.issue_host`). Rotation: `haactl cluster up --tls` makes a
new CA each time (the old certificates stop working at once); there is no revocation list — a leaked host
key is dealt with by a new CA (docs/deploy.md, "Mutual TLS").
"""

from __future__ import annotations

import datetime as dt
import os
import secrets
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from haa import tls as rt

CA_KEY = "ca.key"
HOSTS_DIR = "hosts"
CLIENT_DIR = "client"
#: haactl's certificate name
CLIENT_NAME = "haactl"
CA_DAYS = 3650
LEAF_DAYS = 365
#: certificates start this long in the past (clocks of the machines differ a little)
BACKDATE = dt.timedelta(minutes=10)


class CaError(Exception):
    """The CA cannot be made or used; `str()` is one line."""


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write `data` with `mode` from the first byte on (no moment where a key is readable by others)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        os.write(fd, data)
    finally:
        os.close(fd)
    os.chmod(tmp, mode)  # (the umask may have taken bits away)
    tmp.replace(path)


def _mkdir(path: Path, mode: int) -> None:
    path.mkdir(parents=True, exist_ok=True)
    os.chmod(path, mode)


@dataclass
class ClusterCA:
    """The CA of one cluster TLS directory (see the module docstring)."""

    directory: Path
    key: ec.EllipticCurvePrivateKey
    cert: x509.Certificate

    @classmethod
    def create(cls, directory: Path) -> ClusterCA:
        """A new CA in `directory` (whatever was there is replaced: the old certificates stop working)."""
        directory = Path(directory)
        _mkdir(directory, 0o700)
        for sub in (HOSTS_DIR, CLIENT_DIR):
            old = directory / sub
            if old.is_dir():
                for f in sorted(old.rglob("*"), reverse=True):
                    if f.is_dir():
                        f.rmdir()
                    else:
                        f.unlink()
        key = _key()
        now = dt.datetime.now(dt.UTC)
        name = x509.Name([
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "HAA cluster"),
            x509.NameAttribute(NameOID.COMMON_NAME, f"HAA cluster CA {secrets.token_hex(4)}"),
        ])
        cert = (
            x509.CertificateBuilder()
            .subject_name(name)
            .issuer_name(name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - BACKDATE)
            .not_valid_after(now + dt.timedelta(days=CA_DAYS))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(
                x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                              data_encipherment=False, key_agreement=False, key_cert_sign=True, crl_sign=True,
                              encipher_only=False, decipher_only=False),
                critical=True,
            )
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256())
        )
        _write(directory / CA_KEY, _key_pem(key), 0o600)
        _write(directory / rt.CA_FILE, _cert_pem(cert), 0o644)
        return cls(directory, key, cert)

    @classmethod
    def load(cls, directory: Path) -> ClusterCA:
        directory = Path(directory)
        try:
            key_pem = rt._read(directory / CA_KEY, "CA key", True)
            cert_pem = rt._read(directory / rt.CA_FILE, "CA certificate", False)
        except rt.TlsError as e:
            raise CaError(str(e)) from None
        try:
            key = serialization.load_pem_private_key(key_pem, password=None)
            cert = x509.load_pem_x509_certificate(cert_pem)
        except (ValueError, TypeError):
            raise CaError(f"the CA in {directory} is broken (not PEM): make a new one with `--tls`") from None
        if not isinstance(key, ec.EllipticCurvePrivateKey):
            raise CaError(f"the CA key {directory / CA_KEY} is not an EC key")
        return cls(directory, key, cert)

    def _leaf(self, role: str, name: str, key: ec.EllipticCurvePrivateKey) -> x509.Certificate:
        now = dt.datetime.now(dt.UTC)
        sans: list[x509.GeneralName] = [x509.UniformResourceIdentifier(rt.identity_uri(role, name))]
        usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
        if role == rt.HOST:
            sans.insert(0, x509.DNSName(name))
            usages.insert(0, ExtendedKeyUsageOID.SERVER_AUTH)
        return (
            x509.CertificateBuilder()
            .subject_name(x509.Name([
                x509.NameAttribute(NameOID.ORGANIZATION_NAME, "HAA cluster"),
                x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, role),
                x509.NameAttribute(NameOID.COMMON_NAME, name),
            ]))
            .issuer_name(self.cert.subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - BACKDATE)
            .not_valid_after(min(now + dt.timedelta(days=LEAF_DAYS), self.cert.not_valid_after_utc))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                              data_encipherment=False, key_agreement=False, key_cert_sign=False, crl_sign=False,
                              encipher_only=False, decipher_only=False),
                critical=True,
            )
            .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(self.key.public_key()), critical=False)
            .sign(self.key, hashes.SHA256())
        )

    def host_dir(self, name: str) -> Path:
        return self.directory / HOSTS_DIR / name

    @property
    def client_dir(self) -> Path:
        return self.directory / CLIENT_DIR

    def issue_host(self, name: str) -> Path:
        """A certificate and key for host `name` in `hosts/<name>/` (replacing one it had); returns the directory."""
        from haa.hostd.transport import valid_name

        if not valid_name(name):
            raise CaError(f"{name!r} is not a valid host name")
        d = self.host_dir(name)
        _mkdir(d.parent, 0o700)
        _mkdir(d, 0o700)
        key = _key()
        _write(d / rt.CA_FILE, _cert_pem(self.cert), 0o644)
        _write(d / rt.HOST_CERT, _cert_pem(self._leaf(rt.HOST, name, key)), 0o644)
        _write(d / rt.HOST_KEY, _key_pem(key), 0o600)
        return d

    def issue_client(self, name: str = CLIENT_NAME) -> Path:
        """haactl's client certificate and key in `client/`; returns the directory."""
        d = self.client_dir
        _mkdir(d, 0o700)
        key = _key()
        _write(d / rt.CA_FILE, _cert_pem(self.cert), 0o644)
        _write(d / rt.CLIENT_CERT, _cert_pem(self._leaf(rt.CLIENT, name, key)), 0o644)
        _write(d / rt.CLIENT_KEY, _key_pem(key), 0o600)
        return d


def make_cluster_tls(directory: Path, hosts: list[str]) -> ClusterCA:
    """A new CA in `directory`, a certificate for each of `hosts` and haactl's client certificate; CaError (one
    line) if they cannot be written (e.g. a directory docker created, owned by root)."""
    try:
        ca = ClusterCA.create(directory)
        for h in hosts:
            ca.issue_host(h)
        ca.issue_client()
    except OSError as e:
        raise CaError(f"cannot write the cluster's TLS material in {directory}: {e.strerror or e}"
                      f"{f' ({e.filename})' if e.filename else ''}") from None
    return ca
