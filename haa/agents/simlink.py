"""`SimLink`: an avatar agent's channel to haa-sim (the AvatarSim service: the hardware a robot driver talks to).

AgentPlayback (docs/playback.md): haa-sim's replies bypass the host, so with a tap (haa.sdk.tap) the stub is
wrapped and every call and reply recorded in the agent process; replaying offline, the recording answers
(haa.sdk.external builds both wrappers from `sim_service()`, the service's protobuf descriptor).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from google.protobuf.descriptor import ServiceDescriptor

    from haa.sdk.tap import Tap


def sim_service() -> ServiceDescriptor:
    """haa-sim's AvatarSim service (what a recording or replay stub wraps)."""
    from haa.pb import sim_pb2

    return sim_pb2.DESCRIPTOR.services_by_name["AvatarSim"]


class SimLink:
    """An asyncio gRPC channel to haa-sim (AvatarSim only: the hardware a robot driver talks to).

    `tap`: the agent's AgentPlayback tap (`agent._ctx.tap`, docs/playback.md): recording, every call and reply
    is recorded (haa-sim's replies bypass the host); replaying offline, the recording answers and nothing is
    connected."""

    def __init__(self, address: str, token_file: str, caller: str, tap: Tap | None = None) -> None:
        from grpc import aio

        from haa.pb import sim_pb2_grpc as pbg

        self.channel: Any = None
        if tap is not None and getattr(tap, "offline", False):
            self.metadata: tuple[tuple[str, str], ...] = (("x-haa-caller", caller),)
            self.avatar = tap.wrap_stub("haa-sim", sim_service(), None)
            return
        if not address:
            raise ValueError("config.sim: the haa-sim address is required")
        md = [("x-haa-caller", caller)]
        if token_file:
            md.append(("x-haa-token", Path(token_file).read_text().strip()))
        self.metadata = tuple(md)
        self.channel = aio.insecure_channel(
            address, options=[("grpc.max_receive_message_length", 32 * 1024 * 1024)]
        )
        self.avatar = pbg.AvatarSimStub(self.channel)
        if tap is not None:
            self.avatar = tap.wrap_stub("haa-sim", sim_service(), self.avatar)

    async def close(self) -> None:
        if self.channel is not None:
            await self.channel.close(grace=None)
