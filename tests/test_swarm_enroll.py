"""Certificate enrollment of swarm tasks (haa.cluster.enroll; docs/swarm.md, "TLS under docker service scale"), on
loopback without docker: the real HTTPS service with a cluster CA, the real requester.

The swarm's DNS is replaced by a table (name -> addresses) and the name `enroll` is pointed at 127.0.0.1 for the
client, the way the stack's overlay network resolves them. A task gets a certificate for its own name that
haa-hostd loads (haa.tls.load_host); a wrong enrollment token is refused at once (401); a name that resolves to
another address than the caller's is refused (403, counted and logged as rejected_name_mismatch) — holding the
token does not let a task take another host's name. ≈2 s.
"""

from __future__ import annotations

import re
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from cryptography import x509

from haa import tls as rt
from haa.cluster import enroll
from haa.cluster.tls import ClusterCA

TOKEN = "e" * 64


class Service:
    def __init__(self, tmp: Path) -> None:
        self.ca = ClusterCA.create(tmp / "ca")
        self.records: list[dict[str, Any]] = []
        ca, own = enroll.service_ca(tmp / "ca" / "ca.pem", tmp / "ca" / "ca.key", tmp / "work")
        self.names = {"host4": {"127.0.0.1"}, "host5": {"10.9.9.9"}}
        self.enroller = enroll.Enroller(ca, TOKEN, resolve=lambda n: self.names.get(n, set()),
                                        log=self.records.append)
        self.server = enroll.make_server(self.enroller, ("127.0.0.1", 0), own / rt.HOST_CERT, own / rt.HOST_KEY)
        self.url = f"https://enroll:{self.server.server_address[1]}"
        self.ca_file = tmp / "ca" / "ca.pem"


@pytest.fixture
def service(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Service]:
    real = socket.getaddrinfo

    def getaddrinfo(host: Any, *a: Any, **kw: Any) -> Any:
        return real("127.0.0.1" if host == enroll.SERVICE_NAME else host, *a, **kw)

    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    s = Service(tmp_path)
    t = threading.Thread(target=s.server.serve_forever, daemon=True)
    t.start()
    yield s
    s.server.shutdown()
    s.server.server_close()


def test_a_task_gets_a_certificate_for_its_own_name(service: Service, tmp_path: Path) -> None:
    out = enroll.request(service.url, "host4", TOKEN, service.ca_file, tmp_path / "tls", timeout=10)
    host = rt.load_host(out, "host4")  # what haa-hostd --tls-dir does
    assert host is not None
    cert = x509.load_pem_x509_certificate((out / rt.HOST_CERT).read_bytes())
    assert cert.issuer == service.ca.cert.subject
    assert cert.subject.get_attributes_for_oid(x509.oid.NameOID.COMMON_NAME)[0].value == "host4"
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["host4"]
    assert san.get_values_for_type(x509.UniformResourceIdentifier) == [rt.identity_uri(rt.HOST, "host4")]
    assert (out / rt.HOST_KEY).stat().st_mode & 0o077 == 0
    assert service.enroller.counts == {"issued": 1}
    with pytest.raises(rt.TlsError):  # the certificate is host4's, not anybody else's
        rt.load_host(out, "host5")


def test_wrong_token_is_refused_at_once(service: Service, tmp_path: Path) -> None:
    with pytest.raises(enroll.EnrollError, match="401 wrong or missing enrollment token"):
        enroll.request(service.url, "host4", "x" * 64, service.ca_file, tmp_path / "tls", timeout=10)
    assert service.enroller.counts == {"rejected_token": 1}
    assert not (tmp_path / "tls").exists()


def test_a_name_bound_to_another_task_is_refused(service: Service, tmp_path: Path) -> None:
    why = re.escape("403 host5 resolves to 10.9.9.9, not to the caller 127.0.0.1")
    with pytest.raises(enroll.EnrollError, match=why):
        enroll.request(service.url, "host5", TOKEN, service.ca_file, tmp_path / "tls", timeout=1.5)
    assert service.enroller.counts.get("rejected_name_mismatch", 0) >= 1 and "issued" not in service.enroller.counts
    assert service.records[0]["event"] == "enroll_refused" and service.records[0]["name"] == "host5"
    # an unknown name, and the service's own name, are no better
    status, reply = service.enroller.handle("127.0.0.1", f"Bearer {TOKEN}", b'{"name": "enroll", "csr": "x"}')
    assert status == 400, reply
