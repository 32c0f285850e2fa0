"""Clusters of haa-hostd hosts as an operator sees them (moved here from haactl so that libraries such as the
mission runner can use them; haa must not import haactl).

* `haa.cluster.backend` — `Backend`: what every cluster offers (hosts, status fan-out, formation, graceful
  leave) and `ClusterError`, the one-line operator error.
* `haa.cluster.local_backend` — `LocalBackend`: haa-hostd processes on loopback recorded in a state file.
* `haa.cluster.compose_backend` — `ComposeBackend`: the docker compose cluster of compose/compose.yaml.
* `haa.cluster.swarm_backend` — `SwarmBackend`: the Docker Swarm stack of compose/stack.yaml.
* `haa.cluster.procs` — free ports, the haa-hostd command line, the token file, starting one haa-hostd process.
* `haa.cluster.hostprocs` — local hosts for benchmarks and tests: `HostProc` / `MemberHost` (one process),
  `MemberGroup` (a membership-mode group), `LocalCluster` (a static full mesh), `wait_for`.
* `haa.cluster.events` — the allocation timeline from every host's persisted log (parser, merge, attribution).
* `haa.cluster.feed` — `EventFeed`: that timeline merged with the live `AgentEvents` streams of every host.
* `haa.cluster.status` — `gather_status`: every host's Status, the agreed group, whether views and DDBs agree.
* `haa.cluster.agents` — every agent as the whole cluster sees it (`merge_agents`).
"""
