"""A minimal Foxglove WebSocket protocol client (for tests/test_live_stack.py), written from the
protocol: RFC 6455 framing, ``advertise`` -> ``subscribe``, binary ``messageData`` (opcode 1:
subscription id u32, log time u64, payload). Loopback only; no third-party package."""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import threading
from collections import defaultdict


class FoxgloveClient:
    """Connect to ``127.0.0.1:port``, subscribe to every advertised channel whose topic is in
    ``topics``, and count (and keep the sizes of) the messages of each topic in a thread."""

    def __init__(self, port: int, topics: tuple[str, ...]) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        key = base64.b64encode(os.urandom(16)).decode()
        request = (
            f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
            "Sec-WebSocket-Protocol: foxglove.sdk.v1, foxglove.websocket.v1\r\n\r\n"
        )
        self.sock.sendall(request.encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        assert b" 101 " in head.split(b"\r\n")[0], head
        self.topics = topics
        self.channels: dict[int, dict] = {}
        self.subscribed: dict[int, str] = {}  # subscription id -> topic
        self.messages: dict[str, list[int]] = defaultdict(list)  # topic -> payload sizes
        self.server_info: dict | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _recv(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            chunk = self.sock.recv(n - len(out))
            if not chunk:
                raise ConnectionError("closed")
            out += chunk
        return out

    def _frame(self) -> tuple[int, bytes]:
        opcode, payload = 0, b""
        while True:
            b0, b1 = self._recv(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._recv(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._recv(8))[0]
            mask = self._recv(4) if b1 & 0x80 else None
            data = self._recv(n)
            if mask:
                data = bytes(b ^ mask[i % 4] for i, b in enumerate(data))
            opcode = opcode or (b0 & 0x0F)
            payload += data
            if b0 & 0x80:
                return opcode, payload

    def _send_text(self, text: str) -> None:
        data = text.encode()
        mask = os.urandom(4)
        head = bytes([0x81])
        n = len(data)
        head += bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n)
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def _run(self) -> None:
        next_id = 1
        while not self._stop.is_set():
            try:
                opcode, payload = self._frame()
            except (OSError, ConnectionError):
                return
            if opcode == 1:
                msg = json.loads(payload)
                if msg.get("op") == "serverInfo":
                    self.server_info = msg
                elif msg.get("op") == "advertise":
                    subs = []
                    for ch in msg["channels"]:
                        self.channels[ch["id"]] = ch
                        if ch["topic"] in self.topics:
                            self.subscribed[next_id] = ch["topic"]
                            subs.append({"id": next_id, "channelId": ch["id"]})
                            next_id += 1
                    if subs:
                        self._send_text(json.dumps({"op": "subscribe", "subscriptions": subs}))
            elif opcode == 2 and payload[:1] == b"\x01":
                sub_id = struct.unpack_from("<I", payload, 1)[0]
                self.messages[self.subscribed.get(sub_id, "?")].append(len(payload) - 13)
            elif opcode == 8:
                return

    def ready(self) -> bool:
        """True once every topic of ``topics`` is subscribed."""
        return set(self.subscribed.values()) >= set(self.topics)

    def close(self) -> None:
        self._stop.set()
        try:
            self.sock.close()
        except OSError:
            pass
