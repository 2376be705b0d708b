"""A socketcand-compatible TCP endpoint bridging TCP clients and a python-can bus.

python-can's ``virtual`` bus only works inside one process, and a kernel vcan needs root to
create (where it exists, :class:`~dentibot.sim.can_bus_attach.CanBusBridge` attaches the bus
to it as well); :class:`SocketcandServer` lets a driver in *another* process reach a simulated
node (:class:`~dentibot.sim.epos4_node.Epos4Node`) sitting on a ``virtual`` bus, with no
privileges::

    can.Bus(interface="socketcand", host="127.0.0.1", port=server.port, channel="vcan0")

It speaks the socketcand ASCII protocol as far as python-can 4.6's ``socketcand`` client uses
it (raw mode). Every message is ``< ... >``:

- server greets ``< hi >``; ``< open vcan0 >`` -> ``< ok >`` (another channel:
  ``< error could not open bus >``); ``< rawmode >`` -> ``< ok >``; ``< bcmmode >`` ->
  ``< ok >``; ``< echo >`` -> ``< echo >`` (keep-alive).
- client -> bus: ``< send ID LEN B0 B1 ... >``: ID hex, 3 digits = 11-bit, 8 digits = 29-bit;
  LEN hex 0..8; bytes hex, one per field (python-can writes them without zero padding).
- bus -> client, raw mode: ``< frame ID SECS.USECS DATA >``: ID as above (upper case), the
  frame's timestamp, DATA all bytes as one upper-case hex string (empty for no data).

Unpleasant parts handled: commands split across TCP reads or several in one read, garbage
between commands (skipped and counted), over-long input without ``>`` (dropped), malformed
``send`` (answered ``< error ... >``, counted, connection kept). python-can's client checks
each handshake answer with a single ``recv`` compared *exactly*, so a frame glued to the last
``< ok >`` would break its handshake: after ``< rawmode >`` frames are held back until the
client sends its first message or ``handshake_grace_s`` has passed, then flushed in order.
A client that does not read fast enough gets frames dropped (``dropped``) once its write
buffer exceeds ``max_write_buffer`` bytes, like a full socket on the real daemon.

Frames a client sends are put on the bus and also copied to the other raw-mode clients (as
SocketCAN raw sockets on one host see each other's frames); never echoed to the sender.
The BCM commands of real socketcand (add, update, delete, subscribe, filter ...) are not
implemented: they are answered ``< error ... >``.

The ASCII codec (:class:`CommandBuffer`, :func:`parse_command`, :func:`parse_send`,
:func:`encode_frame`) is pure and lives here because its only other user is python-can's own
client.
"""

from __future__ import annotations

import asyncio
import socket
import time
from collections import deque
from dataclasses import dataclass, field

import can
import structlog

from dentibot.errors import ConfigError, ProtocolError
from dentibot.sim.canopen_node import BusAttached

log = structlog.get_logger(__name__)

DEVICE = "socketcand"
#: socketcand's default TCP port.
DEFAULT_PORT = 29536
#: Longest command accepted (characters between and including ``<`` and ``>``).
MAX_COMMAND_CHARS = 512


# ============================================================================ ASCII codec
class CommandBuffer:
    """Splits a TCP byte stream into ``< ... >`` commands, whatever the read boundaries.

    Bytes outside ``< ... >`` are skipped, and so is an opening ``<`` with no ``>`` within
    ``max_chars``; ``discarded`` counts the bytes skipped."""

    def __init__(self, max_chars: int = MAX_COMMAND_CHARS) -> None:
        self.max_chars = max_chars
        self.discarded = 0
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[str]:
        buf = self._buf
        buf += data
        out: list[str] = []
        while buf:
            start = buf.find(b"<")
            if start < 0:
                self.discarded += len(buf)
                buf.clear()
                break
            if start:
                self.discarded += start
                del buf[:start]
            end = buf.find(b">")
            if end < 0:
                if len(buf) > self.max_chars:
                    self.discarded += len(buf)
                    buf.clear()
                break
            inner = buf.rfind(b"<", 0, end)      # "< junk < send ... >": keep the last one
            if inner > 0:
                self.discarded += inner
                del buf[:inner]
                end -= inner
            raw = bytes(buf[:end + 1])
            del buf[:end + 1]
            if len(raw) > self.max_chars:
                self.discarded += len(raw)
                continue
            try:
                out.append(raw.decode("ascii"))
            except UnicodeDecodeError:
                self.discarded += len(raw)
        return out


def parse_command(text: str) -> tuple[str, list[str]]:
    """``"< send 123 2 a b >"`` -> ``("send", ["123", "2", "a", "b"])``."""
    if not (text.startswith("<") and text.endswith(">")):
        raise ProtocolError(DEVICE, f"{text!r} is not enclosed in < >")
    parts = text[1:-1].split()
    if not parts:
        raise ProtocolError(DEVICE, "empty command < >")
    return parts[0].lower(), parts[1:]


def _hex(field_name: str, s: str, max_value: int) -> int:
    try:
        v = int(s, 16)
    except ValueError:
        raise ProtocolError(DEVICE, f"{field_name} {s!r} is not hexadecimal") from None
    if not 0 <= v <= max_value or s.startswith(("-", "+")) or "_" in s or s[:2].lower() == "0x":
        raise ProtocolError(DEVICE, f"{field_name} {s!r} is not a hex number 0..{max_value:X}")
    return v


def parse_send(args: list[str]) -> tuple[int, bool, bytes]:
    """(can id, extended?, data) of the arguments of a ``send`` command."""
    if len(args) < 2:
        raise ProtocolError(DEVICE, f"send needs an id and a length, got {args}")
    sid, slen, sbytes = args[0], args[1], args[2:]
    if len(sid) == 8:
        can_id, ext = _hex("id", sid, 0x1FFF_FFFF), True
    elif 1 <= len(sid) <= 3:
        can_id, ext = _hex("id", sid, 0x7FF), False
    else:
        raise ProtocolError(DEVICE, f"id {sid!r}: 3 hex digits (11-bit) or 8 (29-bit)")
    n = _hex("length", slen, 8)
    if len(sbytes) != n:
        raise ProtocolError(DEVICE, f"length {n} but {len(sbytes)} data bytes given")
    if any(len(b) > 2 for b in sbytes):
        raise ProtocolError(DEVICE, f"data bytes {sbytes}: at most 2 hex digits each")
    return can_id, ext, bytes(_hex("data byte", b, 0xFF) for b in sbytes)


def encode_frame(can_id: int, is_extended: bool, data: bytes, timestamp: float) -> str:
    """``< frame ID SECS.USECS DATA >`` as socketcand sends a received frame in raw mode."""
    sid = f"{can_id & 0x1FFF_FFFF:08X}" if is_extended else f"{can_id & 0x7FF:03X}"
    secs = int(timestamp)
    usecs = round((timestamp - secs) * 1e6)
    if usecs >= 1_000_000:
        secs, usecs = secs + 1, usecs - 1_000_000
    return f"< frame {sid} {secs}.{usecs:06d} {bytes(data).hex().upper()} >"


# ============================================================================ server
@dataclass(eq=False)
class _Client:
    writer: asyncio.StreamWriter
    peer: str
    buffer: CommandBuffer = field(default_factory=CommandBuffer)
    mode: str = "init"              # init (after hi) -> bcm (after open) -> raw
    live: bool = False              # raw mode and the handshake is surely over
    pending: deque = field(default_factory=lambda: deque(maxlen=1024))
    grace: asyncio.TimerHandle | None = None
    errors: int = 0


class SocketcandServer(BusAttached):
    """socketcand endpoint for ``bus`` (a python-can bus, owned by the caller).

    Args:
        bus: the bus to bridge (e.g. ``can.Bus(interface="virtual", channel=...)``).
        host: address to bind (127.0.0.1).
        port: TCP port (29536, socketcand's default; 0 = ephemeral, see ``port`` after
            ``start()``).
        channel: the channel name clients must ``open`` ("vcan0").
        handshake_grace_s: after ``< rawmode >`` hold frames back until the client speaks or
            this long has passed (0.25 s).
        max_write_buffer: bytes queued to one client beyond which frames are dropped.
    """

    def __init__(self, bus: can.BusABC, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 channel: str = "vcan0", *, handshake_grace_s: float = 0.25,
                 max_write_buffer: int = 256 * 1024) -> None:
        if not 0 <= port <= 65535:
            raise ConfigError("socketcand.port", port, "0..65535 (0 = ephemeral)")
        if not handshake_grace_s >= 0:
            raise ConfigError("socketcand.handshake_grace_s", handshake_grace_s, ">= 0 s")
        self.bus = bus
        self.host = host
        self.port = port
        self.channel = channel
        self.handshake_grace_s = float(handshake_grace_s)
        self.max_write_buffer = int(max_write_buffer)
        # counters
        self.clients_served = 0
        self.frames_from_bus = 0
        self.frames_from_clients = 0
        self.frames_to_clients = 0
        self.dropped = 0
        self.errors = 0
        self._clients: set[_Client] = set()
        self._tasks: set[asyncio.Task] = set()
        self._server: asyncio.Server | None = None
        self._closed = False
        self._commands = {
            "open": self._cmd_open,
            "rawmode": self._cmd_rawmode,
            "bcmmode": self._cmd_bcmmode,
            "echo": self._cmd_echo,
            "send": self._cmd_send,
        }

    @property
    def clients(self) -> int:
        return len(self._clients)

    async def start(self) -> None:
        if self._server is not None:
            return
        if self._closed:
            raise ConfigError("socketcand", "closed", "a server that has not been closed")
        self._server = await asyncio.start_server(self._serve, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        self._attach(self.bus, self._on_bus_frame)
        log.info("socketcand server listening", host=self.host, port=self.port,
                 channel=self.channel)

    async def close(self) -> None:
        """Stop listening, drop every client, detach from the bus (idempotent; the bus
        stays open)."""
        if self._closed:
            return
        self._closed = True
        if self._server is not None:
            self._server.close()
        for client in list(self._clients):
            self._drop(client)                  # the handlers then read EOF and return
        tasks = list(self._tasks)
        if tasks:
            _, late = await asyncio.wait(tasks, timeout=1.0)
            for t in late:
                t.cancel()
            if late:
                await asyncio.gather(*late, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()
            self._server = None
        self._detach()

    # ------------------------------------------------------------------ per client
    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        peer = str(writer.get_extra_info("peername"))
        client = _Client(writer, peer)
        self._clients.add(client)
        self.clients_served += 1
        log.info("socketcand client connected", peer=peer)
        try:
            writer.write(b"< hi >")
            while not self._closed:
                data = await reader.read(4096)
                if not data:
                    break
                for text in client.buffer.feed(data):
                    self._handle(client, text)
        except (ConnectionError, OSError) as exc:
            log.info("socketcand client connection error", peer=peer, error=str(exc))
        except asyncio.CancelledError:
            # only close() cancels a handler; end quietly, since asyncio's stream callback
            # reports a handler task that ends cancelled as an unhandled exception
            pass
        finally:
            self._drop(client)
            if task is not None:
                self._tasks.discard(task)
            log.info("socketcand client gone", peer=peer, errors=client.errors,
                     discarded_bytes=client.buffer.discarded)

    def _drop(self, client: _Client) -> None:
        self._clients.discard(client)
        if client.grace is not None:
            client.grace.cancel()
            client.grace = None
        client.writer.transport.abort()

    def _reply(self, client: _Client, text: str) -> None:
        if not client.writer.transport.is_closing():
            client.writer.write(text.encode("ascii"))

    def _error(self, client: _Client, why: str) -> None:
        client.errors += 1
        self.errors += 1
        log.warning("socketcand bad command", peer=client.peer, error=why)
        self._reply(client, f"< error {why} >")

    def _handle(self, client: _Client, text: str) -> None:
        if client.mode == "raw" and not client.live:
            self._go_live(client)           # it has read our "< ok >": frames may follow
        try:
            verb, args = parse_command(text)
        except ProtocolError as exc:
            self._error(client, str(exc).removeprefix(f"{DEVICE}: "))
            return
        handler = self._commands.get(verb)
        if handler is None:
            self._error(client, f"unknown or unsupported command {verb}")
            return
        handler(client, args)

    def _cmd_open(self, client: _Client, args: list[str]) -> None:
        if client.mode != "init":
            self._error(client, "bus already open")
        elif args != [self.channel]:
            self._error(client, "could not open bus")
        else:
            client.mode = "bcm"
            self._reply(client, "< ok >")

    def _cmd_rawmode(self, client: _Client, args: list[str]) -> None:
        if client.mode == "init":
            self._error(client, "no bus open")
            return
        client.mode = "raw"
        client.live = False
        client.pending.clear()
        self._reply(client, "< ok >")
        client.grace = asyncio.get_running_loop().call_later(
            self.handshake_grace_s, self._go_live, client)

    def _cmd_bcmmode(self, client: _Client, args: list[str]) -> None:
        if client.mode == "init":
            self._error(client, "no bus open")
            return
        client.mode, client.live = "bcm", False
        self._reply(client, "< ok >")

    def _cmd_echo(self, client: _Client, args: list[str]) -> None:
        self._reply(client, "< echo >")

    def _cmd_send(self, client: _Client, args: list[str]) -> None:
        if client.mode == "init":
            self._error(client, "no bus open")
            return
        try:
            can_id, ext, data = parse_send(args)
        except ProtocolError as exc:
            self._error(client, str(exc).removeprefix(f"{DEVICE}: "))
            return
        msg = can.Message(arbitration_id=can_id, is_extended_id=ext, data=data,
                          timestamp=time.time())
        try:
            self.bus.send(msg)
        except (can.CanError, OSError) as exc:
            self._error(client, f"send failed {type(exc).__name__}")
            return
        self.frames_from_clients += 1
        line = encode_frame(can_id, ext, data, msg.timestamp).encode("ascii")
        for other in list(self._clients):
            if other is not client and other.mode == "raw":
                self._to_client(other, line)

    def _go_live(self, client: _Client) -> None:
        if client.grace is not None:
            client.grace.cancel()
            client.grace = None
        if client.mode != "raw" or client.live:
            return
        client.live = True
        while client.pending:
            self._write(client, client.pending.popleft())

    # ------------------------------------------------------------------ bus -> clients
    def _on_bus_frame(self, msg: can.Message) -> None:
        if self._closed or msg.is_error_frame or msg.is_remote_frame:
            return
        self.frames_from_bus += 1
        line = encode_frame(msg.arbitration_id, msg.is_extended_id, bytes(msg.data),
                            msg.timestamp or time.time()).encode("ascii")
        for client in list(self._clients):
            if client.mode == "raw":
                self._to_client(client, line)

    def _to_client(self, client: _Client, line: bytes) -> None:
        if client.live:
            self._write(client, line)
        else:
            if len(client.pending) == client.pending.maxlen:
                self.dropped += 1
            client.pending.append(line)

    def _write(self, client: _Client, line: bytes) -> None:
        transport = client.writer.transport
        if transport.is_closing():
            return
        if transport.get_write_buffer_size() > self.max_write_buffer:
            self.dropped += 1
            return
        client.writer.write(line)
        self.frames_to_clients += 1
