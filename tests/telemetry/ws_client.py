"""A small client of the Foxglove WebSocket protocol, written from the specifications alone.

RFC 6455 (the opening handshake with its ``Sec-WebSocket-Accept`` check, frames, masking of
client frames, fragmentation, ping/pong, close) and the Foxglove WebSocket protocol v1 (JSON
``serverInfo``/``advertise`` from the server, the client's JSON ``subscribe``, binary Message
Data ``0x01 | uint32 subscription id | uint64 log time ns | payload``, little-endian). The
protocol has two subprotocol names: ``foxglove.websocket.v1`` and, for the same messages,
``foxglove.sdk.v1``, the only one the Foxglove SDK's server accepts; like the viewers, the
client offers both and the server picks. The standard library only: the live view is checked
against the protocol, not against a second implementation built on the same code.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import socket
import struct
import time
from dataclasses import dataclass

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
_GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"          # RFC 6455, section 1.3

OP_CONT, OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0x0, 0x1, 0x2, 0x8, 0x9, 0xA
MESSAGE_DATA = 0x01                                   # Foxglove server binary opcode


@dataclass
class MessageData:
    subscription_id: int
    log_time_ns: int
    payload: bytes


class FoxgloveWsClient:
    """Connects, completes the handshake, then reads whole messages (text: the decoded JSON
    object; binary Message Data: :class:`MessageData`)."""

    def __init__(self, host: str, port: int, timeout: float = 10.0) -> None:
        self.sock = socket.create_connection((host, port), timeout=timeout)
        self._buf = b""
        key = base64.b64encode(os.urandom(16)).decode()
        request = (f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                   f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                   f"Sec-WebSocket-Version: 13\r\n"
                   f"Sec-WebSocket-Protocol: {', '.join(SUBPROTOCOLS)}\r\n\r\n")
        self.sock.sendall(request.encode())
        head = self._read_until(b"\r\n\r\n").decode("latin-1")
        status, *lines = head.split("\r\n")
        headers = {k.strip().lower(): v.strip()
                   for k, _, v in (line.partition(":") for line in lines if line)}
        if " 101 " not in f"{status} ":
            raise ConnectionError(f"handshake refused: {status}")
        accept = base64.b64encode(hashlib.sha1((key + _GUID).encode()).digest()).decode()
        if headers.get("sec-websocket-accept") != accept:
            raise ConnectionError("bad Sec-WebSocket-Accept")
        self.subprotocol = headers.get("sec-websocket-protocol")
        if self.subprotocol not in SUBPROTOCOLS:
            raise ConnectionError(f"the server chose {self.subprotocol!r}, not one offered")

    def _read_until(self, marker: bytes) -> bytes:
        while marker not in self._buf:
            self._recv()
        head, _, self._buf = self._buf.partition(marker)
        return head

    def _recv(self) -> None:
        chunk = self.sock.recv(65536)
        if not chunk:
            raise ConnectionError("connection closed by the server")
        self._buf += chunk

    def _read_exact(self, n: int) -> bytes:
        while len(self._buf) < n:
            self._recv()
        out, self._buf = self._buf[:n], self._buf[n:]
        return out

    def _frame(self) -> tuple[bool, int, bytes]:
        b0, b1 = self._read_exact(2)
        fin, opcode = bool(b0 & 0x80), b0 & 0x0F
        masked, n = bool(b1 & 0x80), b1 & 0x7F
        if n == 126:
            (n,) = struct.unpack("!H", self._read_exact(2))
        elif n == 127:
            (n,) = struct.unpack("!Q", self._read_exact(8))
        mask = self._read_exact(4) if masked else None
        payload = self._read_exact(n)
        if mask:
            payload = bytes(c ^ mask[i % 4] for i, c in enumerate(payload))
        return fin, opcode, payload

    def _send(self, opcode: int, payload: bytes) -> None:
        mask = os.urandom(4)                             # client frames are always masked
        n = len(payload)
        if n < 126:
            head = struct.pack("!BB", 0x80 | opcode, 0x80 | n)
        elif n < 1 << 16:
            head = struct.pack("!BBH", 0x80 | opcode, 0x80 | 126, n)
        else:
            head = struct.pack("!BBQ", 0x80 | opcode, 0x80 | 127, n)
        body = bytes(c ^ mask[i % 4] for i, c in enumerate(payload))
        self.sock.sendall(head + mask + body)

    def send_json(self, obj: dict) -> None:
        self._send(OP_TEXT, json.dumps(obj).encode())

    def receive(self) -> dict | MessageData:
        """The next whole text or binary message (control frames handled on the way)."""
        parts: list[bytes] = []
        kind = None
        while True:
            fin, opcode, payload = self._frame()
            if opcode == OP_PING:
                self._send(OP_PONG, payload)
                continue
            if opcode == OP_PONG:
                continue
            if opcode == OP_CLOSE:
                raise ConnectionError("closed by the server")
            if opcode != OP_CONT:
                kind = opcode
            parts.append(payload)
            if fin:
                break
        data = b"".join(parts)
        if kind == OP_TEXT:
            return json.loads(data)
        op, sub, log_ns = struct.unpack_from("<BIQ", data)
        if op != MESSAGE_DATA:
            raise ValueError(f"unexpected binary opcode {op:#x}")
        return MessageData(sub, log_ns, data[13:])

    def advertised(self, topics: set[str], timeout: float = 10.0) -> dict[str, dict]:
        """Read until every topic in ``topics`` is advertised; topic -> channel."""
        channels: dict[str, dict] = {}
        deadline = time.monotonic() + timeout
        while not topics <= set(channels):
            if time.monotonic() > deadline:
                raise TimeoutError(f"not advertised: {topics - set(channels)}")
            msg = self.receive()
            if isinstance(msg, dict) and msg.get("op") == "advertise":
                channels.update({c["topic"]: c for c in msg["channels"]})
        return channels

    def close(self) -> None:
        try:
            self._send(OP_CLOSE, struct.pack("!H", 1000))
        except OSError:
            pass
        self.sock.close()
