"""The live view accepts both names of the Foxglove WebSocket subprotocol, on 127.0.0.1 only.

foxglove-sdk's server accepts ``foxglove.sdk.v1`` only; clients of Foxglove's older ``ws-protocol``
libraries (Lichtblick, roslibjs-foxglove, ...) offer ``foxglove.websocket.v1``, the same protocol.
"""

from __future__ import annotations

import asyncio
import json
import struct
import time

import numpy as np
import pytest
import websockets
from websockets.exceptions import InvalidStatus

from echoloc.realtime.liveview import LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL, LiveView


async def _handshake_and_one_map(
    port: int, offered: list[str], view: LiveView
) -> tuple[str | None, dict, bytes]:
    """Connect offering ``offered``; return the agreed subprotocol, serverInfo and one map message."""
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=offered, close_timeout=1) as ws:
        agreed = ws.subprotocol
        info = json.loads(await asyncio.wait_for(ws.recv(), 10))
        channels: dict[int, dict] = {}
        while not any(c["topic"] == "/echoloc/map" for c in channels.values()):
            message = json.loads(await asyncio.wait_for(ws.recv(), 10))
            if message["op"] == "advertise":
                channels.update({c["id"]: c for c in message["channels"]})
        (channel,) = [c for c in channels.values() if c["topic"] == "/echoloc/map"]
        await ws.send(
            json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": channel["id"]}]})
        )
        grid = np.arange(6, dtype=float).reshape(2, 3) / 10

        def publish() -> None:
            for _ in range(40):
                view.publish_map(grid, 0.05)
                time.sleep(0.05)

        publisher = asyncio.get_running_loop().run_in_executor(None, publish)
        while True:
            data = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(data, bytes) and data[0] == 0x01:  # message data, through the relay
                break
        await publisher
        return agreed, info, data


@pytest.mark.parametrize(
    "offered", [[LEGACY_SUBPROTOCOL], [SDK_SUBPROTOCOL], [LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL]]
)
def test_a_client_offering_either_subprotocol_gets_server_info_and_data(offered: list[str]) -> None:
    with LiveView(port=0) as view:
        assert view.url.startswith("ws://127.0.0.1:")
        agreed, info, data = asyncio.run(_handshake_and_one_map(view.port, offered, view))
    # The server agrees to a name the client offered: the SDK's when offered, else the older one.
    assert agreed == (SDK_SUBPROTOCOL if SDK_SUBPROTOCOL in offered else LEGACY_SUBPROTOCOL)
    assert info["op"] == "serverInfo"
    assert info["name"] == "echoloc"
    subscription, _log_time = struct.unpack_from("<IQ", data, 1)
    assert subscription == 7


def test_a_client_offering_neither_is_refused_as_before() -> None:
    async def connect(port: int) -> None:
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["other.v1"]):
            pass

    with LiveView(port=0) as view, pytest.raises(InvalidStatus) as info:
        asyncio.run(connect(view.port))
    assert info.value.response.status_code == 400


def test_a_busy_port_is_one_error() -> None:
    from echoloc.errors import EchoLocError

    with LiveView(port=0) as first, pytest.raises(EchoLocError, match="cannot start the live view"):
        LiveView(port=first.port)
