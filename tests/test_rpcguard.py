"""`haa.rpcguard`: the guard's refusals end a call with a status without raising.

`context.abort` raises an `AbortError` whose traceback holds the handler's frames, and with them the raw and the
decoded request, until the garbage collector's next full pass: refused 4 MiB calls retried by a client took a host
to 798-972 MiB that way. The guard sets the status and returns instead, for a missing token, a request that does
not parse and an exception escaping the servicer; `context.abort` called by a servicer still works.
"""

from __future__ import annotations

import asyncio
import gc
import sys
from typing import Any

import grpc
import pytest
from grpc import aio

from haa import rpcguard
from haa.pb import control_pb2 as cpb

SERVICE = cpb.DESCRIPTOR.services_by_name["HostControl"]


class FakeContext:
    """The parts of `aio.ServicerContext` the guard uses; `abort` raises as grpc's does."""

    def __init__(self) -> None:
        self.code: grpc.StatusCode | None = None
        self.details = ""
        self.aborted = False

    def set_code(self, code: grpc.StatusCode) -> None:
        self.code = code

    def set_details(self, details: str) -> None:
        self.details = details

    async def abort(self, code: grpc.StatusCode, details: str = "") -> None:
        self.aborted = True
        self.code, self.details = code, details
        raise aio.AbortError()

    def invocation_metadata(self) -> tuple:
        return ()


class Servicer:
    def __init__(self) -> None:
        self.seen: list[Any] = []

    async def Status(self, request: cpb.StatusRequest, context: Any) -> cpb.StatusReply:
        self.seen.append(request)
        raise ValueError("bad status request")

    async def DdbGet(self, request: cpb.DdbGetRequest, context: Any) -> cpb.DdbGetReply:
        await context.abort(grpc.StatusCode.NOT_FOUND, "gone")
        return cpb.DdbGetReply()

    def __getattr__(self, name: str) -> Any:
        async def other(request: Any, context: Any) -> None:
            return None

        return other


def handler(name: str, guard: rpcguard.Guard) -> Any:
    generic = rpcguard.guarded_handler(SERVICE, Servicer(), guard)

    class Details:
        method = f"/{SERVICE.full_name}/{name}"
        invocation_metadata = ()

    return generic.service(Details()).unary_unary


def call(name: str, guard: rpcguard.Guard, raw: bytes) -> tuple[Any, FakeContext]:
    ctx = FakeContext()
    reply = asyncio.run(handler(name, guard)(raw, ctx))
    return reply, ctx


def test_a_call_without_the_token_is_refused_without_raising_and_keeps_nothing() -> None:
    events: list[str] = []
    guard = rpcguard.Guard(authenticate=lambda ctx: False, on_event=lambda k, m, d, e: events.append(k))
    raw = bytes(4 << 20)
    before = sys.getrefcount(raw)
    gc.disable()
    try:
        reply, ctx = call("Status", guard, raw)
        assert sys.getrefcount(raw) == before  # no traceback holds the request until a full collection
    finally:
        gc.enable()
    assert ctx.code == grpc.StatusCode.UNAUTHENTICATED and not ctx.aborted
    assert isinstance(reply, cpb.StatusReply) and events == ["unauthenticated"]


def test_a_malformed_request_and_a_servicer_exception_set_their_status() -> None:
    events: list[str] = []
    guard = rpcguard.Guard(on_event=lambda k, m, d, e: events.append(k))
    _, ctx = call("Status", guard, b"\xff\xff\xff")
    assert ctx.code == grpc.StatusCode.INVALID_ARGUMENT and "malformed" in ctx.details and not ctx.aborted
    reply, ctx = call("Status", guard, b"")
    assert ctx.code == grpc.StatusCode.INVALID_ARGUMENT and "bad status request" in ctx.details
    assert not ctx.aborted and isinstance(reply, cpb.StatusReply)
    assert events == ["malformed", "error"]


def test_a_servicer_may_still_abort() -> None:
    with pytest.raises(aio.AbortError):
        call("DdbGet", rpcguard.Guard(), b"")
