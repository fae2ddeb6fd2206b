"""A small Foxglove WebSocket client for tests: the ws-protocol's JSON and binary messages, and a protobuf
wire-format reader for the foxglove.* messages (no protobuf package needed)."""

from __future__ import annotations

import asyncio
import json
import struct
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import websockets

# foxglove-sdk servers name the ws-protocol "foxglove.sdk.v1" (it was "foxglove.websocket.v1"; the messages
# are the same). Like the Foxglove app, offer both.
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 0x01


def varint(data: bytes, index: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[index]
        index += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, index


def protobuf_fields(data: bytes) -> dict[int, list[Any]]:
    """Field number -> values: ints (varint), bytes (length-delimited), 4/8 raw bytes (fixed32/64)."""
    fields: dict[int, list[Any]] = defaultdict(list)
    index = 0
    while index < len(data):
        key, index = varint(data, index)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, index = varint(data, index)
        elif wire == 2:
            size, index = varint(data, index)
            value, index = data[index : index + size], index + size
        elif wire in (1, 5):
            width = 8 if wire == 1 else 4
            value, index = data[index : index + width], index + width
        else:
            raise ValueError(f"wire type {wire}")
        fields[number].append(value)
    return fields


def fixed32(raw: bytes) -> int:
    return int(struct.unpack("<I", raw)[0])


def double(raw: bytes) -> float:
    return float(struct.unpack("<d", raw)[0])


@dataclass
class FoxgloveClient:
    """Records every message of the connection; ``until`` reads until a condition holds."""

    websocket: Any
    server_info: dict[str, Any] = field(default_factory=dict)
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)  # topic -> advertised channel
    ops: list[dict[str, Any]] = field(default_factory=list)  # every JSON message
    data: dict[int, list[bytes]] = field(default_factory=lambda: defaultdict(list))  # subscription -> payloads
    subscriptions: dict[str, int] = field(default_factory=dict)  # topic -> subscription id

    @classmethod
    async def connect(cls, url: str) -> FoxgloveClient:
        websocket = await websockets.connect(url, subprotocols=SUBPROTOCOLS)  # type: ignore[arg-type]
        return cls(websocket)

    async def until(self, condition: Callable[[], bool], timeout: float = 20.0) -> None:
        async def read() -> None:
            while not condition():
                self.record(await self.websocket.recv())

        await asyncio.wait_for(read(), timeout)

    def record(self, message: str | bytes) -> None:
        if isinstance(message, bytes):
            if message[0] == MESSAGE_DATA:
                (subscription,) = struct.unpack_from("<I", message, 1)
                self.data[subscription].append(message[13:])
            return
        op = json.loads(message)
        self.ops.append(op)
        if op["op"] == "serverInfo":
            self.server_info = op
        elif op["op"] == "advertise":
            self.channels.update({channel["topic"]: channel for channel in op["channels"]})

    async def send(self, **message: Any) -> None:
        await self.websocket.send(json.dumps(message))

    async def subscribe(self, *topics: str) -> None:
        pairs = []
        for topic in topics:
            self.subscriptions[topic] = len(self.subscriptions) + 1
            pairs.append({"id": self.subscriptions[topic], "channelId": self.channels[topic]["id"]})
        await self.send(op="subscribe", subscriptions=pairs)

    def received(self, topic: str) -> list[bytes]:
        return self.data[self.subscriptions[topic]]

    def ops_named(self, name: str, request_id: str | None = None) -> list[dict[str, Any]]:
        return [op for op in self.ops if op["op"] == name and (request_id is None or op.get("id") == request_id)]

    async def parameters(self, request_id: str, timeout: float = 20.0) -> dict[str, Any]:
        """The parameterValues answer to ``request_id``, as name -> value."""
        await self.until(lambda: bool(self.ops_named("parameterValues", request_id)), timeout)
        reply = self.ops_named("parameterValues", request_id)[0]
        return {p["name"]: p["value"] for p in reply["parameters"]}

    async def close(self) -> None:
        await self.websocket.close()
