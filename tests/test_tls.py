"""Mutual TLS (docs/deploy.md): certificates, and a real `--tls` cluster that refuses impostors.

The unit tests check the cluster CA (`haa.cluster.tls`) and the loading checks (`haa.tls`). The cluster tests
share one local cluster of 3 haa-hostd processes made by `haactl cluster up --tls` (in-process CLI) and run in
order: a peer with a certificate of another CA, a valid certificate for h3 used by a process calling itself h5
(and h1), a client without a certificate, a plaintext client and a host certificate on the control API are all
refused, counted (status counters) and logged (the hosts' JSON logs); meanwhile the group stays formed with no
suspicion, haactl's commands work, a host added later gets its certificate and joins, and a DDB write commits
after all the refusals.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import stat
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes
from helpers import Cli, local_cluster, wait_sync, wait_value

from haa import tls
from haa.cluster.local_backend import LocalBackend
from haa.cluster.tls import ClusterCA, make_cluster_tls
from haa.core.ddb import ops as ddb
from haa.hostd.transport import MD_HB_KEY, MD_INC, MD_SENDER, MD_TOKEN, OPEN_METHOD
from haa.pb import control_pb2 as cpb

# ------------------------------------------------------------------------------------------------ certificates


def test_cluster_ca_makes_host_and_client_certificates_with_private_keys(tmp_path: Path) -> None:
    make_cluster_tls(tmp_path / "tls", ["h1", "h2"])
    for path in [tmp_path / "tls" / "ca.key", *(tmp_path / "tls").rglob("*.key")]:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    for d in [tmp_path / "tls", *(p for p in (tmp_path / "tls").rglob("*") if p.is_dir())]:
        assert stat.S_IMODE(d.stat().st_mode) == 0o700, d
    h1 = tls.load_host(tmp_path / "tls" / "hosts" / "h1", "h1")
    cert = x509.load_pem_x509_certificate(h1.cert)
    assert tls.cert_identity(cert) == ("host", "h1")
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["h1"]
    client = tls.load_client(tmp_path / "tls" / "client")
    assert tls.cert_identity(x509.load_pem_x509_certificate(client.cert)) == ("client", "haactl")
    # a host added later: the same CA
    ClusterCA.load(tmp_path / "tls").issue_host("h7")
    assert tls.load_host(tmp_path / "tls" / "hosts" / "h7", "h7").ca == h1.ca


def test_loading_refuses_unusable_material_with_one_line(tmp_path: Path) -> None:
    make_cluster_tls(tmp_path / "a", ["h1", "h2"])
    make_cluster_tls(tmp_path / "b", ["h1"])
    h1 = tmp_path / "a" / "hosts" / "h1"

    def refused(directory: Path, name: str, text: str) -> None:
        with pytest.raises(tls.TlsError) as e:
            tls.load_host(directory, name)
        assert text in str(e.value) and "\n" not in str(e.value)

    refused(h1, "h2", "is for host 'h1', not 'h2'")
    refused(tmp_path / "nope", "h1", "no such directory")
    with pytest.raises(tls.TlsError, match="not a host certificate"):
        tls._check_pair(tmp_path / "a" / "client", tls.CLIENT_CERT, tls.CLIENT_KEY, tls.HOST, None)
    # another CA's certificate next to this CA
    mixed = tmp_path / "mixed"
    mixed.mkdir(mode=0o700)
    (mixed / "ca.pem").write_bytes((h1 / "ca.pem").read_bytes())
    (mixed / "host.pem").write_bytes((tmp_path / "b" / "hosts" / "h1" / "host.pem").read_bytes())
    key = mixed / "host.key"
    key.write_bytes((tmp_path / "b" / "hosts" / "h1" / "host.key").read_bytes())
    key.chmod(0o600)
    refused(mixed, "h1", "was not issued by the CA")
    # a key that does not belong to the certificate
    key.write_bytes((tmp_path / "a" / "hosts" / "h2" / "host.key").read_bytes())
    (mixed / "host.pem").write_bytes((h1 / "host.pem").read_bytes())
    refused(mixed, "h1", "does not belong to certificate")
    key.write_bytes((h1 / "host.key").read_bytes())
    key.chmod(0o644)
    refused(mixed, "h1", "readable by others")
    key.chmod(0o600)
    assert tls.load_host(mixed, "h1").name == "h1"
    # an expired certificate
    ca = ClusterCA.load(tmp_path / "a")
    cert = x509.load_pem_x509_certificate((h1 / "host.pem").read_bytes())
    old = (x509.CertificateBuilder(extensions=list(cert.extensions)).subject_name(cert.subject).issuer_name(cert.issuer)
           .public_key(cert.public_key()).serial_number(x509.random_serial_number())
           .not_valid_before(dt.datetime(2020, 1, 1, tzinfo=dt.UTC))
           .not_valid_after(dt.datetime(2021, 1, 1, tzinfo=dt.UTC))
           .sign(ca.key, hashes.SHA256()))
    from cryptography.hazmat.primitives.serialization import Encoding

    (mixed / "host.pem").write_bytes(old.public_bytes(Encoding.PEM))
    refused(mixed, "h1", "is not valid now")


def test_handshake_reason_reads_grpc_core_lines() -> None:
    line = (b"I1127 21:55:42.628729   11088 ssl_transport_security.cc:2563] Handshake failed with error SSL_ERROR_SSL:"
            b" error:100000c0:SSL routines:OPENSSL_internal:PEER_DID_NOT_RETURN_A_CERTIFICATE: Invalid certificate")
    assert tls.handshake_reason(line) == "PEER_DID_NOT_RETURN_A_CERTIFICATE"
    assert tls.handshake_reason(b"E1127 ssl_transport_security.cc:3238] No match found for server name: h2") is None


def test_handshake_tap_counts_grpc_lines_and_passes_stderr_through(tmp_path: Path) -> None:
    seen: list[str] = []
    sink = tmp_path / "stderr.txt"
    saved = os.dup(2)
    fd = os.open(sink, os.O_WRONLY | os.O_CREAT, 0o600)
    os.dup2(fd, 2)  # the "real" stderr of this test
    os.close(fd)
    try:
        tap = tls.HandshakeTap(seen.append)
        tap.start()
        os.write(2, b"ordinary line\nE1127 ssl_transport_security.cc:1] Handshake failed with error SSL_ERROR_SSL: "
                    b"error:1000:SSL routines:OPENSSL_internal:CERTIFICATE_VERIFY_FAILED: x\n")
        wait_sync(lambda: seen, 10, "the tap to read the handshake line", interval=0.01)
        tap.stop()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
    assert seen == ["CERTIFICATE_VERIFY_FAILED"]
    text = sink.read_text()
    assert text.startswith("ordinary line\n") and "CERTIFICATE_VERIFY_FAILED" in text


def test_haa_hostd_refuses_material_for_another_name_in_one_line(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    from haa.hostd.daemon import load_settings

    make_cluster_tls(tmp_path / "tls", ["h1"])
    token = tmp_path / "token"
    token.write_text("t\n")
    with pytest.raises(SystemExit) as e:
        load_settings(["--name", "h2", "--listen", "127.0.0.1:0", "--core", "h1=127.0.0.1:1", "--token-file",
                       str(token), "--tls-dir", str(tmp_path / "tls" / "hosts" / "h1")])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--tls-dir: certificate" in err and "is for host 'h1', not 'h2'" in err


# ------------------------------------------------------------------------------------------------ a TLS cluster


class Cluster:
    def __init__(self, cli: Cli) -> None:
        self.cli = cli
        self.root = cli.root
        self.view0 = 0  # the view the group formed in

    @property
    def backend(self) -> LocalBackend:
        return LocalBackend(self.root)

    def counters(self, name: str) -> dict[str, int]:
        with self.backend.client(name) as c:
            return dict(c.status().counters.values)

    def wait_counter(self, name: str, key: str, at_least: int, timeout: float = 20.0) -> dict[str, int]:
        return wait_value(lambda: self.counters(name), lambda c: c.get(key, 0) >= at_least, timeout,
                          f"{name}'s {key} to reach {at_least}", show=lambda c: f"{key} = {c.get(key, 0)}")

    def logged(self, name: str, event: str) -> list[dict[str, Any]]:
        path = self.root / name / f"{name}.jsonl"
        out = []
        for line in path.read_text().splitlines():
            rec = json.loads(line)
            if rec.get("event") == event:
                out.append(rec)
        return out

    def wait_logged(self, name: str, event: str, timeout: float = 20.0) -> dict[str, Any]:
        return wait_sync(lambda: self.logged(name, event), timeout, f"{name} to log {event}", interval=0.1)[0]

    def members(self) -> dict[str, Any]:
        return json.loads(self.cli("cluster", "status", "--json", "--sample", "0").stdout)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    with local_cluster(tmp_path_factory.mktemp("tls") / "cluster", "--tls", "--hosts", "3", "--timeout", "90",
                       down=("--purge", "--grace", "2")) as cli:
        yield Cluster(cli)


def _pem(path: Path) -> bytes:
    return path.read_bytes()


def open_link(cluster: Cluster, target: str, creds: grpc.ChannelCredentials, sender: str) -> grpc.RpcError:
    """Open a host link to `target` as `sender` with the cluster token; return the refusal."""
    b = cluster.backend
    md = ((MD_TOKEN, b.token), (MD_SENDER, sender), (MD_INC, str(time.time_ns())), (MD_HB_KEY, "ab" * 32))
    with grpc.secure_channel(b.host(target).address, creds, options=tls.channel_options(target)) as ch:
        call = ch.stream_stream(OPEN_METHOD)(iter(()), metadata=md, timeout=10)
        with pytest.raises(grpc.RpcError) as e:
            for _ in call:
                pass
    return e.value


def test_the_tls_cluster_formed_and_keeps_its_material_private(cluster: Cluster) -> None:
    st = cluster.members()
    assert sorted(st["members"]) == ["h1", "h2", "h3"]
    cluster.view0 = st["view"]
    for key in (cluster.root / "tls").rglob("*.key"):
        assert stat.S_IMODE(key.stat().st_mode) == 0o600
    # the hosts really serve TLS only: a plaintext client gets nowhere
    with grpc.insecure_channel(cluster.backend.host("h1").address) as ch, pytest.raises(grpc.RpcError) as e:
        ch.unary_unary("/haa.v1.HostControl/Status")(b"", metadata=((MD_TOKEN, cluster.backend.token),), timeout=5)
    assert e.value.code() == grpc.StatusCode.UNAVAILABLE


def test_a_peer_with_a_certificate_of_another_ca_is_refused(cluster: Cluster, tmp_path: Path) -> None:
    before = cluster.counters("h1").get("rejected_tls_handshake", 0)
    other = make_cluster_tls(tmp_path / "other", ["h2"]).host_dir("h2")
    ca = _pem(cluster.root / "tls" / "ca.pem")  # it trusts the real CA; the hosts do not trust its CA
    creds = grpc.ssl_channel_credentials(ca, _pem(other / "host.key"), _pem(other / "host.pem"))
    err = open_link(cluster, "h1", creds, "h2")
    assert err.code() == grpc.StatusCode.UNAVAILABLE
    c = cluster.wait_counter("h1", "rejected_tls_handshake", before + 1)
    reasons = {k for k in c if k.startswith("rejected_tls_handshake.")}
    assert reasons - {"rejected_tls_handshake.peer_did_not_return_a_certificate"}, c
    rec = cluster.wait_logged("h1", "reject_tls_handshake")
    assert rec["level"] == "warning" and rec["fields"]["reason"]


def test_a_valid_certificate_for_h3_calling_itself_h5_or_h1_is_refused(cluster: Cluster) -> None:
    h3 = cluster.root / "tls" / "hosts" / "h3"
    creds = grpc.ssl_channel_credentials(_pem(h3 / "ca.pem"), _pem(h3 / "host.key"), _pem(h3 / "host.pem"))
    for target, claim in (("h1", "h5"), ("h2", "h1")):
        before = cluster.counters(target).get("rejected_name_mismatch", 0)
        err = open_link(cluster, target, creds, claim)
        assert err.code() == grpc.StatusCode.PERMISSION_DENIED, err
        assert "host h3" in (err.details() or "") and repr(claim) in (err.details() or "")
        assert cluster.counters(target)["rejected_name_mismatch"] == before + 1
        rec = cluster.wait_logged(target, "reject_name_mismatch")
        assert rec["fields"]["certificate"] == "host h3"
    # the real h1's links were not disturbed (a claim is refused before it touches the sender's state)
    assert cluster.counters("h2").get("link_superseded_streams", 0) == 0


def test_a_client_without_a_certificate_cannot_call_the_control_api(cluster: Cluster) -> None:
    b = cluster.backend
    before = cluster.counters("h2").get("rejected_tls_handshake.peer_did_not_return_a_certificate", 0)
    ca = _pem(cluster.root / "tls" / "ca.pem")
    with grpc.secure_channel(b.host("h2").address, grpc.ssl_channel_credentials(ca),
                             options=tls.channel_options("h2")) as ch, pytest.raises(grpc.RpcError) as e:
        ch.unary_unary("/haa.v1.HostControl/Status")(cpb.StatusRequest().SerializeToString(),
                                                     metadata=((MD_TOKEN, b.token),), timeout=5)
    assert e.value.code() == grpc.StatusCode.UNAVAILABLE
    cluster.wait_counter("h2", "rejected_tls_handshake.peer_did_not_return_a_certificate", before + 1)


def test_a_host_certificate_cannot_drive_the_control_api(cluster: Cluster) -> None:
    b = cluster.backend
    h3 = cluster.root / "tls" / "hosts" / "h3"
    creds = grpc.ssl_channel_credentials(_pem(h3 / "ca.pem"), _pem(h3 / "host.key"), _pem(h3 / "host.pem"))
    with grpc.secure_channel(b.host("h1").address, creds, options=tls.channel_options("h1")) as ch, \
            pytest.raises(grpc.RpcError) as e:
        ch.unary_unary("/haa.v1.HostControl/Status")(cpb.StatusRequest().SerializeToString(),
                                                     metadata=((MD_TOKEN, b.token),), timeout=5)
    assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
    assert cluster.counters("h1")["rejected_not_client"] >= 1
    assert cluster.wait_logged("h1", "control_reject_not_client")["fields"]["certificate"] == "host h3"


def test_haactl_works_a_host_joins_and_a_write_commits_after_the_refusals(cluster: Cluster) -> None:
    # the refusals changed nothing: the same view, nobody suspected
    st = cluster.members()
    assert st["view"] == cluster.view0 and sorted(st["members"]) == ["h1", "h2", "h3"]
    assert all(not h["suspicions"] for h in st["hosts"]), st["hosts"]
    # haactl's commands go over TLS with its client certificate
    cluster.cli("ddb", "put", "tls/before", "1")
    cluster.cli("host", "add", "h4", "--timeout", "60")
    assert (cluster.root / "tls" / "hosts" / "h4" / "host.key").exists()
    st = cluster.members()
    assert sorted(st["members"]) == ["h1", "h2", "h3", "h4"]
    with cluster.backend.client("h4") as c:
        r = c.ddb_write([ddb.put("tls/after", "blob", b"ok")], timeout=30)
        assert r.committed, r
        assert sorted(o.key for o in c.ddb_get(["tls/before", "tls/after"]).objects) == ["tls/after", "tls/before"]
    for h in ("h1", "h2", "h3", "h4"):
        c = cluster.counters(h)
        # heartbeats arrived as datagrams under TLS, each checked with its link's own key
        assert c.get("hb_rejected_unauthenticated", 0) == 0, (h, c)
        assert c.get("rx_datagrams", 0) > 0, (h, c)
    assert os.path.exists(cluster.root / "tls" / "ca.key")


def test_a_static_mesh_over_tls_commits(tmp_path: Path) -> None:
    """`haactl bench ap1 --tls` and the demo's static mode: `LocalCluster(tls=True)`, real processes."""
    from haa.cluster.hostprocs import LocalCluster

    with LocalCluster(["h1", "h2", "h3"], tmp_path, tls=True) as c:
        c.start()
        c.wait_trusted(timeout=60)
        r = c["h2"].client.propose(b"over tls", wait=True)
        assert r.decided and r.committed and sorted(r.participants) == ["h1", "h2", "h3"]
        counters = dict(c["h1"].status().counters.values)
        assert counters.get("rejected_name_mismatch", 0) == 0 and counters.get("rejected_tls_handshake", 0) == 0
