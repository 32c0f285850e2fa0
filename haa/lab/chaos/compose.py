"""Chaos runs on the docker compose cluster (`haactl chaos run PLAN --compose`, docs/chaos.md "Compose").

`ComposeChaosCluster` is the `haa.lab.chaos.run.ChaosCluster` of the compose cluster: it brings up `plan.hosts`
host services of the compose file (h1..hN; refused while the project already runs — a chaos run starts
from fresh data dirs), with HAA_AGENT_MODULES naming the workload's module (compose/compose.yaml passes it
on to every host); at the end it stops every container (`compose stop`: the hosts leave gracefully), copies
each host's JSON-lines log out of its data dir through the docker SDK (`get_archive`, which reads stopped
and killed containers alike: what a host persisted survives its crash), collects the stats bundles when
asked, and removes the project (`compose down`).

`PartitionCompose` adds what partitions need to `ComposeBackend`: `disconnect(h)` is `docker network
disconnect` of h's container from the project network (h keeps running, isolated from every other host and
from its published control port), `reconnect(h)` connects it again with the same fixed address and its
service name as alias (the name peers resolve). tc netem (link delay/loss) is not offered: this machine's
kernel has no netem qdisc (`tc qdisc add ... netem` -> "Specified qdisc kind is unknown"), so the
containers get no NET_ADMIN either.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

from haa.cluster.backend import ClusterError, natural_key
from haa.cluster.compose_backend import ComposeBackend
from haa.lab.chaos.plan import Plan
from haa.lab.chaos.run import Progress, agent_modules
from haa.lab.chaos.workload import WORKLOAD_MODULE


class PartitionCompose(ComposeBackend):
    """`ComposeBackend` with network partitions (module docstring)."""

    def __init__(self, compose_file: Path | None = None, project: str | None = None) -> None:
        super().__init__(compose_file, project)
        #: host -> (network name, its IPv4 address there, aliases) while it is cut off
        self.cut: dict[str, tuple[str, str, list[str]]] = {}

    def disconnect(self, name: str) -> None:
        if name in self.cut:
            raise ClusterError(f"host {name} is already cut off the network")
        c = self.container(name)
        nets: dict[str, Any] = (c.attrs.get("NetworkSettings") or {}).get("Networks") or {}
        if not nets:
            raise ClusterError(f"host {name}'s container is on no network")
        net_name, cfg = next(iter(nets.items()))
        ip = ((cfg.get("IPAMConfig") or {}).get("IPv4Address")) or cfg.get("IPAddress") or ""
        aliases = [a for a in (cfg.get("Aliases") or []) if a == name] or [name]
        try:
            self.docker.networks.get(net_name).disconnect(c, force=True)
        except Exception as e:  # docker.errors.APIError
            raise ClusterError(f"docker network disconnect {net_name} {name}: {e}") from None
        self.cut[name] = (net_name, ip, aliases)

    def reconnect(self, name: str) -> None:
        if name not in self.cut:
            return
        net_name, ip, aliases = self.cut[name]
        try:
            self.docker.networks.get(net_name).connect(self.container(name), ipv4_address=ip or None,
                                                       aliases=aliases)
        except Exception as e:
            raise ClusterError(f"docker network connect {net_name} {name} --ip {ip}: {e}") from None
        del self.cut[name]


class ComposeChaosCluster:
    """The compose cluster as a `ChaosCluster` (module docstring); `bundles_to`: collect the hosts' stats
    bundles into that directory before the containers are removed."""

    def __init__(self, compose_file: Path | None = None, project: str | None = None,
                 bundles_to: Path | None = None) -> None:
        self.backend = PartitionCompose(compose_file, project)
        self.bundles_to = bundles_to
        self.bundle_note = ""

    def problems(self, plan: Plan) -> list[str]:
        out = []
        n = len(self.backend.services)
        if plan.hosts > n:
            out.append(f"hosts: {plan.hosts}, but the compose file {self.backend.file} defines {n} hosts")
        if plan.hostd_args:
            out.append("hostd_args: not available with --compose (the compose file gives the hosts' command lines)")
        if plan.mutation:
            out.append("mutation: local cluster only (the mutated hosts are started from this checkout)")
        return out

    def start(self, plan: Plan, progress: Progress) -> list[str]:
        b = self.backend
        running = [h.name for h in b.hosts() if h.up]
        if running:  # never take down a cluster this run did not start
            raise ClusterError(f"the {b.describe()} is running ({', '.join(running)}): a chaos run brings up its own; "
                               "`haactl cluster down --compose` first (or another project: HAA_COMPOSE_PROJECT)")
        progress(f"starting {plan.hosts} hosts of {b.describe()}")
        try:
            with agent_modules(WORKLOAD_MODULE):
                return b.up(plan.hosts, log=progress)
        except ClusterError:
            with contextlib.suppress(ClusterError):
                b.down(grace=1.0)
            raise

    def stop(self, out: Path, progress: Progress) -> None:
        from haa.lab.stats.collect import collect_quietly, read_host

        b = self.backend
        progress("stopping the containers")
        try:
            for name in list(b.cut):
                b.reconnect(name)
            b.compose("stop", "--timeout", "5")
            d = out / "hosts"
            d.mkdir(parents=True, exist_ok=True)
            for h in sorted(b.hosts(), key=lambda h: natural_key(h.name)):
                log = read_host(b, h).files.get("log")
                if log:
                    (d / f"{h.name}.jsonl").write_bytes(log)
            if self.bundles_to is not None:
                res = collect_quietly(b, self.bundles_to)
                self.bundle_note = res if isinstance(res, str) else f"stats bundles of {len(res.bundles)} hosts"
        finally:
            b.down(grace=1.0)
