"""Mutual TLS of a cluster at run time: loading a host's or haactl's certificate, gRPC credentials, and who the
peer of a call is (docs/deploy.md, "Mutual TLS").

A `--tls` cluster has its own certificate authority (made by `haa.cluster.tls`); every host has one certificate
and key, and haactl one client certificate. A certificate names its holder twice: the common name and a
subjectAltName URI `urn:haa:<role>:<name>` (role `host` or `client`); a host certificate also carries the host
name as a DNS name, which is what a connecting host or haactl checks the server against
(`grpc.ssl_target_name_override`): the links of `haa.hostd.transport` are opened to *that* host, not to
whatever answers at its address.

* `HostTls` — a host's material (`--tls-dir DIR`: `ca.pem`, `host.pem`, `host.key`). `load_host` checks that
  the files are there, the key is not readable by others, the certificate is a host certificate for the
  `--name` it is given, issued by the CA next to it, and valid now; every failure is one `TlsError` line.
* `ClientTls` — haactl's material (`ca.pem`, `client.pem`, `client.key`); `load_client` checks the same.
* `peer_identity(context)` — (role, name) of the certificate the peer of a call presented, from grpc's auth
  context (`peer_uri`), or None on a connection without TLS. The host link refuses a stream whose
  `x-haa-sender` is not the certificate's host name; the control API refuses certificates that are not
  client certificates.
* `HandshakeTap` — a TLS handshake that fails (no client certificate, a certificate of another CA, an expired
  one) never reaches Python: grpc's core refuses the connection and writes one line to the process's
  stderr. The tap sits between file descriptor 2 and the real stderr (every byte is passed on), counts those
  lines and reports each to a callback: the host counts them as `rejected_tls_handshake` (and by reason) and
  logs `reject_tls_handshake` (rate-limited) with grpc's reason. grpc's line does not say which side refused:
  a handshake this host's own link failed (a peer with another CA's certificate) is counted the same way.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
import re
import stat
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import grpc

if TYPE_CHECKING:  # `cryptography` is imported where a certificate is read: ~13 MiB a host pays only with TLS on
    from cryptography import x509

#: file names inside a host's TLS directory and haactl's
CA_FILE = "ca.pem"
HOST_CERT = "host.pem"
HOST_KEY = "host.key"
CLIENT_CERT = "client.pem"
CLIENT_KEY = "client.key"
#: certificate roles (the `urn:haa:<role>:<name>` subjectAltName)
HOST = "host"
CLIENT = "client"
URI_PREFIX = "urn:haa:"
#: the largest certificate or key file read
MAX_PEM_BYTES = 64 << 10

_URI_RE = re.compile(r"^urn:haa:(host|client):([A-Za-z0-9][A-Za-z0-9_.-]{0,62})$")


class TlsError(ValueError):
    """TLS material that cannot be used; `str()` is one line."""


def identity_uri(role: str, name: str) -> str:
    return f"{URI_PREFIX}{role}:{name}"


def parse_identity(uri: str) -> tuple[str, str] | None:
    """("host", "h3") of "urn:haa:host:h3"; None for anything else."""
    m = _URI_RE.match(uri)
    return (m.group(1), m.group(2)) if m else None


def cert_identity(cert: x509.Certificate) -> tuple[str, str] | None:
    """The (role, name) a certificate of ours names in its subjectAltName URI, or None."""
    from cryptography import x509

    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return None
    for uri in san.get_values_for_type(x509.UniformResourceIdentifier):
        ident = parse_identity(uri)
        if ident is not None:
            return ident
    return None


def _read(path: Path, what: str, secret: bool) -> bytes:
    try:
        st = path.stat()
    except FileNotFoundError:
        raise TlsError(f"{what} {path}: no such file") from None
    except OSError as e:
        raise TlsError(f"{what} {path}: {e.strerror or e}") from None
    if stat.S_ISDIR(st.st_mode):
        raise TlsError(f"{what} {path} is a directory")
    if st.st_size > MAX_PEM_BYTES:
        raise TlsError(f"{what} {path}: larger than {MAX_PEM_BYTES >> 10} KiB")
    if secret and st.st_mode & 0o077:
        raise TlsError(f"{what} {path} is readable by others (mode {stat.S_IMODE(st.st_mode):o}): chmod 600 it")
    try:
        return path.read_bytes()
    except OSError as e:
        raise TlsError(f"{what} {path}: {e.strerror or e}") from None


def _load_cert(data: bytes, path: Path, what: str) -> x509.Certificate:
    from cryptography import x509

    try:
        return x509.load_pem_x509_certificate(data)
    except ValueError:
        raise TlsError(f"{what} {path}: not a PEM certificate") from None


def _check_pair(directory: Path, cert_name: str, key_name: str, role: str, name: str | None) -> tuple[bytes, ...]:
    """(ca, cert, key) PEM bytes of `directory`, checked (see the module docstring)."""
    from cryptography.hazmat.primitives import serialization

    if not directory.is_dir():
        raise TlsError(f"TLS directory {directory}: {'not a directory' if directory.exists() else 'no such directory'}")
    ca_pem = _read(directory / CA_FILE, "CA certificate", False)
    cert_pem = _read(directory / cert_name, "certificate", False)
    key_pem = _read(directory / key_name, "private key", True)
    ca = _load_cert(ca_pem, directory / CA_FILE, "CA certificate")
    cert = _load_cert(cert_pem, directory / cert_name, "certificate")
    try:
        key = serialization.load_pem_private_key(key_pem, password=None)
    except (ValueError, TypeError):
        raise TlsError(f"private key {directory / key_name}: not an unencrypted PEM private key") from None
    if key.public_key().public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    ) != cert.public_key().public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo):
        raise TlsError(f"private key {directory / key_name} does not belong to certificate {directory / cert_name}")
    try:
        cert.verify_directly_issued_by(ca)
    except Exception as e:  # ValueError, TypeError, or cryptography's InvalidSignature
        raise TlsError(f"certificate {directory / cert_name} was not issued by the CA in {directory / CA_FILE}"
                       f" ({type(e).__name__})") from None
    now = dt.datetime.now(dt.UTC)
    for c, p in ((ca, CA_FILE), (cert, cert_name)):
        if not c.not_valid_before_utc <= now <= c.not_valid_after_utc:
            raise TlsError(f"certificate {directory / p} is not valid now (valid {c.not_valid_before_utc:%Y-%m-%d} to "
                           f"{c.not_valid_after_utc:%Y-%m-%d} UTC)")
    ident = cert_identity(cert)
    if ident is None or ident[0] != role:
        raise TlsError(f"certificate {directory / cert_name} is not a {role} certificate of an HAA cluster")
    if name is not None and ident[1] != name:
        raise TlsError(f"certificate {directory / cert_name} is for host {ident[1]!r}, not {name!r}")
    return ca_pem, cert_pem, key_pem


def channel_options(server_name: str) -> list[tuple[str, Any]]:
    """Channel options that make the channel check the server's certificate for `server_name` (a host name)."""
    return [("grpc.ssl_target_name_override", server_name)]


@dataclass(frozen=True)
class HostTls:
    """A host's CA, certificate and key (PEM bytes)."""

    name: str
    ca: bytes
    cert: bytes
    key: bytes
    directory: str = ""

    def server_credentials(self) -> grpc.ServerCredentials:
        """Mutual TLS: every client must present a certificate of the cluster's CA."""
        return grpc.ssl_server_credentials([(self.key, self.cert)], root_certificates=self.ca, require_client_auth=True)

    def channel_credentials(self) -> grpc.ChannelCredentials:
        """Credentials for this host's links to its peers (its own certificate as the client's)."""
        return grpc.ssl_channel_credentials(self.ca, self.key, self.cert)


@dataclass(frozen=True)
class ClientTls:
    """haactl's CA, client certificate and key (PEM bytes)."""

    ca: bytes
    cert: bytes
    key: bytes
    directory: str = ""

    def channel_credentials(self) -> grpc.ChannelCredentials:
        return grpc.ssl_channel_credentials(self.ca, self.key, self.cert)


def load_host(directory: str | os.PathLike[str], name: str) -> HostTls:
    """Host `name`'s TLS material in `directory` (ca.pem, host.pem, host.key); TlsError if unusable."""
    d = Path(directory)
    ca, cert, key = _check_pair(d, HOST_CERT, HOST_KEY, HOST, name)
    return HostTls(name, ca, cert, key, str(d))


def load_client(directory: str | os.PathLike[str]) -> ClientTls:
    """haactl's TLS material in `directory` (ca.pem, client.pem, client.key); TlsError if unusable."""
    d = Path(directory)
    ca, cert, key = _check_pair(d, CLIENT_CERT, CLIENT_KEY, CLIENT, None)
    return ClientTls(ca, cert, key, str(d))


def peer_identity(context: Any) -> tuple[str, str] | None:
    """(role, name) of the certificate the peer of this call presented (a grpc servicer context), or None
    when the connection has no TLS or the certificate names no HAA identity."""
    try:
        auth = context.auth_context() or {}
    except Exception:
        return None
    for raw in auth.get("peer_uri", ()):
        uri = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else str(raw)
        ident = parse_identity(uri)
        if ident is not None:
            return ident
    return None


# ---------------------------------------------------------------------- handshake failures (grpc core's stderr)

#: grpc core's line for a refused TLS handshake, e.g. "... ssl_transport_security.cc:2563] Handshake failed with
#: error SSL_ERROR_SSL: error:100000c0:SSL routines:OPENSSL_internal:PEER_DID_NOT_RETURN_A_CERTIFICATE: ..."
_HANDSHAKE_RE = re.compile(rb"Handshake failed with (?:fatal )?error (\S+?):? (.*)$")
_REASON_RE = re.compile(rb"OPENSSL_internal:([A-Z0-9_]{3,})")


def handshake_reason(line: bytes) -> str | None:
    """The short reason of a grpc core "Handshake failed" stderr line (e.g. "PEER_DID_NOT_RETURN_A_CERTIFICATE",
    "CERTIFICATE_VERIFY_FAILED"), or None if the line is something else."""
    m = _HANDSHAKE_RE.search(line)
    if m is None:
        return None
    r = _REASON_RE.search(m.group(2))
    if r is not None:
        return r.group(1).decode()
    return m.group(1).decode("ascii", "replace")[:80]


class HandshakeTap:
    """Tap file descriptor 2 (see the module docstring): `on_refused(reason)` for every failed TLS handshake
    grpc's core reports there. Everything written to stderr still reaches the original stderr, unchanged."""

    def __init__(self, on_refused: Callable[[str], None]) -> None:
        self.on_refused = on_refused
        self._orig = -1
        self._read_fd = -1
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        r, w = os.pipe()
        self._orig = os.dup(2)
        os.dup2(w, 2)
        os.close(w)
        self._read_fd = r
        self._thread = threading.Thread(target=self._pump, name="tls-handshake-tap", daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        buf = b""
        while True:
            try:
                data = os.read(self._read_fd, 65536)
            except OSError:
                data = b""
            if not data:  # `stop` put the original stderr back: the pipe's last writer is gone
                os.close(self._read_fd)
                os.close(self._orig)
                return
            with contextlib.suppress(OSError):
                os.write(self._orig, data)
            buf += data
            *lines, buf = buf.split(b"\n")
            if len(buf) > 65536:
                buf = b""
            for line in lines:
                reason = handshake_reason(line)
                if reason is not None:
                    with contextlib.suppress(Exception):
                        self.on_refused(reason)

    def stop(self) -> None:
        """Put the original stderr back (the pump ends when the pipe's last writer is gone)."""
        if self._orig < 0 or self._thread is None:
            return
        os.dup2(self._orig, 2)
        self._thread.join(timeout=1.0)
