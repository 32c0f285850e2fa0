"""Inputs that bypass the host (docs/playback.md): an avatar agent's calls to haa-sim.

`RecordingStub` wraps a gRPC asyncio stub (AvatarSimStub): every call is an output (`ExternalCall`, the
request's bytes) and every reply, stream item, stream end and error an input (`External`), recorded in the
agent process as the agent's code receives it. `ReplayStub` stands in for the stub offline: it answers every
call from the recording and checks that the request is the recorded one. Both take the service's methods
from its protobuf descriptor (unary or server-streaming, reply type).
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from typing import Any

import grpc
from google.protobuf import message_factory
from google.protobuf.descriptor import ServiceDescriptor

from haa.pb import playback_pb2 as ppb


def methods(service: ServiceDescriptor) -> dict[str, tuple[bool, Any]]:
    """Method name -> (server streaming, reply message class)."""
    return {m.name: (m.server_streaming, message_factory.GetMessageClass(m.output_type))
            for m in service.methods}


class RecordingStub:
    """The stub `inner` with every call recorded through `tap` (a `haa.sdk.recorder.Recorder`)."""

    def __init__(self, tap: Any, source: str, service: ServiceDescriptor, inner: Any) -> None:
        self._tap = tap
        self._source = source
        self._service = service.name
        for name, (streaming, _) in methods(service).items():
            call = getattr(inner, name)
            setattr(self, name, self._stream(name, call) if streaming else self._unary(name, call))

    def _unary(self, name: str, call: Any) -> Callable[..., Any]:
        method = f"{self._service}/{name}"

        async def unary(request: Any, **kw: Any) -> Any:
            n = self._tap.external_call(self._source, method, request.SerializeToString())
            try:
                reply = await call(request, **kw)
            except grpc.aio.AioRpcError as e:
                self._tap.external(ppb.PlaybackInput.External(source=self._source, method=method, call=n,
                                                              code=e.code().value[0], details=e.details() or ""))
                raise
            self._tap.external(ppb.PlaybackInput.External(source=self._source, method=method, call=n,
                                                          payload=reply.SerializeToString()))
            return reply

        return unary

    def _stream(self, name: str, call: Any) -> Callable[..., Any]:
        method = f"{self._service}/{name}"

        def stream(request: Any, **kw: Any) -> AsyncIterator[Any]:
            n = self._tap.external_call(self._source, method, request.SerializeToString())

            async def items() -> AsyncIterator[Any]:
                try:
                    async for item in call(request, **kw):
                        self._tap.external(ppb.PlaybackInput.External(source=self._source, method=method, call=n,
                                                                      payload=item.SerializeToString()))
                        yield item
                except grpc.aio.AioRpcError as e:
                    self._tap.external(ppb.PlaybackInput.External(source=self._source, method=method, call=n,
                                                                  code=e.code().value[0], details=e.details() or ""))
                    raise
                self._tap.external(ppb.PlaybackInput.External(source=self._source, method=method, call=n, end=True))

            return items()

        return stream


def rpc_error(code: int, details: str) -> grpc.aio.AioRpcError:
    """The AioRpcError the live call raised (its status code and details)."""
    status = next((s for s in grpc.StatusCode if s.value[0] == code), grpc.StatusCode.UNKNOWN)
    return grpc.aio.AioRpcError(status, grpc.aio.Metadata(), grpc.aio.Metadata(), details=details)


class ReplayStub:
    """Offline stand-in of a stub: `feed` (a `haa.lab.playback.replay.ReplayFeed`) checks each request against the
    recorded output and hands out the recorded replies in the recorded order."""

    def __init__(self, feed: Any, source: str, service: ServiceDescriptor) -> None:
        self._feed = feed
        self._source = source
        self._service = service.name
        for name, (streaming, reply_cls) in methods(service).items():
            setattr(self, name, self._stream(name, reply_cls) if streaming else self._unary(name, reply_cls))

    def _unary(self, name: str, reply_cls: Any) -> Callable[..., Any]:
        method = f"{self._service}/{name}"

        async def unary(request: Any, **_kw: Any) -> Any:
            n = self._feed.external_call(self._source, method, request.SerializeToString())
            ext = await self._feed.take_external(n)
            if ext.code:
                raise rpc_error(ext.code, ext.details)
            return reply_cls.FromString(ext.payload)

        return unary

    def _stream(self, name: str, reply_cls: Any) -> Callable[..., Any]:
        method = f"{self._service}/{name}"

        def stream(request: Any, **_kw: Any) -> AsyncIterator[Any]:
            n = self._feed.external_call(self._source, method, request.SerializeToString())

            async def items() -> AsyncIterator[Any]:
                while True:
                    ext = await self._feed.take_external(n)
                    if ext.code:
                        raise rpc_error(ext.code, ext.details)
                    if ext.end:
                        return
                    yield reply_cls.FromString(ext.payload)

            return items()

        return stream
