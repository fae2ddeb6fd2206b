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

    async def subscribe(self, *topics: str, timeout: float = 20.0) -> None:
        """Subscribe to ``topics``; returns once the server has taken each subscription.

        foxglove-sdk 0.30.3 advertises a new channel a moment before it accepts subscriptions to it, and
        refuses one sent in between with an error status "Unknown channel ID: N" (seen in most subscriptions
        sent the instant a channel appears). The server handles a connection's messages in order and answers
        on one queue, so a getParameters sent after the subscribe is a barrier: once its answer is in, each
        subscription was either refused (its status came first) or taken. A refused one is sent again, in
        answer to the refusal; one not taken within ``timeout`` fails the test."""
        assert "parameters" in self.server_info.get("capabilities", []), "the barrier needs getParameters"
        pending: dict[int, int] = {}  # channel id -> subscription id
        for topic in topics:
            self.subscriptions[topic] = len(self.subscriptions) + 1
            pending[self.channels[topic]["id"]] = self.subscriptions[topic]
        deadline = asyncio.get_running_loop().time() + timeout
        while pending:
            mark, barrier = len(self.ops), f"subscribed-{len(self.ops)}"
            pairs = [{"id": subscription, "channelId": channel} for channel, subscription in pending.items()]
            await self.send(op="subscribe", subscriptions=pairs)
            await self.send(op="getParameters", parameterNames=[barrier], id=barrier)  # no such parameter
            left = deadline - asyncio.get_running_loop().time()
            await self.until(lambda b=barrier: bool(self.ops_named("parameterValues", b)), max(left, 0.001))
            refused = {op["message"] for op in self.ops[mark:] if op["op"] == "status"}
            pending = {c: s for c, s in pending.items() if f"Unknown channel ID: {c}" in refused}

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
