"""Hostile transactions: agent-table and DDB transactions with every kind of bad value, for the verifiers and tests.

Issue 13 (defect 1) found that one `AgentSpawn` with `cost=+inf` wedged a live group: the table accepted the
agent and the allocator raised while the host was reacting to the committed transaction. The rule since is that
applying a committed transaction is total and deterministic, and that values are validated at the edge. A
buggy or hostile member can still propose anything (it skips the edge checks), so the simulators and the property
tests feed the replicas transactions built here: every `AgentTx` body kind, each field drawn from the values that
break naive code — NaN, +-inf, -0.0, huge finite numbers whose sums overflow, negative numbers, numbers just
outside a bound, empty, very long and non-ASCII strings, unknown enum values, unknown agents and hosts, references
to real agents with wrong epochs — plus raw bytes (random, truncated or bit-flipped encodings).

`hostile_agent_tx(rng, agents, hosts)` returns the encoded `AgentTx`; `hostile_ddb_batch(rng)` an encoded
`DdbBatch`; `mutate(rng, data)` flips, truncates or splices bytes. Everything is drawn from the `random.Random`
given, so a schedule that uses them stays reproducible from its seed. Pure: no I/O, no clock.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence

from haa.pb import agenttx_pb2 as apb
from haa.pb import ddb_pb2 as dpb

#: numbers that break naive arithmetic or comparisons (NaN compares false; inf - inf is NaN; 1e308 + 1e308 is inf)
BAD_FLOATS = (
    float("nan"), float("inf"), float("-inf"), -0.0, -1.0, -1e-300, 1e308, 1.7976931348623157e308, 1e300, 5e-324,
    1e3 + 1e-9, 1000.0000001, 1.0000001, 2.0, 1e9, 1e12 + 1.0,
)
#: strings for names, types, hosts and enums
BAD_STRINGS = ("", " ", "h1", "h2", "nobody", "A1", "\x00", "é" * 40, "x" * 65, "x" * 4096, "../../etc", "maybe", "-1")
BAD_UINTS = (0, 1, 2, 3, 2**32, 2**63 - 1, 2**64 - 1)

KINDS = (
    "create", "remove", "start", "finish", "move", "freeze", "release", "claim", "recovered", "backup", "failed",
    "push", "costs", "host", "control",
)


def _f(rng: random.Random) -> float:
    return rng.choice(BAD_FLOATS) if rng.random() < 0.8 else rng.uniform(-10.0, 10.0)


def _s(rng: random.Random, real: Sequence[str] = ()) -> str:
    if real and rng.random() < 0.5:
        return rng.choice(list(real))
    return rng.choice(BAD_STRINGS)


def _u(rng: random.Random) -> int:
    return rng.choice(BAD_UINTS) if rng.random() < 0.8 else rng.randrange(0, 20)


def _msg(rng: random.Random, agents: Sequence[str]) -> apb.RoutedMsg:
    return apb.RoutedMsg(src=_s(rng, agents), src_life=_u(rng), seq=_u(rng), dst=_s(rng, agents),
                         payload=rng.randbytes(rng.choice((0, 1, 16))))


def _body(kind: str, rng: random.Random, agents: Sequence[str], hosts: Sequence[str]) -> object:
    a = lambda: _s(rng, agents)  # noqa: E731
    h = lambda: _s(rng, hosts)  # noqa: E731
    if kind == "create":
        return apb.AgentCreate(
            id=rng.choice((a(), "x" * rng.choice((1, 64, 65, 300)))), type=_s(rng, ("counter",)), config=b"{}",
            parent=a() if rng.random() < 0.3 else "", cost=_f(rng), transfer_penalty=_f(rng),
            recovery=_s(rng, ("backup", "restart", "none")), host=h(), req=_u(rng),
            hardware=[_s(rng, ("camera",)) for _ in range(rng.choice((0, 1, 2, 70)))],
        )
    if kind == "remove":
        return apb.AgentRemove(id=a(), host=h(), epoch=_u(rng))
    if kind == "start":
        group = [h() for _ in range(rng.choice((0, 1, 3)))]
        return apb.AllocStartTx(data=rng.randbytes(rng.choice((0, 8, 64))), ses_id=_u(rng), leader=h(), group=group,
                                agents=sorted(agents) if rng.random() < 0.5 else [a()])
    if kind == "finish":
        f = apb.AllocFinishTx(ses_id=_u(rng), leader=h())
        for _ in range(rng.choice((0, 1, 3))):
            f.allocation[a()] = h()
        return f
    if kind == "move":
        return apb.AgentMove(id=a(), host=h())
    if kind == "freeze":
        return apb.AgentFreeze(id=a(), host=h(), epoch=_u(rng))
    if kind == "release":
        return apb.AgentRelease(id=a(), host=h(), epoch=_u(rng), state=rng.randbytes(4),
                                pending=[_msg(rng, agents) for _ in range(rng.choice((0, 2)))])
    if kind == "claim":
        return apb.AgentClaim(id=a(), host=h())
    if kind == "recovered":
        return apb.AgentRecovered(id=a(), host=h())
    if kind == "backup":
        return apb.AgentBackup(id=a(), host=h(), epoch=_u(rng), data=rng.randbytes(rng.choice((0, 16))))
    if kind == "failed":
        return apb.AgentFailed(id=a(), host=h(), epoch=_u(rng), reason=_s(rng))
    if kind == "push":
        return apb.AgentPush(id=a(), queue=rng.choice((0, 1, 2, 3, 2**32 - 1)),
                            msgs=[_msg(rng, agents) for _ in range(rng.choice((0, 1, 5)))])
    if kind == "costs":
        c = apb.AgentCosts(host=h())
        for _ in range(rng.choice((1, 3))):
            c.costs.add(id=a(), cpu=_f(rng))
        for _ in range(rng.choice((0, 2))):
            c.affinity.add(a=a(), b=a(), rate=_f(rng))
        return c
    if kind == "host":
        return apb.HostInfo(name=h(), capacity=_f(rng), draining=rng.random() < 0.3,
                            hardware=[_s(rng, ("camera",)) for _ in range(rng.choice((0, 1, 70)))])
    if kind == "control":
        return apb.AllocControl(paused=rng.random() < 0.5)
    raise ValueError(f"unknown agent transaction kind {kind!r}")


def hostile_agent_tx(rng: random.Random, agents: Sequence[str] = (), hosts: Sequence[str] = (),
                     kind: str | None = None) -> bytes:
    """One encoded `AgentTx` of `kind` (random if None) with hostile field values; one in ten is mangled bytes."""
    kind = kind or rng.choice(KINDS)
    tx = apb.AgentTx()
    getattr(tx, kind).CopyFrom(_body(kind, rng, agents, hosts))
    data = tx.SerializeToString()
    return mutate(rng, data) if rng.random() < 0.1 else data


#: numbers outside every bound the agent table checks (costs, CPU shares, capacities, penalties)
OUT_OF_BOUNDS = (float("nan"), float("inf"), float("-inf"), -1.0, 1e308, 1.7976931348623157e308, 1e300, 1e9)


def refusable_agent_tx(rng: random.Random, agents: Sequence[str], hosts: Sequence[str]) -> tuple[str, bytes]:
    """(kind, encoded AgentTx) that every replica must refuse or ignore, whatever the state: a member that skips
    the edge checks (a bug, or a hostile process with the token) proposes it. Unlike `hostile_agent_tx`, nothing
    here can be a valid operation by chance, so the agent verifiers can inject it into any schedule and still
    check their properties: create with an out-of-bounds number, host info with an out-of-bounds capacity, CPU
    and rate measurements out of bounds, a move to an over-long host name, a push to an unknown agent."""
    kind = rng.choice(("create", "host", "costs", "move", "push"))
    tx = apb.AgentTx()
    bad = rng.choice(OUT_OF_BOUNDS)
    if kind == "create":
        c = tx.create
        c.id, c.type, c.recovery, c.host = f"hostile-{rng.randrange(10**9)}", "counter", "backup", _s(rng, hosts)
        c.cost, c.transfer_penalty = 0.1, 0.1
        setattr(c, rng.choice(("cost", "transfer_penalty")), bad)
    elif kind == "host":
        tx.host.name, tx.host.capacity = _s(rng, hosts) or "h1", bad
    elif kind == "costs":
        tx.costs.host = _s(rng, hosts)
        for a in agents:
            tx.costs.costs.add(id=a, cpu=bad if bad != -1.0 else float("nan"))
        if len(agents) >= 2:
            tx.costs.affinity.add(a=agents[0], b=agents[1], rate=rng.choice((float("inf"), float("nan"), -5.0, 1e300)))
    elif kind == "move":
        tx.move.id, tx.move.host = rng.choice(list(agents)) if agents else "a", "h" * 65
    else:
        tx.push.id, tx.push.queue = f"unknown-{rng.randrange(10**9)}", 2
        tx.push.msgs.append(_msg(rng, agents))
    return kind, tx.SerializeToString()


def hostile_ddb_batch(rng: random.Random) -> bytes:
    """One encoded `DdbBatch` with hostile ops (bad keys, type mismatches, counter overflows, bad JSON)."""
    b = dpb.DdbBatch(origin=_s(rng), client_seq=_u(rng), atomic=rng.random() < 0.3)
    for _ in range(rng.choice((0, 1, 3))):
        key = rng.choice(("", "k", "/", "k" * 513, "a/b", "\x00"))
        op = rng.choice(("put", "cas", "delete", "append", "add"))
        if op in ("put", "cas"):
            val = rng.choice((b"", b"{", b'{"a":1,"a":2}', b"NaN", b"\xff", b"[" * 200 + b"]" * 200, b"1"))
            o = b.ops.add()
            body = o.put if op == "put" else o.cas
            body.key, body.type, body.value = key, rng.choice(("json", "blob", "list", "counter", "nope", "")), val
            if op == "cas":
                o.cas.expected_version = _u(rng)
        elif op == "delete":
            b.ops.add().delete.key = key
        elif op == "append":
            o = b.ops.add()
            o.append.key, o.append.item, o.append.max_len = key, rng.randbytes(3), _u(rng) % 2**32
        else:
            o = b.ops.add()
            o.add.key, o.add.delta = key, rng.choice((1, -1, 2**63 - 1, -(2**63)))
    data = b.SerializeToString()
    return mutate(rng, data) if rng.random() < 0.1 else data


def mutate(rng: random.Random, data: bytes) -> bytes:
    """`data` with bytes flipped, truncated, duplicated or spliced with random bytes."""
    ops: list[Callable[[bytearray], bytearray]] = [
        lambda d: d[: rng.randrange(0, len(d) + 1)],
        lambda d: d + d,
        lambda d: d[:1] + bytearray(rng.randbytes(rng.randrange(1, 12))) + d[1:],
    ]
    d = bytearray(data)
    if d:
        ops.append(lambda d: _flip(rng, d))
    return bytes(rng.choice(ops)(d))


def _flip(rng: random.Random, d: bytearray) -> bytearray:
    i = rng.randrange(len(d))
    d[i] ^= 1 << rng.randrange(8)
    return d
