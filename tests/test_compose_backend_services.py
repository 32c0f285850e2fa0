"""ComposeBackend: which services of a compose file are hosts (no docker needed: a fake SDK client).

compose/compose.yaml has the ten hosts h1..h10 and the simulator `sim` (profile `sim`, entrypoint haa-sim,
no `--name`). The simulator is not a host: `cluster status` (hosts()) must not list its container and
`next_name()` (`haactl host add` without a name) must never pick it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from haa.cluster.backend import ClusterError
from haa.cluster.compose_backend import LABEL_PROJECT, LABEL_SERVICE, ComposeBackend, host_service

REPO = Path(__file__).resolve().parents[1]
COMPOSE = REPO / "compose" / "compose.yaml"
HOSTS = [f"h{i}" for i in range(1, 11)]


class FakeContainer:
    def __init__(self, project: str, service: str, port: int, status: str = "running") -> None:
        self.labels = {LABEL_PROJECT: project, LABEL_SERVICE: service}
        self.status = status
        self.short_id = f"c-{service}"
        self.attrs = {
            "State": {"Status": status, "ExitCode": 0},
            "HostConfig": {"PortBindings": {"7000/tcp": [{"HostIp": "127.0.0.1", "HostPort": str(port)}]}},
        }


class FakeContainers:
    def __init__(self, items: list[FakeContainer]) -> None:
        self.items = items

    def list(self, all: bool = False, filters: dict[str, Any] | None = None) -> list[FakeContainer]:
        label = (filters or {}).get("label", "")
        key, _, value = label.partition("=")
        return [c for c in self.items if not label or c.labels.get(key) == value]


class FakeDocker:
    def __init__(self, items: list[FakeContainer]) -> None:
        self.containers = FakeContainers(items)


def backend_with(names: list[str], project: str = "haa", extra: list[FakeContainer] | None = None) -> ComposeBackend:
    b = ComposeBackend(COMPOSE, project=project)
    items = [FakeContainer(project, n, 17000 + i) for i, n in enumerate(names, 1)]
    b._docker = FakeDocker(items + (extra or []))
    return b


def test_the_compose_file_still_has_a_sim_service() -> None:
    # the premise of the tests below: if `sim` goes away, they test nothing
    spec = yaml.safe_load(COMPOSE.read_text())
    assert "sim" in spec["services"] and "--name" not in spec["services"]["sim"]["command"]


def test_only_haa_hostd_services_with_their_own_name_are_hosts() -> None:
    b = ComposeBackend(COMPOSE, project="haa")
    assert sorted(b.services) == sorted(HOSTS)
    assert list(b.other_services) == ["sim"]
    assert b.core_names == ["h1", "h2", "h3"]
    assert b.image() == "haa-hostd:latest"


@pytest.mark.parametrize(
    ("name", "svc", "expect"),
    [
        ("h1", {"command": ["--name", "h1", "--listen", "0.0.0.0:7000"]}, True),
        ("h1", {"command": ["--listen", "0.0.0.0:7000"]}, False),  # no --name
        ("h1", {"command": ["--name", "h2"]}, False),  # another host's name
        ("h1", {"command": ["--listen", "x", "--name"]}, False),  # --name without a value
        ("sim", {"entrypoint": ["/opt/haa/bin/haa-sim"], "command": ["--arena", "small"]}, False),
        ("x", None, False),
        ("x", {}, False),
    ],
)
def test_host_service(name: str, svc: Any, expect: bool) -> None:
    assert host_service(name, svc) is expect


def test_status_does_not_list_a_running_sim_container() -> None:
    sim = FakeContainer("haa", "sim", 17100)
    b = backend_with(HOSTS[:4], extra=[sim])
    assert [h.name for h in b.hosts()] == HOSTS[:4]
    assert "sim" not in b.containers()
    assert b.require_hosts()  # the cluster is there
    with pytest.raises(ClusterError, match=r"unknown host 'sim'"):
        b.host("sim")


def test_next_name_never_picks_sim() -> None:
    sim = FakeContainer("haa", "sim", 17100)
    b = backend_with(HOSTS[:4], extra=[sim])
    assert b.next_name() == "h5"
    b = backend_with([n for n in HOSTS if n != "h7"])
    assert b.next_name() == "h7"
    b = backend_with(HOSTS)  # every host has a container: there is no next host, and sim is not one
    with pytest.raises(ClusterError, match="every host"):
        b.next_name()


def test_other_projects_containers_are_not_ours() -> None:
    other = [FakeContainer("someone-else", n, 18000 + i) for i, n in enumerate(HOSTS, 1)]
    b = backend_with(HOSTS[:2], extra=other)
    assert [h.name for h in b.hosts()] == HOSTS[:2]
    assert b.next_name() == "h3"


def test_up_refuses_more_hosts_than_the_file_has_without_counting_sim() -> None:
    b = backend_with([])
    with pytest.raises(ClusterError, match="defines 10 hosts"):
        b.up(11)


def test_a_compose_file_without_any_host_is_refused(tmp_path: Path) -> None:
    f = tmp_path / "compose.yaml"
    f.write_text(yaml.safe_dump({"services": {"sim": {"image": "x", "command": ["--arena", "small"]}}}))
    with pytest.raises(ClusterError, match="no service runs haa-hostd"):
        ComposeBackend(f)
