"""Guarded gRPC services: check the token before decoding, decode ourselves, map every exception to a status.

grpcio decodes a request with the servicer's `request_deserializer` *before* the handler runs. A request that
does not parse therefore fails with status UNKNOWN ("Unexpected <class 'DecodeError'>") without the handler
- and so the token check - ever seeing it, and nothing counts it. In the same way, an exception that escapes
a handler reaches the client as UNKNOWN with the Python exception's name. `guarded_handler` registers every
method of a protobuf service with raw bytes instead (`request_deserializer=None`) and, for each call:

1. checks the call's metadata first (`Guard.authenticate`); refused: `UNAUTHENTICATED` (`kind` "unauthenticated");
2. parses the bytes into the method's request type; malformed: `INVALID_ARGUMENT` ("malformed");
3. runs the servicer's method (the same `async def Name(request, context)` the generated servicer base
   class declares; a server-streaming method is an async generator, or a coroutine that sends with
   `await context.write(...)` — which it can bound in time, for a client that stops reading; either may
   hand out an already serialized message as `bytes`, sent as it is); an exception escaping it becomes a
   status through `Guard.statuses` ("error"): `TimeoutError` -> `DEADLINE_EXCEEDED`, `ValueError` /
   `OverflowError` / `DecodeError` -> `INVALID_ARGUMENT`, `ConnectionError` -> `UNAVAILABLE`, the caller's own
   exception types as it maps them, anything else -> `INTERNAL` (a bug of ours: logged with its traceback by
   the `on_event` hook). `context.abort(...)` inside a handler works as before (its `AbortError` passes),
   and so does cancellation.

The guard's own refusals set the status and return (an empty reply, which gRPC does not send) instead of
`context.abort`: the `AbortError` that raises carries a traceback holding the handler's frames, and with them
the raw and the decoded request, until the garbage collector's next full pass. Refused 4 MiB calls retried by a
client took a host to 798-972 MiB that way (docs/limits.md, "Messages in flight").

`Guard.on_event(kind, method, detail, exc)` is told about each of the three outcomes, so the owner can count
them (haa-hostd: `rejected_unauthenticated`, `control_malformed`, `control_errors`; see haa.hostd.control).
Status details are cut to `MAX_DETAILS` characters: an exception's text can quote a huge input. So are the
`reason` and `error` texts of a unary reply (`AgentOpReply.reason` naming a 100 kB ref it did not find).

Client-streaming methods are not supported (none of our services has one).
"""

from __future__ import annotations

import asyncio
import inspect
import logging
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import grpc
from google.protobuf import message_factory
from google.protobuf.descriptor import MethodDescriptor, ServiceDescriptor
from google.protobuf.message import DecodeError
from grpc import aio

#: longest status details text sent to a client, in characters
MAX_DETAILS = 300

#: how exceptions escaping a handler map to statuses, first match wins (`Guard.statuses` prepends its own)
DEFAULT_STATUSES: tuple[tuple[type[BaseException], grpc.StatusCode], ...] = (
    (TimeoutError, grpc.StatusCode.DEADLINE_EXCEEDED),
    (DecodeError, grpc.StatusCode.INVALID_ARGUMENT),
    (ValueError, grpc.StatusCode.INVALID_ARGUMENT),  # UnicodeError too
    (OverflowError, grpc.StatusCode.INVALID_ARGUMENT),
    (ConnectionError, grpc.StatusCode.UNAVAILABLE),
)

#: (kind, method, detail, exception or None); kind is "unauthenticated", "malformed" or "error"
OnEvent = Callable[[str, str, str, BaseException | None], None]


def client_address(peer: str) -> str:
    """A gRPC peer ("ipv4:127.0.0.1:51234", "ipv6:[::1]:5", "unix:...") without its port: one client machine."""
    kind, _, rest = peer.partition(":")
    if kind in ("ipv4", "ipv6"):
        return rest.rsplit(":", 1)[0]
    return peer


def _cut(text: str) -> str:
    return text if len(text) <= MAX_DETAILS else text[: MAX_DETAILS - 3] + "..."


def _cut_reasons(reply: Any) -> Any:
    """`reply` with its top-level `reason` / `error` text cut to MAX_DETAILS characters."""
    fields = getattr(getattr(reply, "DESCRIPTOR", None), "fields_by_name", {})
    for name in ("reason", "error"):
        if name in fields:
            text = getattr(reply, name)
            if isinstance(text, str) and len(text) > MAX_DETAILS:
                setattr(reply, name, _cut(text))
    return reply


@dataclass
class Guard:
    """What a guarded service checks and how it reports (see the module docstring)."""

    #: True if the call may proceed (e.g. it carries the token); None: every call may
    authenticate: Callable[[aio.ServicerContext], bool] | None = None
    #: told about every refused call and every exception mapped to a status
    on_event: OnEvent | None = None
    #: (exception type, status) pairs tried before `DEFAULT_STATUSES`
    statuses: Sequence[tuple[type[BaseException], grpc.StatusCode]] = field(default_factory=tuple)
    log: logging.Logger = field(default_factory=lambda: logging.getLogger("haa.rpcguard"))

    def status_for(self, exc: BaseException) -> grpc.StatusCode:
        for typ, code in (*self.statuses, *DEFAULT_STATUSES):
            if isinstance(exc, typ):
                return code
        return grpc.StatusCode.INTERNAL

    def _event(self, kind: str, method: str, detail: str, exc: BaseException | None = None) -> None:
        if self.on_event is not None:
            try:
                self.on_event(kind, method, detail, exc)
            except Exception:  # a reporting hook must not turn a clean refusal into UNKNOWN
                self.log.exception("rpc guard on_event hook failed")

    def admit(self, method: MethodDescriptor, raw: bytes, context: aio.ServicerContext, req_cls: Any) -> Any:
        """The decoded request, or None with the call's status set (UNAUTHENTICATED / INVALID_ARGUMENT)."""
        if self.authenticate is not None and not self.authenticate(context):
            self._event("unauthenticated", method.name, "missing or wrong token")
            _refuse(context, grpc.StatusCode.UNAUTHENTICATED, "missing or wrong cluster token")
            return None
        try:
            return req_cls.FromString(raw)
        except Exception as e:  # DecodeError; the upb backend may raise others for some garbage
            detail = f"malformed {method.input_type.name} ({len(raw)} bytes): {e}"
            self._event("malformed", method.name, detail, e)
            _refuse(context, grpc.StatusCode.INVALID_ARGUMENT, _cut(detail))
            return None

    def fail(self, method: MethodDescriptor, exc: Exception, context: aio.ServicerContext) -> None:
        """Set the call's status to the one `exc` maps to (the handler then returns)."""
        code = self.status_for(exc)
        if code is grpc.StatusCode.DEADLINE_EXCEEDED:
            text = str(exc) or "no answer in time (the operation may still complete)"
        elif code is grpc.StatusCode.INTERNAL:
            text = f"internal error ({type(exc).__name__}: {exc}); see the server's log"
        else:
            text = str(exc) or type(exc).__name__
        detail = f"{method.name}: {text}"
        self._event("error", method.name, f"{code.name}: {detail}", exc)
        _refuse(context, code, _cut(detail))


def _refuse(context: aio.ServicerContext, code: grpc.StatusCode, details: str) -> None:
    """End the call with `code` once the handler returns (not `context.abort`: see the module docstring)."""
    context.set_code(code)
    context.set_details(details)


def _serializer(cls: Any) -> Callable[[Any], bytes]:
    """`cls.SerializeToString`, passing bytes (a message serialized once for many calls) through as they are."""
    encode = cls.SerializeToString

    def serialize(m: Any) -> bytes:
        return m if isinstance(m, bytes) else encode(m)

    return serialize


def _unary(guard: Guard, m: MethodDescriptor, fn: Callable[..., Awaitable[Any]], req_cls: Any,
           empty: Callable[[], Any] | None) -> Any:
    """A unary method (`empty` makes the reply sent with a refusal, which gRPC does not send), or a
    server-streaming one that sends with `context.write` (a coroutine; `empty` None)."""
    async def handler(raw: bytes, context: aio.ServicerContext) -> Any:
        request = guard.admit(m, raw, context, req_cls)
        if request is None:
            return empty() if empty is not None else None
        try:
            return _cut_reasons(await fn(request, context))
        except aio.AbortError:
            raise
        except Exception as e:
            guard.fail(m, e, context)
        return empty() if empty is not None else None

    return handler


def _stream(guard: Guard, m: MethodDescriptor, fn: Callable[..., AsyncIterator[Any]], req_cls: Any) -> Any:
    async def handler(raw: bytes, context: aio.ServicerContext) -> AsyncIterator[Any]:
        request = guard.admit(m, raw, context, req_cls)
        if request is None:
            return
        try:
            async for item in fn(request, context):
                yield item
        except (aio.AbortError, asyncio.CancelledError):
            raise
        except Exception as e:
            guard.fail(m, e, context)

    return handler


def guarded_handler(service: ServiceDescriptor, servicer: object, guard: Guard) -> grpc.GenericRpcHandler:
    """A generic handler serving every method of `service` (a protobuf `ServiceDescriptor`, e.g.
    `control_pb2.DESCRIPTOR.services_by_name["HostControl"]`) from `servicer`'s methods of the same names."""
    handlers: dict[str, grpc.RpcMethodHandler] = {}
    for m in service.methods:
        if m.client_streaming:
            raise ValueError(f"{service.full_name}.{m.name}: client streaming is not supported")
        fn = getattr(servicer, m.name)
        req_cls = message_factory.GetMessageClass(m.input_type)
        out_cls = message_factory.GetMessageClass(m.output_type)
        ser = _serializer(out_cls)
        if m.server_streaming:
            h = _stream(guard, m, fn, req_cls) if inspect.isasyncgenfunction(fn) else _unary(
                guard, m, fn, req_cls, None)
            handlers[m.name] = grpc.unary_stream_rpc_method_handler(h, request_deserializer=None,
                                                                    response_serializer=ser)
        else:
            handlers[m.name] = grpc.unary_unary_rpc_method_handler(
                _unary(guard, m, fn, req_cls, out_cls), request_deserializer=None, response_serializer=ser
            )
    return grpc.method_handlers_generic_handler(service.full_name, handlers)
