"""Certificate enrollment of swarm tasks: how a task made by `docker service scale` gets a host certificate of its
own for mutual TLS (issue 20 §1-2; docs/swarm.md, "TLS under docker service scale").

A swarm secret is the same for every task of a service, so per-host certificates cannot be handed out as
secrets when the number of hosts changes at run time. Instead the stack (compose/stack-tls.yaml over
compose/stack.yaml) runs a small enrollment service that holds the cluster CA (haa.cluster.tls; its key a
swarm secret given to that service alone). Each core or host task, before haa-hostd starts:

1. makes its own key (ECDSA P-256; the key never leaves the task) and a certificate signing request,
2. sends `{"name": HAA_NAME, "csr": PEM}` to the enrollment service over HTTPS, checking the service's
   certificate (DNS name `enroll`, issued by the cluster CA, whose certificate every task has as a secret),
   authenticated by the enrollment token (another secret, `Authorization: Bearer ...`),
3. gets back a certificate for exactly that host name (CN, DNS, URI urn:haa:host:NAME, as `haactl cluster up
   --tls` makes them) and writes ca.pem, host.pem, host.key into HAA_TLS_DIR, which haa-hostd then loads.

The service signs a name only for the task that carries it: the name must resolve, in the swarm's DNS of the
stack's network, to the address the request comes from (each task's hostname is its host name and a DNS alias
on the overlay network). So a task holding the enrollment token — every task does — still cannot get the
certificate of another host: what the token mode allowed (any holder could claim any name) is closed, and a
leaked host key is that one host's. A refused request is answered 401 (token) / 403 (name not bound to the
caller) / 400 (bad request) and logged as one JSON line; the requester retries 403 and connection errors
(a fresh task's alias can take a moment to appear) until its timeout, and fails at once on 401.

`python -m haa.cluster.enroll serve|request` (settings from HAA_* variables, see `main`); errors end the
process with one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import contextlib
import hmac
import json
import os
import socket
import ssl
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from haa import tls as rt
from haa.cluster.tls import CA_KEY, ClusterCA

#: the enrollment service's own name (its certificate's DNS name; the service name in the stack)
SERVICE_NAME = "enroll"
PORT = 7300
MAX_BODY = 16 * 1024
Resolver = Callable[[str], set[str]]


class EnrollError(Exception):
    """Enrollment failed; `str()` is one line."""


def swarm_resolver(name: str) -> set[str]:
    """The IPv4 addresses `name` resolves to (the swarm's DNS inside a task)."""
    try:
        return {str(a[4][0]) for a in socket.getaddrinfo(name, None, socket.AF_INET)}
    except OSError:
        return set()


class _PublicKey:
    """Stands for a private key where ClusterCA only needs `public_key()` (the task keeps its private key)."""

    def __init__(self, key: Any) -> None:
        self._key = key

    def public_key(self) -> Any:
        return self._key


class Enroller:
    """Signs host certificates for swarm tasks (see the module docstring)."""

    def __init__(self, ca: ClusterCA, token: str, resolve: Resolver = swarm_resolver,
                 log: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.ca = ca
        self.token = token.encode()
        self.resolve = resolve
        self.log = log or (lambda rec: print(json.dumps(rec), file=sys.stderr, flush=True))
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()

    def _count(self, what: str) -> None:
        with self._lock:
            self.counts[what] = self.counts.get(what, 0) + 1

    def handle(self, peer: str, auth: str, body: bytes) -> tuple[int, dict[str, Any]]:
        """(HTTP status, JSON reply) for one enrollment request from address `peer`."""
        from haa.hostd.transport import valid_name

        token = auth.removeprefix("Bearer ").strip().encode()
        if not auth.startswith("Bearer ") or not hmac.compare_digest(token, self.token):
            return self._refuse(401, "rejected_token", peer, "", "wrong or missing enrollment token")
        try:
            req = json.loads(body)
            name = str(req["name"])
            csr = x509.load_pem_x509_csr(str(req["csr"]).encode())
        except (ValueError, KeyError, TypeError):
            return self._refuse(400, "rejected_request", peer, "", "not a JSON object with name and a PEM csr")
        if not valid_name(name) or name == SERVICE_NAME:
            return self._refuse(400, "rejected_request", peer, name, f"{name[:64]!r} is not a host name")
        if not csr.is_signature_valid:
            return self._refuse(400, "rejected_request", peer, name, "the CSR's signature does not verify")
        key = csr.public_key()
        if not isinstance(key, ec.EllipticCurvePublicKey) or key.curve.name != "secp256r1":
            return self._refuse(400, "rejected_request", peer, name, "the CSR's key is not ECDSA P-256")
        addrs = self.resolve(name)
        if peer not in addrs:
            return self._refuse(403, "rejected_name_mismatch", peer, name,
                                f"{name} resolves to {', '.join(sorted(addrs)) or 'nothing'}, not to the caller {peer}")
        cert = self.ca._leaf(rt.HOST, name, _PublicKey(key))  # type: ignore[arg-type]
        self._count("issued")
        self.log({"ts": time.time(), "event": "enroll_issued", "name": name, "peer": peer,
                  "serial": format(cert.serial_number, "x")})
        return 200, {"cert": cert.public_bytes(serialization.Encoding.PEM).decode(),
                     "ca": self.ca.cert.public_bytes(serialization.Encoding.PEM).decode()}

    def _refuse(self, status: int, what: str, peer: str, name: str, why: str) -> tuple[int, dict[str, Any]]:
        self._count(what)
        self.log({"ts": time.time(), "event": "enroll_refused", "reason": what, "name": name, "peer": peer,
                  "why": why})
        return status, {"error": why}


def make_server(enroller: Enroller, listen: tuple[str, int], cert: Path, key: Path) -> ThreadingHTTPServer:
    """The HTTPS server of `enroller` (not started: `serve_forever()`)."""

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            n = int(self.headers.get("Content-Length") or 0)
            if self.path != "/enroll" or n <= 0 or n > MAX_BODY:
                status, reply = 400, {"error": "POST /enroll with a body of at most 16 KiB"}
            else:
                status, reply = enroller.handle(self.client_address[0], self.headers.get("Authorization") or "",
                                                self.rfile.read(n))
            data = json.dumps(reply).encode()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def log_message(self, format: str, *args: Any) -> None:  # decisions are logged by Enroller
            pass

    srv = ThreadingHTTPServer(listen, Handler)
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.load_cert_chain(str(cert), str(key))
    srv.socket = ctx.wrap_socket(srv.socket, server_side=True)
    return srv


def service_ca(ca_file: Path, ca_key_file: Path, workdir: Path) -> tuple[ClusterCA, Path]:
    """The CA from its two secrets, and the enrollment service's own certificate directory (DNS `enroll`)."""
    for f in (ca_file, ca_key_file):
        if not f.is_file():
            raise EnrollError(f"{f} is missing (the stack's TLS secrets: haactl cluster up --swarm --tls)")
    d = workdir / "ca"
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    for src, dst, mode in ((ca_file, rt.CA_FILE, 0o644), (ca_key_file, CA_KEY, 0o600)):
        p = d / dst
        p.write_bytes(src.read_bytes())
        p.chmod(mode)
    ca = ClusterCA.load(d)
    return ca, ca.issue_host(SERVICE_NAME)


def request(url: str, name: str, token: str, ca_file: Path, out: Path, timeout: float = 60.0) -> Path:
    """Enroll host `name`: a new key, a certificate from the service at `url` (https://enroll:7300), both
    written with the CA certificate into `out` (ca.pem, host.pem, host.key) and checked as haa-hostd will."""
    key = ec.generate_private_key(ec.SECP256R1())
    csr = (x509.CertificateSigningRequestBuilder()
           .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
           .sign(key, hashes.SHA256()))
    body = json.dumps({"name": name, "csr": csr.public_bytes(serialization.Encoding.PEM).decode()}).encode()
    ctx = ssl.create_default_context(cafile=str(ca_file))
    deadline = time.monotonic() + timeout
    last = ""
    while True:
        req = urllib.request.Request(f"{url.rstrip('/')}/enroll", data=body, method="POST",
                                     headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(req, timeout=10, context=ctx) as r:
                reply = json.loads(r.read())
            break
        except urllib.error.HTTPError as e:
            why = ""
            with contextlib.suppress(ValueError):
                why = json.loads(e.read()).get("error", "")
            if e.code != 403:
                raise EnrollError(f"the enrollment service refused {name}: {e.code} {why}") from None
            last = f"403 {why}"
        except (urllib.error.URLError, OSError) as e:
            last = str(getattr(e, "reason", e))
        if time.monotonic() > deadline:
            raise EnrollError(f"no certificate for {name} from {url} within {timeout:.0f} s ({last})")
        time.sleep(1.0)
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    for fname, data, mode in ((rt.CA_FILE, reply["ca"].encode(), 0o644), (rt.HOST_CERT, reply["cert"].encode(), 0o644),
                              (rt.HOST_KEY, key.private_bytes(serialization.Encoding.PEM,
                                                              serialization.PrivateFormat.PKCS8,
                                                              serialization.NoEncryption()), 0o600)):
        fd = os.open(out / fname, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
    try:
        rt.load_host(out, name)
    except rt.TlsError as e:
        raise EnrollError(f"the certificate issued for {name} does not load: {e}") from None
    return out


def _read_secret(path: str, what: str) -> str:
    try:
        text = Path(path).read_text().strip()
    except OSError as e:
        raise EnrollError(f"cannot read the {what} {path}: {e.strerror or e}") from None
    if not text:
        raise EnrollError(f"the {what} {path} is empty")
    return text


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m haa.cluster.enroll", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("serve", help="run the enrollment service")
    s.add_argument("--listen", default=f"0.0.0.0:{PORT}")
    s.add_argument("--ca", default=os.environ.get("HAA_TLS_CA_FILE", "/run/secrets/haa_tls_ca"))
    s.add_argument("--ca-key", default=os.environ.get("HAA_TLS_CA_KEY_FILE", "/run/secrets/haa_tls_ca_key"))
    s.add_argument("--token-file", default=os.environ.get("HAA_ENROLL_TOKEN_FILE", "/run/secrets/haa_enroll_token"))
    r = sub.add_parser("request", help="get this task's host certificate (before haa-hostd starts)")
    r.add_argument("--name", default=os.environ.get("HAA_NAME"))
    r.add_argument("--url", default=os.environ.get("HAA_TLS_ENROLL"), help="e.g. https://enroll:7300")
    r.add_argument("--ca", default=os.environ.get("HAA_TLS_CA_FILE", "/run/secrets/haa_tls_ca"))
    r.add_argument("--token-file", default=os.environ.get("HAA_ENROLL_TOKEN_FILE", "/run/secrets/haa_enroll_token"))
    r.add_argument("--out", default=os.environ.get("HAA_TLS_DIR"))
    r.add_argument("--timeout", type=float, default=60.0)
    a = p.parse_args(argv)
    try:
        if a.cmd == "serve":
            host, _, port = a.listen.rpartition(":")
            token = _read_secret(a.token_file, "enrollment token")
            ca, own = service_ca(Path(a.ca), Path(a.ca_key), Path(tempfile.mkdtemp(prefix="haa-enroll-")))
            srv = make_server(Enroller(ca, token), (host or "0.0.0.0", int(port)), own / rt.HOST_CERT,
                              own / rt.HOST_KEY)
            print(json.dumps({"ts": time.time(), "event": "enroll_serving", "listen": a.listen}), file=sys.stderr,
                  flush=True)
            srv.serve_forever()
        else:
            for opt in ("name", "url", "out"):
                if not getattr(a, opt):
                    raise EnrollError(f"--{opt} (or its HAA_ variable) is required")
            token = _read_secret(a.token_file, "enrollment token")
            out = request(a.url, a.name, token, Path(a.ca), Path(a.out), a.timeout)
            print(json.dumps({"ts": time.time(), "event": "enrolled", "name": a.name, "dir": str(out)}),
                  file=sys.stderr, flush=True)
    except (EnrollError, ValueError, OSError) as e:
        print(f"haa-enroll: error: {e}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
