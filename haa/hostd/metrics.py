"""The Prometheus metrics of one haa-hostd, read from its `HostRuntime` at scrape time (docs/metrics.md).

`host_registry(rt, loop)` returns a fresh `CollectorRegistry` holding a `HostCollector` for `rt` (run on the
daemon's loop by `haa.metrics.http.OnLoop`) and prometheus_client's `ProcessCollector`
(`process_cpu_seconds_total`, `process_resident_memory_bytes`, ...). `HostCollector.collect()` only reads what the
daemon already keeps; the sources are the statistics sampler's (haa.hostd.sampler), and the daemon hands it the
sampler's histogram bounds and DDB key-prefix rule (this module stays below haa.lab.stats: .importlinter):

* group — `haa_member`, `haa_view`, `haa_members`, `haa_leader` (this host is the leader), `haa_incarnation`;
* failure detector — `haa_suspected{peer}` (1 while this host's UFD suspects it, thesis §4.4), `haa_suspicions`
  (how many peers are suspected now), `haa_ufd_heartbeat_period_seconds{peer}` (the η each peer was asked for);
* OAC — `haa_oac_propose_to_decide_seconds` (transactions this host proposed) and
  `haa_oac_decide_to_deliver_seconds` (every transaction delivered here) histograms, folded at each scrape from
  the runtime's latency samples (`HostRuntime.propose_to_decide` / `decide_to_deliver`, the same the sampler
  reads); `haa_oac_transactions_total{result}`, `haa_oac_delivered_total`;
* DDB — `haa_ddb_objects`, `haa_ddb_bytes`, `haa_ddb_bytes_by_prefix{prefix}` (`haa.hostd.sampler.ddb_prefix`),
  `haa_ddb_seq`, recomputed only when the replica changed;
* host messages — `haa_messages_sent_total{kind}` / `haa_message_bytes_sent_total{kind}` (and `_received_`),
  the transport's per-kind counters; `haa_link_messages_sent_total{peer}` and `haa_link_messages_received_total
  {peer}` (the host-link sequence numbers of the current incarnations), `haa_link_queued{peer}`,
  `haa_link_connected{peer}`;
* agents — `haa_agents{state}` (this host's agents by phase: the state `haactl agent list` shows),
  `haa_agent_processes{state}` (its agent processes by supervisor state), `haa_agent_table{status}`
  (the replicated agent table by status: the same on every member), `haa_agent_cpu_ratio{agent,type}`,
  `haa_agent_rss_bytes`, `haa_agent_mailbox`, `haa_agent_handled_total`, `haa_agent_messages_sent_total
  {agent,peer}` / `haa_agent_bytes_sent_total{agent,peer}` (and `_received_`: the supervisor's per-peer
  counters, peers by agent name), `haa_agent_backup_bytes`;
* allocation, transfers, recoveries — `haa_allocation_sessions_total` (the agent table's session id: sessions
  committed in the group, Alg. 4), `haa_agent_events_total{event}` (this host's agent timeline: `thawed` is a
  transfer arriving here, `recovered` a recovery here, `crashed`, `freezing`, ...), `haa_agents_spawned_total`,
  `haa_agents_failed_total`;
* everything else the runtime, transport and core count (rejections, link errors, sequencer batches, ...) —
  `haa_host_events_total{counter}`.

Agent names (A6.2.1) are the `agent` label: an agent keeps its name across transfers and recoveries.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

from prometheus_client import CollectorRegistry, ProcessCollector
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from haa.metrics.http import OnLoop
from haa.metrics.latency import Histogram, SampleTail

if TYPE_CHECKING:
    import asyncio

    from haa.hostd.agentdriver import AgentDriver
    from haa.hostd.runtime import HostRuntime

#: histogram bucket upper bounds, seconds, when the daemon gives none (it gives the statistics sampler's,
#: haa.hostd.sampler.HIST_BOUNDS_MS, so that metrics and stats.jsonl bin alike)
BUCKETS_S = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)
#: counter-name prefixes exported with their own metric (not again in haa_host_events_total)
_PER_KIND = ("tx_msgs.", "tx_bytes.", "rx_msgs.", "rx_bytes.")
_OWN = frozenset({"oac_committed", "oac_aborted", "oac_delivered"})


class HostCollector:
    """The metrics of one haa-hostd (module docstring); register it in the daemon's own registry."""

    def __init__(self, rt: HostRuntime, bounds_s: tuple[float, ...] = BUCKETS_S,
                 prefix_of: Callable[[str], str] = lambda key: key.split("/", 1)[0],
                 agents: AgentDriver | None = None) -> None:
        self.rt = rt
        self.agents = agents
        self.prefix_of = prefix_of
        self.p2d = Histogram(bounds_s)
        self.d2d = Histogram(bounds_s)
        self._p2d_tail = SampleTail()
        self._d2d_tail = SampleTail()
        self._events: Counter[str] = Counter()
        self._last_event: object | None = None
        self._ddb_key: tuple[int, int] | None = None
        self._ddb: tuple[int, int, dict[str, int]] = (0, 0, {})

    # ------------------------------------------------------------------ collect

    def collect(self) -> Iterator[Metric]:
        rt = self.rt
        yield GaugeMetricFamily("haa_incarnation", "this host's incarnation number", value=rt.ident.inc)
        yield from self._group()
        yield from self._oac()
        yield from self._transport()
        yield from self._agents()
        yield from self._counters()

    def _group(self) -> Iterator[Metric]:
        rt = self.rt
        core = rt.core
        node = rt.mnode
        if node is not None:
            st = node.state
            lead = st.leader()
            yield GaugeMetricFamily("haa_member", "1 while this host is a member of the group",
                                    value=int(bool(node.is_member())))
            yield GaugeMetricFamily("haa_view", "the view number this host has installed", value=st.view)
            yield GaugeMetricFamily("haa_members", "members of the view this host has installed",
                                    value=len(st.members))
            yield GaugeMetricFamily("haa_leader", "1 while this host is the group's leader",
                                    value=int(lead is not None and lead.name == rt.name))
            yield from self._ddb_metrics(st.ddb)
        if core is not None:
            sus = GaugeMetricFamily("haa_suspected", "1 while this host's failure detector suspects the peer",
                                    labels=["peer"])
            eta = GaugeMetricFamily("haa_ufd_heartbeat_period_seconds",
                                    "the heartbeat period this host asked the peer for (eta, thesis §4.4)",
                                    labels=["peer"])
            n = 0
            for q, p in sorted(core.peers.items()):
                sus.add_metric([q], int(bool(p.suspected)))
                n += bool(p.suspected)
                if p.observer is not None:
                    eta.add_metric([q], p.observer.eta)
            yield sus
            yield eta
            yield GaugeMetricFamily("haa_suspicions", "peers this host's failure detector suspects now", value=n)

    def _ddb_metrics(self, ddb: Any) -> Iterator[Metric]:
        key = (id(ddb), ddb.seq)
        if key != self._ddb_key:  # recomputed only when the replica changed
            by: Counter[str] = Counter()
            total = 0
            for k, obj in ddb._objects.items():
                by[self.prefix_of(k)] += obj.size
                total += obj.size
            self._ddb = (ddb.size, total, dict(by))
            self._ddb_key = key
        objects, total, by_prefix = self._ddb
        yield GaugeMetricFamily("haa_ddb_objects", "objects in this host's DDB replica", value=objects)
        yield GaugeMetricFamily("haa_ddb_bytes", "bytes of the objects in this host's DDB replica", value=total)
        g = GaugeMetricFamily("haa_ddb_bytes_by_prefix", "DDB bytes per key prefix (slam/map, demo, ...)",
                              labels=["prefix"])
        for prefix, b in sorted(by_prefix.items()):
            g.add_metric([prefix], b)
        yield g
        yield GaugeMetricFamily("haa_ddb_seq", "DDB batches applied to this replica (its sequence number)",
                                value=ddb.seq)

    def _oac(self) -> Iterator[Metric]:
        rt = self.rt
        c = rt.counters
        self.d2d.add(self._d2d_tail.new_by_count(rt.proposals.decide_to_deliver, c.get("oac_delivered", 0)))
        self.p2d.add(self._p2d_tail.new_by_identity(rt.proposals.propose_to_decide))
        yield self.p2d.family("haa_oac_propose_to_decide_seconds",
                              "OAC latency from proposal to decision, transactions this host proposed (Alg. 1)")
        yield self.d2d.family("haa_oac_decide_to_deliver_seconds",
                              "OAC latency from decision to delivery in total order, every transaction delivered here")
        tx = CounterMetricFamily("haa_oac_transactions", "OAC transactions this host decided", labels=["result"])
        tx.add_metric(["committed"], c.get("oac_committed", 0))
        tx.add_metric(["aborted"], c.get("oac_aborted", 0))
        yield tx
        yield CounterMetricFamily("haa_oac_delivered", "OAC transactions delivered here in total order",
                                  value=c.get("oac_delivered", 0))

    def _transport(self) -> Iterator[Metric]:
        rt = self.rt
        fams = {
            "tx_msgs.": CounterMetricFamily("haa_messages_sent", "host messages sent, by kind", labels=["kind"]),
            "tx_bytes.": CounterMetricFamily("haa_message_bytes_sent", "host message bytes sent, by kind",
                                             labels=["kind"]),
            "rx_msgs.": CounterMetricFamily("haa_messages_received", "host messages received, by kind",
                                            labels=["kind"]),
            "rx_bytes.": CounterMetricFamily("haa_message_bytes_received", "host message bytes received, by kind",
                                             labels=["kind"]),
        }
        for k, v in sorted(rt.counters.items()):
            prefix, dot, kind = k.partition(".")
            fam = fams.get(prefix + dot) if dot else None
            if fam is not None:
                fam.add_metric([kind], v)
        yield from fams.values()
        t = rt.transport
        sent = CounterMetricFamily("haa_link_messages_sent",
                                   "messages queued on the host link to the peer (this incarnation's link)",
                                   labels=["peer"])
        queued = GaugeMetricFamily("haa_link_queued", "messages on the link to the peer not yet acknowledged",
                                   labels=["peer"])
        conn = GaugeMetricFamily("haa_link_connected", "1 while the link to the peer is connected", labels=["peer"])
        for q, link in sorted(t.links.items()):
            sent.add_metric([q], max(0, link.next_seq - 1))
            queued.add_metric([q], len(link.pending) + len(link.unacked))
            conn.add_metric([q], int(bool(link.connected)))
        yield sent
        yield queued
        yield conn
        recv = CounterMetricFamily("haa_link_messages_received",
                                   "messages delivered from the peer's host link (its current incarnation)",
                                   labels=["peer"])
        # the transport's per-sender receive state (read only): the highest link sequence number delivered
        for q, rx in sorted(getattr(t, "_rx", {}).items()):
            recv.add_metric([q], rx.last)
        yield recv

    def _agents(self) -> Iterator[Metric]:
        rt = self.rt
        node = rt.mnode
        names: dict[str, str] = {}
        table = None
        if node is not None and rt.config.agents:
            table = node.state.agents
            names = {r.id: r.name for r in table}
        if table is not None:
            by_status: Counter[str] = Counter()
            backup = 0
            for r in table:
                by_status[r.status] += 1
                backup += len(r.backup) if r.backup else 0
            g = GaugeMetricFamily("haa_agent_table", "agents of the replicated agent table by status",
                                  labels=["status"])
            for s, n in sorted(by_status.items()):
                g.add_metric([s], n)
            yield g
            yield GaugeMetricFamily("haa_agent_backup_bytes", "bytes of agent backups in the agent table",
                                    value=backup)
            yield CounterMetricFamily("haa_allocation_sessions",
                                      "allocation sessions committed in the group (the agent table's session id, "
                                      "Alg. 4)", value=table.ses_id)
        drv = self.agents
        if drv is None:
            return
        local = getattr(rt.node, "local", None)  # the agent layer's instances here (AgentNode.local)
        if isinstance(local, dict):
            phases: Counter[str] = Counter(loc.phase for loc in local.values())
            g = GaugeMetricFamily("haa_agents", "agents on this host by phase (the `agent list` state)",
                                  labels=["state"])
            for s, n in sorted(phases.items()):
                g.add_metric([s], n)
            yield g
        stats = drv.sup.stats()
        by_state: Counter[str] = Counter(st.state for st in stats.values())
        g = GaugeMetricFamily("haa_agent_processes", "agent processes on this host by supervisor state",
                              labels=["state"])
        for s, n in sorted(by_state.items()):
            g.add_metric([s], n)
        yield g
        per: dict[tuple[str, str], list[float]] = {}
        pairs: dict[tuple[str, str, str], list[int]] = {}  # (agent, peer, "out" | "in") -> [messages, bytes]
        for st in stats.values():
            row = per.setdefault((st.name, st.type_name), [0.0, 0.0, 0.0, 0.0])
            row[0] += st.cpu
            row[1] += st.rss
            row[2] += st.mailbox
            row[3] += st.handled
            for d, (msgs, byts) in (("out", (st.msgs_out, st.bytes_out)), ("in", (st.msgs_in, st.bytes_in))):
                for peer, n in msgs.items():
                    if not peer:
                        continue
                    p = pairs.setdefault((st.name, names.get(peer, peer[:8]), d), [0, 0])
                    p[0] += n
                    p[1] += byts.get(peer, 0)
        fams: list[GaugeMetricFamily | CounterMetricFamily] = [
            GaugeMetricFamily("haa_agent_cpu_ratio", "share of one core the agent process used lately",
                              labels=["agent", "type"]),
            GaugeMetricFamily("haa_agent_rss_bytes", "resident memory of the agent process", labels=["agent", "type"]),
            GaugeMetricFamily("haa_agent_mailbox", "items waiting in the agent's mailbox", labels=["agent", "type"]),
            CounterMetricFamily("haa_agent_handled", "inputs the agent process handled", labels=["agent", "type"]),
        ]
        for (name, typ), row in sorted(per.items()):
            for fam, v in zip(fams, row, strict=True):
                fam.add_metric([name, typ], v)
        yield from fams
        ms = CounterMetricFamily("haa_agent_messages_sent", "messages the agent sent to the peer agent",
                                 labels=["agent", "peer"])
        bs = CounterMetricFamily("haa_agent_bytes_sent", "payload bytes the agent sent to the peer agent",
                                 labels=["agent", "peer"])
        mr = CounterMetricFamily("haa_agent_messages_received", "messages the agent received from the peer agent",
                                 labels=["agent", "peer"])
        br = CounterMetricFamily("haa_agent_bytes_received", "payload bytes the agent received from the peer agent",
                                 labels=["agent", "peer"])
        for (name, peer, d), (n, b) in sorted(pairs.items()):
            (ms if d == "out" else mr).add_metric([name, peer], n)
            (bs if d == "out" else br).add_metric([name, peer], b)
        yield from (ms, bs, mr, br)
        # the agent timeline of this host, counted by event as it grows (the sampler's `timeline`)
        last = self._last_event
        fresh: list[str] = []
        for item in reversed(drv.timeline):
            if item is last:
                break
            fresh.append(item["event"])
        if drv.timeline:
            self._last_event = drv.timeline[-1]
        self._events.update(fresh)
        ev = CounterMetricFamily("haa_agent_events", "agent timeline events on this host (thawed: a transfer "
                                 "arrived; recovered: a recovery)", labels=["event"])
        for e, n in sorted(self._events.items()):
            ev.add_metric([e], n)
        yield ev
        st2 = drv.status()
        yield CounterMetricFamily("haa_agents_spawned", "agent processes this host spawned", value=st2["spawned"])
        yield CounterMetricFamily("haa_agents_failed", "agent processes that failed to start here",
                                  value=st2["failed"])

    def _counters(self) -> Iterator[Metric]:
        fam = CounterMetricFamily("haa_host_events", "everything else the runtime, transport and core count",
                                  labels=["counter"])
        for k, v in sorted(self.rt.all_counters().items()):
            if k.startswith(_PER_KIND) or k in _OWN:
                continue
            fam.add_metric([k], v)
        yield fam


def host_registry(rt: HostRuntime, loop: asyncio.AbstractEventLoop, bounds_s: tuple[float, ...] = BUCKETS_S,
                  prefix_of: Callable[[str], str] | None = None,
                  agents: AgentDriver | None = None) -> CollectorRegistry:
    """A fresh registry with the host's collector (run on `loop`, the daemon's) and the process collector.
    `bounds_s`, `prefix_of`: the histogram buckets and the DDB key-prefix rule (the daemon passes the statistics
    sampler's); `agents`: the host's agent driver (the daemon's), None without agents."""
    reg = CollectorRegistry(auto_describe=False)
    collector = (HostCollector(rt, bounds_s, prefix_of, agents=agents) if prefix_of
                 else HostCollector(rt, bounds_s, agents=agents))
    reg.register(OnLoop(loop, [collector]))
    ProcessCollector(registry=reg)
    return reg
