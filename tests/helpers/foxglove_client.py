"""A Foxglove WebSocket client, as a viewer talks to a live server: connect (subprotocol
``foxglove.sdk.v1``), read ``serverInfo`` and ``advertise``, subscribe to every advertised
channel, and keep each binary MessageData frame (opcode 1: subscription id u32, log time u64,
payload; little-endian) by topic, and each Time frame (opcode 2: u64 ns). The protocol is
Foxglove's published one (foxglove/ws-protocol); the transport is the ``websockets`` package.
"""

from __future__ import annotations

import json
import struct
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA, TIME = 1, 2


@dataclass
class FoxgloveClient:
    url: str
    channels: dict[int, dict[str, Any]] = field(default_factory=dict)  # id → advertisement
    messages: dict[str, list[tuple[int, bytes]]] = field(
        default_factory=lambda: defaultdict(list))  # topic → [(log time ns, payload)]
    times_ns: list[int] = field(default_factory=list)
    server_info: dict[str, Any] | None = None
    error: BaseException | None = None

    def __post_init__(self) -> None:
        self._stop = threading.Event()
        self._subscribed: dict[int, str] = {}  # subscription id → topic
        self._thread = threading.Thread(target=self._run, daemon=True, name="foxglove-client")

    def start(self, connect_timeout_s: float = 20.0) -> None:
        self._connect_deadline = time.monotonic() + connect_timeout_s
        self._thread.start()

    def wait_closed(self, timeout_s: float = 10.0) -> None:
        """Read until the server closes the connection (everything it sent is then here);
        AssertionError if it does not within ``timeout_s``; what the client hit, raised."""
        self._thread.join(timeout=timeout_s)
        if self._thread.is_alive():
            self._stop.set()
            self._thread.join(timeout=5.0)
            raise AssertionError(f"{self.url} still open {timeout_s:g} s after the run ended")
        if self.error is not None:
            raise self.error

    def _run(self) -> None:
        try:
            socket = self._connect()
            with socket:
                while not self._stop.is_set():
                    try:
                        frame = socket.recv(timeout=0.1)
                    except TimeoutError:
                        continue
                    except ConnectionClosed:
                        return
                    if isinstance(frame, str):
                        self._on_text(socket, json.loads(frame))
                    else:
                        self._on_binary(frame)
        except BaseException as err:  # handed to stop()
            self.error = err

    def _connect(self):
        while True:  # the server may not be up yet
            try:
                return connect(self.url, subprotocols=SUBPROTOCOLS, open_timeout=2.0)
            except OSError:
                if time.monotonic() > self._connect_deadline or self._stop.is_set():
                    raise
                time.sleep(0.05)

    def _on_text(self, socket, message: dict[str, Any]) -> None:
        if message["op"] == "serverInfo":
            self.server_info = message
        elif message["op"] == "advertise":
            subscriptions = []
            for channel in message["channels"]:
                self.channels[channel["id"]] = channel
                sub_id = len(self._subscribed) + 1
                self._subscribed[sub_id] = channel["topic"]
                subscriptions.append({"id": sub_id, "channelId": channel["id"]})
            socket.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    def _on_binary(self, frame: bytes) -> None:
        if frame[0] == MESSAGE_DATA:
            sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
            self.messages[self._subscribed[sub_id]].append((log_time, bytes(frame[13:])))
        elif frame[0] == TIME:
            (stamp,) = struct.unpack_from("<Q", frame, 1)
            self.times_ns.append(stamp)
