"""`haa-hostd`: the host daemon's command line (console script `haa-hostd` -> `haa.hostd.daemon:main`).

Membership mode (the normal one; Alg. 3 group membership, the replicated DDB):

    haa-hostd --name h4 --listen 0.0.0.0:7000 --core h1=h1:7000,h2=h2:7000,h3=h3:7000 \\
              --token-file cluster.token [--advertise h4:7000] [--data-dir /var/lib/haa/h4] [--config h4.yaml]

Static mode (a fixed full mesh running OAC without membership: the AP-1 benchmark and the demo):

    haa-hostd --name h1 --listen 127.0.0.1:7001 --peers h2=127.0.0.1:7002,h3=127.0.0.1:7003 --token-file F

Every option can also be given as environment variable `HAA_<OPTION>` (`HAA_CORE`, `HAA_TOKEN_FILE`, ...)
or as a key of a YAML file (`--config` / `HAA_CONFIG`; keys are the option names, plus a `membership:`
section with the Alg. 3 tunables of `NodeConfig`); the command line wins over the environment, the
environment over the file. The settings are validated by a pydantic model (`HostSettings`); anything wrong —
an unreadable or empty token file, broken YAML, a file over its limits (256 KiB, 64 levels, 10,000 nodes,
no duplicate keys: `haa.files`, docs/limits.md), an unknown key, more than 1,000 `--core` or `--peers`
entries, a bad address, duplicate names, both `--peers` and `--core`, c_f or c_H out of range, a
non-positive timeout — ends the process with exit code 2
and one line on stderr naming the option and the reason, before anything starts. A port that cannot be
bound exits with code 1.

`--advertise` is the address the other hosts connect to; by default `--listen`, with a wildcard host
replaced by this machine's host name. `--data-dir` keeps the JSON-lines log, the statistics sampler's time
series (`stats.jsonl` and `config.json`, every `--stats-period` s, default 1, 0 = off: haa.hostd.sampler,
docs/stats.md), the last incarnation and the hosts of the last view (`known_hosts.json`): a restarted host
applies to them as well as to the core processes and never founds a group of its own (`--forget-group` drops
them: needed only if every host of the group was lost).
`--metrics-port P` serves Prometheus metrics on http://<--listen's host>:P/metrics (haa.metrics,
docs/metrics.md; 0, the default, = none).

`--tls-dir DIR` turns on mutual TLS (haa.tls, docs/deploy.md): DIR holds the cluster CA's `ca.pem` and this
host's `host.pem` / `host.key` (made by `haactl cluster up --tls`); the certificate must be for `--name`,
the key not readable by others. Links and the control API then need a certificate of that CA.

`--record-dir DIR` (env HAA_RECORD_DIR) makes every agent this host runs record its inputs and outputs into
DIR (AgentPlayback: haa.lab.playback, docs/playback.md); the agent processes inherit it as HAA_RECORD_DIR, and the
recorder as their tap (HAA_AGENT_TAP=haa.sdk.recorder:from_env, loaded by name: haa.sdk.tap).

The QoS options are the failure detector's targets (thesis §4.4.2): detection time bound T_D^U, mean
mistake recurrence time lower bound T_MR^L and mean mistake duration upper bound T_M^U, in seconds
(default `haa.core.ufd.qos.CLUSTER_QOS`). SIGTERM and SIGINT are a graceful leave (membership mode: the group
removes this host first, for at most `--leave-timeout` seconds), then a graceful shutdown (links closed, the
final delivered count and hash logged); a second signal skips the wait. The event loop is uvloop; set
HAA_EVENT_LOOP=asyncio for the standard library loop.
"""

from __future__ import annotations

import argparse
import asyncio
import errno
import fcntl
import logging
import os
import re
import signal
import sys
from collections.abc import Coroutine
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, NoReturn

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from haa import files
from haa import tls as tlsmod
from haa.core.agents.agentnode import AgentConfig
from haa.core.allocation.specs import MAX_CAPACITY, MIN_CAPACITY
from haa.core.host.hostcore import CoreConfig
from haa.core.membership.membership import NodeConfig
from haa.core.ufd.qos import CLUSTER_QOS, QosTargets
from haa.core.ufd.ufd import UfdConfig
from haa.hostd.agentdriver import AgentDriver
from haa.hostd.control import HostControlService
from haa.hostd.logs import LOGGER_NAME, log_event
from haa.hostd.outcomes import WriteFailed
from haa.hostd.runtime import HostRuntime, RuntimeConfig
from haa.hostd.sampler import StatsSampler
from haa.hostd.transport import NAME_RE
from haa.sdk.tap import TAP_ENV

#: the tap factory of the agent processes when the host records (haa.sdk.tap: named, imported at run time
#: in the agent process; haa.lab.playback sits above the host's runtime)
RECORDER_TAP = "haa.sdk.recorder:from_env"

PROG = "haa-hostd"
log = logging.getLogger(LOGGER_NAME + ".daemon")
_HOST_RE = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9]([A-Za-z0-9.-]{0,251}[A-Za-z0-9])?)$")
DEFAULT_INITIAL_PERIOD = UfdConfig().initial_period
#: at most this many entries in --core and in --peers: every one costs the event loop setup work at start
#: (a failure detector each, ~0.5 ms), so a list of a million kept the loop, and SIGTERM, waiting for minutes
MAX_HOSTS = 1000
#: --config file limits (haa.files): a settings file is small
CONFIG_MAX_BYTES = 256 << 10
CONFIG_MAX_NODES = 10_000
#: --hardware: at most this many items of at most MAX_HARDWARE_CHARS characters each
MAX_HARDWARE = 64
MAX_HARDWARE_CHARS = 64
#: longest HOST:PORT (a DNS name is at most 253 characters) and --data-dir path
MAX_ADDRESS_CHARS = 300
MAX_PATH_CHARS = 4096


def check_address(value: str, allow_port_zero: bool = False) -> str:
    """Validate "HOST:PORT" (HOST a name, an IPv4 address or a bracketed IPv6 address)."""
    if len(value) > MAX_ADDRESS_CHARS:
        raise ValueError(f"an address of {len(value)} characters (at most {MAX_ADDRESS_CHARS})")
    host, sep, port = value.rpartition(":")
    if not sep or not host:
        raise ValueError(f"{value!r} is not HOST:PORT")
    if not _HOST_RE.match(host):
        raise ValueError(f"{value!r}: bad host {host!r}")
    if not port.isdigit() or not (0 if allow_port_zero else 1) <= int(port) <= 65535:
        raise ValueError(f"{value!r}: bad port {port!r}")
    return value


def parse_peers(text: str) -> list[tuple[str, str]]:
    """Parse "NAME=HOST:PORT,NAME=HOST:PORT,..." (an empty string is a host without peers; at most
    MAX_HOSTS entries)."""
    if text.count(",") >= MAX_HOSTS and len([s for s in text.split(",") if s.strip()]) > MAX_HOSTS:
        raise ValueError(f"more than {MAX_HOSTS} hosts")
    out: list[tuple[str, str]] = []
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        name, sep, addr = item.partition("=")
        if not sep:
            raise ValueError(f"{files.one_line(repr(item), 100)} is not NAME=HOST:PORT")
        out.append((name.strip(), addr.strip()))
    return out


class MembershipSettings(BaseModel):
    """Alg. 3 tunables (`membership:` section of the YAML file; see `haa.core.membership.membership.NodeConfig`)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    c_f: int | None = Field(default=None, ge=0)
    c_h: int | None = Field(default=None, ge=1)
    formation_timeout: float = Field(default=NodeConfig().formation_timeout, gt=0, allow_inf_nan=False)
    formation_retry: float = Field(default=NodeConfig().formation_retry, gt=0, allow_inf_nan=False)
    discovery: float = Field(default=NodeConfig().discovery, gt=0, allow_inf_nan=False)
    reapply: float = Field(default=NodeConfig().reapply, gt=0, allow_inf_nan=False)
    catchup_timeout: float = Field(default=NodeConfig().catchup_timeout, gt=0, allow_inf_nan=False)
    retry_backoff: float = Field(default=NodeConfig().retry_backoff, gt=0, allow_inf_nan=False)
    max_write_attempts: int = Field(default=NodeConfig().max_write_attempts, ge=1)
    #: DDB writes through the sequencer (docs/oac.md); false: every member proposes its own (Alg. 3 as printed)
    sequencer: bool = NodeConfig().sequencer
    seq_inflight: int = Field(default=NodeConfig().seq_inflight, ge=1, le=64)


class HostSettings(BaseModel):
    """Everything haa-hostd needs to start, validated."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    listen: str
    peers: list[tuple[str, str]] = Field(default_factory=list, max_length=MAX_HOSTS)
    core: list[tuple[str, str]] = Field(default_factory=list, max_length=MAX_HOSTS)
    advertise: str | None = None
    token: SecretStr
    data_dir: Path
    qos_td: float = Field(default=CLUSTER_QOS.td_upper, gt=0, allow_inf_nan=False)
    qos_tmr: float = Field(default=CLUSTER_QOS.tmr_lower, gt=0, allow_inf_nan=False)
    qos_tm: float = Field(default=CLUSTER_QOS.tm_upper, gt=0, allow_inf_nan=False)
    exclude_after: float = Field(default=CoreConfig().exclude_after, gt=0, allow_inf_nan=False)
    leave_timeout: float = Field(default=3.0, gt=0, allow_inf_nan=False)
    forget_group: bool = False
    #: heartbeats as UDP datagrams on the listen port (docs/transport.md); off: on the host-link streams
    datagram_heartbeats: bool = True
    #: what carries the host links: gRPC streams, or framed TCP connections on `link_port` (haa.hostd.tcplink;
    #: every host of a cluster must use the same; docs/transport.md, "The TCP host link")
    host_link: Literal["grpc", "tcp"] = "grpc"
    link_port: int = Field(default=0, ge=0, le=65535)
    #: the agent layer (membership mode): off with --no-agents
    agents: bool = True
    # the allocator's bounds (docs/limits.md, "Agent and host numbers"): a capacity outside them is refused here
    capacity: float = Field(default=1.0, ge=MIN_CAPACITY, le=MAX_CAPACITY, allow_inf_nan=False)
    hardware: list[str] = Field(default_factory=list, max_length=MAX_HARDWARE)
    rebalance_period: float = Field(default=30.0, ge=0, allow_inf_nan=False)
    drain_timeout: float = Field(default=10.0, gt=0, allow_inf_nan=False)
    #: an agent instance that dies within this long of its start is a start failure (backed off; docs/limits.md)
    agent_start_grace: float = Field(default=AgentConfig().start_grace, ge=0, le=3600, allow_inf_nan=False)
    agent_hang_timeout: float = Field(default=3.0, gt=0.5, allow_inf_nan=False)
    #: agent types whose modules the fork server imports at start rather than at their first spawn
    preload_agents: list[str] = Field(default_factory=list, max_length=256)
    #: the statistics sampler's period (haa.hostd.sampler: <data dir>/stats.jsonl), s; 0 = no sampling
    stats_period: float = Field(default=1.0, ge=0, le=3600, allow_inf_nan=False)
    #: Prometheus /metrics on this port, bound to --listen's host (haa.metrics, docs/metrics.md); 0 = none
    metrics_port: int = Field(default=0, ge=0, le=65535)
    #: mutual TLS: this host's ca.pem, host.pem, host.key (haa.tls); None = token only
    tls_dir: Path | None = None
    #: AgentPlayback: every agent of this host records into this folder (haa.lab.playback, docs/playback.md)
    record_dir: Path | None = None
    membership: MembershipSettings = Field(default_factory=MembershipSettings)
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    log_stderr: bool = False

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        _check_name(v)
        if not NAME_RE.match(v):
            raise ValueError(f"{v!r} is not a host name (letters, digits, '_', '.', '-'; at most 63)")
        return v

    @field_validator("listen")
    @classmethod
    def _listen(cls, v: str) -> str:
        return check_address(v, allow_port_zero=True)

    @field_validator("advertise")
    @classmethod
    def _advertise(cls, v: str | None) -> str | None:
        return None if v is None else check_address(v)

    @field_validator("peers")
    @classmethod
    def _peers(cls, v: list[tuple[str, str]], info: ValidationInfo) -> list[tuple[str, str]]:
        seen: set[str] = set()
        own = info.data.get("name")
        for name, addr in v:
            _check_name(name)
            if not NAME_RE.match(name):
                raise ValueError(f"{name!r} is not a host name")
            if name == own:
                raise ValueError(f"names this host itself ({own!r})")
            if name in seen:
                raise ValueError(f"duplicate peer name {name!r}")
            seen.add(name)
            check_address(addr)
        return v

    @field_validator("core")
    @classmethod
    def _core(cls, v: list[tuple[str, str]], info: ValidationInfo) -> list[tuple[str, str]]:
        seen: set[str] = set()
        for name, addr in v:
            _check_name(name)
            if not NAME_RE.match(name):
                raise ValueError(f"{name!r} is not a host name")
            if name in seen:
                raise ValueError(f"duplicate core process {name!r}")
            seen.add(name)
            check_address(addr)
        if v and info.data.get("peers"):
            raise ValueError("give either --peers (static mode) or --core (membership), not both")
        return v

    @field_validator("hardware")
    @classmethod
    def _hardware(cls, v: list[str]) -> list[str]:
        for item in v:
            if not item or len(item) > MAX_HARDWARE_CHARS or not item.isprintable():
                raise ValueError(f"an item must be 1 to {MAX_HARDWARE_CHARS} printable characters")
        return v

    @field_validator("data_dir")
    @classmethod
    def _data_dir(cls, v: Path) -> Path:
        if len(str(v)) > MAX_PATH_CHARS:
            raise ValueError(f"a path of more than {MAX_PATH_CHARS} characters")
        return v

    @model_validator(mode="after")
    def _group_sizes(self) -> HostSettings:
        """c_f < c/2 and c_f < c_H <= c (thesis §4.6.1), checked before anything starts."""
        c = len(self.core)
        if c:
            m = self.membership
            c_f = m.c_f if m.c_f is not None else (c - 1) // 2
            if 2 * c_f >= c:
                raise ValueError(f"membership.c_f = {c_f} violates c_f < c/2 with {c} core processes")
            c_h = m.c_h if m.c_h is not None else min(c, c_f + 1)
            if not c_f < c_h <= c:
                raise ValueError(f"membership.c_h = {c_h} violates c_f < c_H <= c (c_f = {c_f}, c = {c})")
        return self

    def runtime_config(self) -> RuntimeConfig:
        qos = QosTargets(td_upper=self.qos_td, tmr_lower=self.qos_tmr, tm_upper=self.qos_tm)
        initial = min(DEFAULT_INITIAL_PERIOD, self.qos_td / 2)  # INITIAL_PERIOD must be below T_D^U
        core = CoreConfig(ufd=UfdConfig(qos=qos, initial_period=initial), exclude_after=self.exclude_after)
        return RuntimeConfig(
            name=self.name,
            listen=self.listen,
            peers=dict(self.peers),
            token=self.token.get_secret_value(),
            core=core,
            data_dir=self.data_dir,
            log_level=getattr(logging, self.log_level.upper()),
            log_stderr=self.log_stderr,
            core_processes=list(self.core),
            advertise=self.advertise or "",
            node=NodeConfig(core=core, **self.membership.model_dump()),
            forget_group=self.forget_group,
            datagram_heartbeats=self.datagram_heartbeats,
            host_link=self.host_link,
            link_port=self.link_port,
            leave_timeout=self.leave_timeout,
            agents=self.agents,
            agent=AgentConfig(
                capacity=self.capacity,
                hardware=tuple(self.hardware),
                rebalance_period=self.rebalance_period,
                drain_timeout=self.drain_timeout,
                start_grace=self.agent_start_grace,
            ),
            agent_hang_timeout=self.agent_hang_timeout,
            preload_agents=list(self.preload_agents),
            tls=tlsmod.load_host(self.tls_dir, self.name) if self.tls_dir is not None else None,
        )


def _check_name(name: str) -> None:
    """Refuse an overlong host name before it is quoted in an error message."""
    if len(name) > 63:
        raise ValueError(f"a host name of {len(name)} characters (at most 63)")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        fail(message)


def fail(message: str, code: int = 2) -> NoReturn:
    print(f"{PROG}: error: {files.one_line(message, 1000)}", file=sys.stderr)
    sys.exit(code)


#: options that may also come from the environment (HAA_<NAME>) and the YAML file
_OPTIONS = (
    "name",
    "listen",
    "peers",
    "core",
    "advertise",
    "token_file",
    "data_dir",
    "qos_td",
    "qos_tmr",
    "qos_tm",
    "exclude_after",
    "leave_timeout",
    "forget_group",
    "datagram_heartbeats",
    "host_link",
    "link_port",
    "log_level",
    "log_stderr",
    "agents",
    "capacity",
    "hardware",
    "rebalance_period",
    "drain_timeout",
    "agent_start_grace",
    "agent_hang_timeout",
    "preload_agents",
    "stats_period",
    "tls_dir",
    "metrics_port",
    "record_dir",
)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog=PROG,
        description="HAA host daemon: group membership, replicated DDB, failure detector, OAC, transport.",
        epilog="Every option can also be given as environment variable HAA_<OPTION> (e.g. HAA_CORE) or as a "
        "key of the --config YAML file (e.g. `core: h1=a:7000,h2=b:7000`); the command line wins over the "
        "environment, the environment over the file.",
    )
    p.add_argument("--config", default=os.environ.get("HAA_CONFIG"), help="YAML settings file (env HAA_CONFIG)")
    p.add_argument("--name", help="this host's name")
    p.add_argument("--listen", help="HOST:PORT to serve on")
    p.add_argument("--core", help="NAME=HOST:PORT,... the ordered core process list (membership mode)")
    p.add_argument("--advertise", help="HOST:PORT other hosts reach this one at (default: --listen)")
    p.add_argument("--peers", help="NAME=HOST:PORT,... every other host (static mode: OAC without membership)")
    p.add_argument("--token-file", help="cluster token file")
    p.add_argument("--data-dir", help="logs, incarnation, known hosts (default data/NAME)")
    p.add_argument("--qos-td", type=float, help=f"T_D^U: detection time bound, s ({CLUSTER_QOS.td_upper})")
    p.add_argument("--qos-tmr", type=float, help=f"T_MR^L: mistake recurrence, s ({CLUSTER_QOS.tmr_lower})")
    p.add_argument("--qos-tm", type=float, help=f"T_M^U: mistake duration, s ({CLUSTER_QOS.tm_upper})")
    p.add_argument(
        "--exclude-after", type=float, help=f"exclude a peer suspected for this long, s ({CoreConfig().exclude_after})"
    )
    p.add_argument("--leave-timeout", type=float, help="SIGTERM: wait this long for the graceful leave, s (3)")
    p.add_argument(
        "--forget-group",
        action="store_const",
        const=True,
        help="ignore the hosts a previous life knew (needed when every host of a group was lost)",
    )
    p.add_argument("--stream-heartbeats", dest="datagram_heartbeats", action="store_const", const=False,
                   help="send failure-detector heartbeats on the host-link streams, not as UDP datagrams")
    p.add_argument("--host-link", choices=["grpc", "tcp"],
                   help="what carries the host-to-host links: gRPC streams (default) or framed TCP connections; "
                        "every host of a cluster must use the same (env HAA_HOST_LINK)")
    p.add_argument("--link-port", type=int,
                   help="--host-link tcp: the TCP port of the links on the --listen host (default 0: any free port; "
                        "peers ask the gRPC server for it)")
    p.add_argument("--no-agents", dest="agents", action="store_const", const=False,
                   help="membership mode without the agent layer (no agent processes)")
    p.add_argument("--capacity", type=float, help="processing capacity K_h for the allocation (1.0 = one core)")
    p.add_argument("--hardware", help="comma-separated hardware this host offers agents (e.g. camera,sonar)")
    p.add_argument("--rebalance-period", type=float, help="periodic allocation sessions, s (30; 0 = none)")
    p.add_argument("--drain-timeout", type=float, help="graceful leave: hand agents over for at most this long, s (10)")
    p.add_argument("--agent-start-grace", type=float,
                   help="an agent instance dying within this long of its start is a start failure (backed off), s (10)")
    p.add_argument("--agent-hang-timeout", type=float, help="an agent silent this long is hung, s (3)")
    p.add_argument("--preload-agents", help="comma-separated agent types imported when the agent runtime starts "
                   "instead of at their first spawn (none: every type is imported when first needed)")
    p.add_argument("--stats-period", type=float,
                   help="sample this host's statistics into <data dir>/stats.jsonl every this many s (1; 0 = off)")
    p.add_argument("--metrics-port", type=int,
                   help="serve Prometheus metrics on http://<listen host>:PORT/metrics (0 = off, the default)")
    p.add_argument("--tls-dir", help="mutual TLS: directory with ca.pem, host.pem, host.key (haactl cluster up --tls)")
    p.add_argument("--record-dir", help="every agent of this host records its inputs and outputs into this folder "
                   "(AgentPlayback, docs/playback.md; env HAA_RECORD_DIR)")
    p.add_argument("--log-level", choices=["debug", "info", "warning", "error"])
    p.add_argument("--log-stderr", action="store_const", const=True, help="also write the JSON log lines to stderr")
    return p


def read_token(path: str) -> str:
    """The token of --token-file (at most `haa.files.MAX_TOKEN_BYTES`, UTF-8, not empty)."""
    try:
        token = files.read_text(path, what="token file", max_bytes=files.MAX_TOKEN_BYTES).strip()
    except files.FileError as e:
        if e.os_errno == errno.EISDIR:
            # what docker makes of a bind mount whose source does not exist (compose/token before `make image`)
            raise ValueError(
                f"token file {path} is a directory, not a file: make one first (`make image` writes compose/token; "
                "or put a random line in it), and remove the directory docker created in its place"
            ) from None
        raise ValueError(f"cannot read token file {e}") from None
    if not token:
        raise ValueError(f"token file {path!r} is empty")
    return token


def _read_yaml(path: str) -> dict[str, Any]:
    """The --config file as {option: value}; ValueError (a `haa.files.FileError`, one line) if it is
    unreadable, too large or deep, not UTF-8, broken YAML, has a duplicate key or an unknown option."""
    data = files.load_yaml(
        path, what="config file", max_bytes=CONFIG_MAX_BYTES, max_nodes=CONFIG_MAX_NODES
    )
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise files.FileError(path, "must hold a mapping of option: value")
    out: dict[str, Any] = {}
    for k, v in data.items():
        key = str(k).replace("-", "_")
        if key not in _OPTIONS and key != "membership":
            raise files.FileError(path, f"unknown option {files.one_line(repr(k), 80)}")
        out[key] = v
    return out


def _bool(text: str) -> bool:
    t = text.strip().lower()
    if t in ("1", "true", "yes", "on"):
        return True
    if t in ("0", "false", "no", "off", ""):
        return False
    raise ValueError(f"{text!r} is not a boolean")


def _host_list(value: Any, opt: str) -> list[tuple[str, str]]:
    if isinstance(value, dict | list) and len(value) > MAX_HOSTS:
        fail(f"--{opt}: more than {MAX_HOSTS} hosts")
    if isinstance(value, dict):  # YAML mapping form
        return [(str(k), str(v)) for k, v in value.items()]
    if isinstance(value, list):  # YAML list of "NAME=HOST:PORT"
        value = ",".join(str(x) for x in value)
    try:
        return parse_peers(str(value))
    except ValueError as e:
        fail(f"--{opt}: {e}")


def load_settings(argv: list[str] | None = None) -> HostSettings:
    """Parse and validate command line, environment and YAML file (exits with code 2 and one line on
    stderr on any error)."""
    args = build_parser().parse_args(argv)
    merged: dict[str, Any] = {}
    if args.config:
        try:
            merged.update(_read_yaml(args.config))
        except ValueError as e:
            fail(f"--config: {e}")
    for opt in _OPTIONS:
        env = os.environ.get("HAA_" + opt.upper())
        if env is not None and env != "":
            if opt in ("forget_group", "log_stderr", "agents", "datagram_heartbeats"):
                try:
                    merged[opt] = _bool(env)
                except ValueError as e:
                    fail(f"HAA_{opt.upper()}: {e}")
            else:
                merged[opt] = env
        v = getattr(args, opt)
        if v is not None:
            merged[opt] = v
    for opt in ("name", "listen", "token_file"):
        if not merged.get(opt):
            fail(f"--{opt.replace('_', '-')} (or HAA_{opt.upper()}) is required")
    for opt in ("peers", "core"):
        merged[opt] = _host_list(merged.get(opt) or "", opt)
    for opt in ("hardware", "preload_agents"):
        v = merged.get(opt)
        if isinstance(v, str):
            merged[opt] = [x.strip() for x in v.split(",") if x.strip()]
    try:
        token = read_token(str(merged.pop("token_file")))
    except ValueError as e:
        fail(f"--token-file: {e}")
    name = str(merged["name"])
    merged["data_dir"] = Path(str(merged["data_dir"])) if merged.get("data_dir") else Path("data") / name
    try:
        settings = HostSettings(token=SecretStr(token), **merged)
    except ValidationError as e:
        err = e.errors()[0]
        loc = ".".join(str(x) for x in err["loc"] if not isinstance(x, int))
        opt = f"--{loc.split('.')[0].replace('_', '-')}" if loc else "settings"
        if loc.startswith("membership."):
            opt = f"membership.{loc.split('.', 1)[1]}"
        msg = err["msg"].removeprefix("Value error, ")
        fail(f"{opt}: {msg}")
    if settings.tls_dir is not None:
        try:
            tlsmod.load_host(settings.tls_dir, settings.name)
        except tlsmod.TlsError as e:
            fail(f"--tls-dir: {e}")
    return settings


@dataclass(frozen=True)
class Host:
    """One assembled haa-hostd (`build_host`): the runtime, its agent driver (None without agents) and the
    control service it serves."""

    runtime: HostRuntime
    agents: AgentDriver | None
    control: HostControlService


def build_host(cfg: RuntimeConfig) -> Host:
    """The composition root of one host: the runtime, the agent driver that runs its agent processes
    (membership mode with agents on) and the control API, each given what it needs — the runtime gets the
    driver as its agent backend (it hands the driver its `AgentOps` at start) and serves the control service;
    the control service gets the runtime and the driver. The runtime imports neither (.importlinter)."""
    agents = (AgentDriver(cfg.name, cfg.data_dir, hang_timeout=cfg.agent_hang_timeout,
                          preload_types=cfg.preload_agents)
              if cfg.membership and cfg.agents else None)
    rt = HostRuntime(cfg, agents=agents)
    control = HostControlService(rt, agents)
    rt.add_service(control)
    return Host(rt, agents, control)


class GracefulShutdown:
    """SIGTERM/SIGINT: in membership mode leave the group gracefully first (at most `leave_timeout` seconds,
    plus the agents' `drain_timeout` to hand them over), then stop; a second signal stops at once."""

    def __init__(self, rt: HostRuntime) -> None:
        self.rt = rt
        self.leaving = False

    def __call__(self) -> None:
        rt = self.rt
        if not rt.membership or rt.left or self.leaving or rt.node is None:
            rt.request_stop()
            return
        self.leaving = True
        task = asyncio.get_running_loop().create_task(self._leave_then_stop())
        rt.stream_tasks.add(task)
        task.add_done_callback(rt.stream_tasks.discard)

    async def _leave_then_stop(self) -> None:
        rt = self.rt
        try:
            drain = rt.config.agent.drain_timeout if rt.agents is not None else 0.0
            await rt.leave(timeout=rt.config.leave_timeout + drain)
        except (TimeoutError, WriteFailed) as e:
            log_event(log, logging.WARNING, "leave_incomplete", reason=str(e) or "timeout")
        finally:
            rt.request_stop()


async def serve(cfg: RuntimeConfig, stats_period: float = 0.0, metrics_port: int = 0) -> None:
    host = build_host(cfg)
    rt = host.runtime
    metrics = await _start_metrics(rt, metrics_port, host.agents) if metrics_port else None
    loop = asyncio.get_running_loop()
    shutdown = GracefulShutdown(rt)
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, shutdown)
    # the statistics sampler (haa.hostd.sampler) only reads the runtime and the driver: its first sample comes
    # after the runtime started, its last after it stopped
    sampler = (StatsSampler(rt, stats_period, host.agents)
               if stats_period > 0 and cfg.data_dir is not None else None)
    if sampler is not None:
        sampler.start()
    try:
        await rt.run()
    finally:
        if sampler is not None:
            await sampler.stop()
        if metrics is not None:
            await asyncio.to_thread(metrics.stop)


async def _start_metrics(rt: HostRuntime, port: int, agents: AgentDriver | None) -> Any:
    """Serve /metrics (haa.metrics) on the daemon's loop; a port that cannot be bound ends the process (code 1)."""
    from haa.hostd.metrics import host_registry
    from haa.hostd.sampler import HIST_BOUNDS_MS, ddb_prefix
    from haa.metrics.http import MetricsServer, metrics_bind_host

    # the statistics sampler's histogram bounds and DDB key prefixes: metrics and stats.jsonl bin alike
    reg = host_registry(rt, asyncio.get_running_loop(), bounds_s=tuple(b / 1000.0 for b in HIST_BOUNDS_MS),
                        prefix_of=ddb_prefix, agents=agents)
    server = MetricsServer(reg, metrics_bind_host(rt.config.listen), port)
    try:
        server.start()
    except OSError as e:
        fail(f"--metrics-port: cannot listen on {server.host}:{port}: {e.strerror or e}", code=1)
    return server


def run_event_loop(coro: Coroutine[Any, Any, None]) -> None:
    """Run on uvloop unless HAA_EVENT_LOOP=asyncio: measured on 10 hosts sharing 2 cores, uvloop gives
    grpc.aio ~45% more OAC throughput and ~20% lower latency (README, AP-1)."""
    if os.environ.get("HAA_EVENT_LOOP", "uvloop") == "asyncio":
        asyncio.run(coro)
        return
    import uvloop

    uvloop.run(coro)


def lock_data_dir(path: Path) -> int:
    """Hold an exclusive lock on `<data-dir>/lock` for the life of the process: one haa-hostd per data
    directory. Its incarnation numbers and known hosts live there, and a host must never run two
    incarnations at once (the quorum rule for removals relies on it, docs/membership.md)."""
    path.mkdir(parents=True, exist_ok=True)
    fd = os.open(path / "lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


def main(argv: list[str] | None = None) -> None:
    settings = load_settings(argv)
    cfg = settings.runtime_config()
    if settings.record_dir is not None:  # the fork server and every agent process inherit both (haa.sdk.tap)
        os.environ["HAA_RECORD_DIR"] = str(settings.record_dir.absolute())
        os.environ[TAP_ENV] = RECORDER_TAP
    try:
        lock_data_dir(settings.data_dir)
    except OSError as e:
        if e.errno in (errno.EAGAIN, errno.EACCES):
            fail(f"--data-dir: {settings.data_dir} is in use by another haa-hostd", code=1)
        fail(f"--data-dir: cannot lock {settings.data_dir}: {e.strerror or e}", code=1)
    try:
        run_event_loop(serve(cfg, settings.stats_period, settings.metrics_port))
    except RuntimeError as e:
        if "bind" in str(e).lower():
            fail(f"cannot listen on {cfg.listen}: {e}", code=1)
        raise
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
