"""CANopen master plumbing on python-can (CiA 301), shared by the device drivers.

:class:`CanOpenMaster` holds what a master needs besides its device's profile: opening the
bus (kernel SocketCAN, python-can's ``virtual`` bus, any python-can interface, a bus
factory, or a socketcand server through :class:`SocketcandBus`), in a thread and bounded by
``connect_timeout_s`` (a silent peer is a :class:`~dentibot.io.interfaces.ConnectTimeout`);
reception by COB-ID (frames handed to the event loop in batches by
:class:`~dentibot.io.can_reader.LoopReader`, which the loop runs itself for a bus with a file
descriptor); expedited SDO transfers, one outstanding at a
time, each bounded by ``sdo_timeout_s`` (an abort is a :class:`SdoAbort` with its CiA 301
abort code); NMT commands; the heartbeat consumer's parameters (CiA 301: a node silent for
longer than ``heartbeat_timeout_s`` is lost); the master's cyclic task (SYNC producer);
teardown.
"""

from __future__ import annotations

import asyncio
import math
import select
import socket
import time
from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from operator import methodcaller
from typing import Any, Self

import can
import structlog

from dentibot.errors import DeviceFault, ProtocolError
from dentibot.io import canopen_protocol as co
from dentibot.io.can_reader import LoopReader
from dentibot.io.canopen_protocol import NmtCommand, OdObject, SdoFrame
from dentibot.io.interfaces import ConnectTimeout
from dentibot.io.tasks import in_thread
from dentibot.io.virtual_bus import LoopVirtualBus

log = structlog.get_logger(__name__)

#: Bad frames and failed sends logged one by one before logging only every ``_LOG_EVERY``-th.
_LOG_FIRST, _LOG_EVERY = 10, 1000
#: Reader receive timeout (s): how long ``close()`` may wait for the reader thread.
_READER_TIMEOUT_S = 0.05

#: socketcand's default TCP port.
SOCKETCAND_PORT = 29536
#: How long closing a socketcand connection waits for the server to close its side.
_CLOSE_DRAIN_S = 0.1
#: Longest socketcand message accepted (characters from ``<`` to ``>``); a frame line is
#: under 60.
_SOCKETCAND_MAX_CHARS = 512


class ConfigurationMismatch(DeviceFault):
    """The node does not hold a value the driver wrote at start-up (read back differs):
    ``obj`` (the object), ``written``, ``read``. A node that would not act as configured
    (a drive not watching the host's heartbeat, an encoder not reporting in the configured
    units) must not be run."""

    def __init__(self, device: str, obj: OdObject, written: int, read: int, why: str) -> None:
        self.obj, self.written, self.read = obj, written, read
        super().__init__(device, f"{obj} reads back {read} (0x{read:X}) after writing "
                                 f"{written} (0x{written:X}): {why}")


class SocketcandBus(can.BusABC):
    """A socketcand client (raw mode) whose every wait is bounded.

    The ASCII protocol (socketcand's documentation, as python-can's client uses it): the
    server greets ``< hi >``; ``< open CHANNEL >`` -> ``< ok >``; ``< rawmode >`` -> ``< ok >``;
    then ``< send ID LEN B0 .. >`` to the bus (ID 3 hex digits for 11-bit, 8 for 29-bit) and
    ``< frame ID SECS.USECS DATA >`` from it (DATA one hex string). python-can's own client
    waits for the greeting with no time limit, retries a refused connection for 10 s and
    compares each handshake answer to a single ``recv``; this one:

    - connects with ``timeout_s`` and finishes the whole handshake before the same deadline;
      no greeting in time is :class:`TimeoutError` (the driver turns it into
      :class:`~dentibot.io.interfaces.ConnectTimeout` naming the address), an ``< error .. >``
      answer is :class:`can.CanInitializationError`;
    - buffers the stream, so answers and frames split or glued across TCP reads are fine;
    - bounds every send by ``send_timeout_s`` (a peer that stops reading makes ``send`` raise
      :class:`can.CanOperationError` instead of blocking the event loop);
    - reports a closed connection as :class:`can.CanOperationError` from ``recv`` (the
      reader hands it to the driver as a link error).
    """

    def __init__(self, channel: str, host: str = "127.0.0.1", port: int = SOCKETCAND_PORT, *,
                 timeout_s: float = 2.0, send_timeout_s: float = 0.05, tcp_tune: bool = True,
                 **kwargs: Any) -> None:
        self.host, self.port = host, port
        self.channel = channel
        self.timeout_s = float(timeout_s)
        self._text = ""
        self._frames: deque[can.Message] = deque()
        self.channel_info = f"socketcand {host}:{port} channel {channel}"
        deadline = time.monotonic() + self.timeout_s
        try:
            sock = socket.create_connection((host, port), timeout=self.timeout_s)
        except TimeoutError:
            raise TimeoutError("TCP connection") from None
        try:
            if tcp_tune:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._sock = sock
            self._expect("< hi >", "greeting", deadline)
            self._say(f"< open {channel} >", deadline)
            self._expect("< ok >", f"answer to < open {channel} >", deadline)
            self._say("< rawmode >", deadline)
            self._expect("< ok >", "answer to < rawmode >", deadline)
            sock.settimeout(float(send_timeout_s))
        except BaseException:
            sock.close()
            raise
        super().__init__(channel=channel, **kwargs)

    # ---------------------------------------------------------------- handshake
    def _say(self, text: str, deadline: float) -> None:
        self._sock.settimeout(max(1e-3, deadline - time.monotonic()))
        self._sock.sendall(text.encode("ascii"))

    def _expect(self, want: str, what: str, deadline: float) -> None:
        while True:
            msg = self._next_message()
            if msg is not None:
                if msg == want:
                    return
                if msg.startswith("< frame "):          # a frame before the answer: keep it
                    self._keep_frame(msg)
                    continue
                if msg.startswith("< error"):
                    raise can.CanInitializationError(
                        f"{self.channel_info}: {what}: the server answered {msg!r}")
                raise can.CanInitializationError(
                    f"{self.channel_info}: {what}: expected {want!r}, got {msg!r}")
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(what)
            self._sock.settimeout(left)
            try:
                data = self._sock.recv(4096)
            except TimeoutError:
                raise TimeoutError(what) from None
            if not data:
                raise can.CanInitializationError(
                    f"{self.channel_info}: the server closed the connection before its {what}")
            self._text += data.decode("ascii", "replace")

    def _next_message(self) -> str | None:
        """Take the next complete ``< ... >`` message off the buffer (bytes outside one, and
        over-long ones, are skipped)."""
        text = self._text
        while True:
            start = text.find("<")
            if start < 0:
                self._text = ""
                return None
            end = text.find(">", start)
            if end < 0:
                self._text = text[start:] if len(text) - start <= _SOCKETCAND_MAX_CHARS else ""
                return None
            msg, text = text[start:end + 1], text[end + 1:]
            if len(msg) <= _SOCKETCAND_MAX_CHARS:
                self._text = text
                return msg

    def _keep_frame(self, msg: str) -> None:
        frame = self.parse_frame(msg)
        if frame is not None:
            frame.channel = self.channel
            self._frames.append(frame)

    @staticmethod
    def parse_frame(msg: str) -> can.Message | None:
        """``< frame ID SECS.USECS DATA >`` -> :class:`can.Message` (None if malformed)."""
        parts = msg[1:-1].split()
        if len(parts) not in (3, 4) or parts[0] != "frame":
            return None
        sid, stamp = parts[1], parts[2]
        data_hex = parts[3] if len(parts) == 4 else ""
        try:
            can_id = int(sid, 16)
            ts = float(stamp)
            data = bytes.fromhex(data_hex)
        except ValueError:
            return None
        if len(sid) not in (3, 8) or len(data) > 8:
            return None
        return can.Message(timestamp=ts, arbitration_id=can_id, is_extended_id=len(sid) == 8,
                           data=data)

    @staticmethod
    def send_line(msg: can.Message) -> str:
        sid = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
        data = bytes(msg.data)[:msg.dlc]
        return " ".join(["<", "send", sid, f"{len(data):X}", *(f"{b:02X}" for b in data), ">"])

    # ---------------------------------------------------------------- BusABC
    def fileno(self) -> int:
        """The connection's socket: an event loop watches it for frames (python-can's
        convention, as its SocketCAN bus)."""
        return self._sock.fileno()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        while True:
            if self._frames:
                return self._frames.popleft(), False
            msg = self._next_message()
            if msg is not None:
                if msg.startswith("< frame "):
                    self._keep_frame(msg)
                continue                                # < ok >, < echo >, < error ..>
            try:
                ready, _, _ = select.select([self._sock], [], [], timeout)
            except (OSError, ValueError) as exc:
                raise can.CanOperationError(f"{self.channel_info}: receive failed: "
                                            f"{exc}") from exc
            if not ready:
                return None, False
            try:
                data = self._sock.recv(4096)
            except OSError as exc:
                raise can.CanOperationError(f"{self.channel_info}: receive failed: "
                                            f"{exc}") from exc
            if not data:
                raise can.CanOperationError(f"{self.channel_info}: the server closed the "
                                            "connection")
            self._text += data.decode("ascii", "replace")
            timeout = 0.0

    def drain(self, limit: int) -> list[can.Message]:
        """Up to ``limit`` frames that can be had now without waiting, in order: what the
        socket holds is read once, and the complete frames in the buffer are parsed (the
        rest stay for the next call). For an event loop's callback when the socket is
        readable (:class:`~dentibot.io.can_reader.LoopReader`): one read and no waiting, where
        python-can's ``recv(0)`` per frame polls the socket once for each. The end of the
        stream, or a failed read, is :class:`can.CanOperationError`."""
        sock = self._sock
        try:
            if select.select([sock], [], [], 0)[0]:
                data = sock.recv(65536)
                if not data:
                    raise can.CanOperationError(f"{self.channel_info}: the server closed the "
                                                "connection")
                self._text += data.decode("ascii", "replace")
        except (OSError, ValueError) as exc:
            raise can.CanOperationError(f"{self.channel_info}: receive failed: {exc}") from exc
        frames = self._frames
        while len(frames) < limit and (msg := self._next_message()) is not None:
            if msg.startswith("< frame "):
                self._keep_frame(msg)
        out = [frames.popleft() for _ in range(min(limit, len(frames)))]
        return out

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.send_text(self.send_line(msg).encode("ascii"))

    def send_text(self, text: bytes) -> None:
        """Send ``< send .. >`` lines already encoded (several frames in one TCP write: see
        :meth:`CanOpenMaster._send_frames`)."""
        try:
            self._sock.sendall(text)
        except OSError as exc:              # TimeoutError included: the peer stopped reading
            raise can.CanOperationError(f"{self.channel_info}: send failed: {exc!r}") from exc

    @classmethod
    def send_text_of(cls, frames: Sequence[tuple[int, bytes]]) -> bytes:
        """The ``< send .. >`` lines of standard frames ``(COB-ID, data)``, in order."""
        return "".join(cls.send_line(can.Message(arbitration_id=cid, data=data,
                                                 is_extended_id=False))
                       for cid, data in frames).encode("ascii")

    def shutdown(self) -> None:
        """Close the connection gracefully: our end is shut first (the server reads every
        frame sent so far, then the end of the stream), and what the server still sends is
        read and dropped until it closes too, for at most ``_CLOSE_DRAIN_S``. A socket
        closed with frames unread in it sends a reset instead, and a reset makes the
        server's kernel drop what the server had not read yet: the last frames sent
        (the drive's disable, the NMT stop) would be lost."""
        super().shutdown()
        sock = self._sock
        try:
            sock.shutdown(socket.SHUT_WR)
            deadline = time.monotonic() + _CLOSE_DRAIN_S
            while (left := deadline - time.monotonic()) > 0:
                sock.settimeout(left)
                if not sock.recv(4096):
                    break
        except OSError:                     # (TimeoutError included) reset, gone, or silent
            pass
        finally:
            sock.close()



class SdoAbort(DeviceFault):
    """The node refused an SDO: ``code`` (CiA 301 abort code), ``index``, ``sub``."""

    def __init__(self, device: str, index: int, sub: int, code: int, verb: str) -> None:
        self.index, self.sub, self.code = index, sub, code
        super().__init__(device, f"SDO {verb} 0x{index:04X}:{sub:02X} aborted with 0x{code:08X}"
                                 f" ({co.sdo_abort_meaning(code)})")


def _resolve(fut: asyncio.Future, value: object) -> None:
    if not fut.done():
        fut.set_result(value)


#: A frame handler: (payload, time of reception on the monotonic clock).
Handler = Callable[[bytes, float], None]


class CanOpenMaster:
    """Base of a CANopen master driver: the bus, reception, SDO client, NMT, teardown.

    A subclass registers its frame handlers in ``_handlers`` (COB-ID -> :data:`Handler`),
    calls :meth:`_open_bus` in its ``connect()`` and :meth:`_teardown` in its ``close()``.
    Log events start with :attr:`log_name`; a handler raising
    :class:`~dentibot.errors.ProtocolError` counts a bad frame in ``errors``.

    Args:
        bus_factory: zero-argument callable returning an open ``can.BusABC``; the driver
            owns it (shuts it down on close). None: ``can.Bus(interface, channel, ...)``.
        interface: python-can interface name ("socketcan", "socketcand", "virtual", ...).
        channel: CAN channel ("can0"; for socketcand the server's channel, e.g. "vcan0").
        host, port: socketcand server address (29536 is socketcand's default port).
        bus_kwargs: extra keyword arguments for ``can.Bus`` (e.g. ``bitrate``). For
            socketcand ``tcp_tune=True`` (TCP_NODELAY) is the default here.
        sdo_timeout_s: per SDO request.
        connect_timeout_s: opening the bus, for socketcand the TCP connection and the whole
            handshake.
        sync_period_s: period of the master's own cyclic task (:meth:`_cyclic`).
        heartbeat_ms: the nodes' producer heartbeat time 0x1017 (ms; None: the node's own);
            heartbeat_timeout_s: silence after which a node counts as lost.
        name: device name in errors and logs.

    A subclass provides ``connect()`` and ``close()``; ``async with`` uses them.
    """

    #: First word of the log events ("epos4 send failed").
    log_name = "canopen"
    #: How :meth:`_bus_description` names a bus from ``bus_factory``.
    factory_description = "the bus from the factory"
    #: Count CAN error frames in ``errors`` (else they are ignored).
    count_error_frames = False

    def __init__(self, bus_factory: Callable[[], can.BusABC] | None, *, interface: str,
                 channel: str, host: str, port: int, bus_kwargs: dict[str, Any] | None,
                 sdo_timeout_s: float, connect_timeout_s: float, sync_period_s: float,
                 heartbeat_ms: int | None, heartbeat_timeout_s: float, name: str) -> None:
        self._bus_factory = bus_factory
        self.interface, self.channel = interface, channel
        self.host, self.port = host, port
        self.bus_kwargs = dict(bus_kwargs or {})
        self.sdo_timeout_s = float(sdo_timeout_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self.sync_period_s = float(sync_period_s)
        self.heartbeat_ms = heartbeat_ms
        self.heartbeat_timeout_s = float(heartbeat_timeout_s)
        self.name = name
        self._handlers: dict[int, Handler] = {}
        self.errors = 0             # frames that broke the protocol (wrong length ...)
        self.send_errors = 0
        self.sdo_requests = 0
        self.sdo_aborts = 0
        self.sdo_timeouts = 0
        self.overruns = 0           # own cycles skipped because the loop was late
        self._ask: asyncio.Future | None = None     # the own cycle's wait (cycle_soon)
        self._asked_t = -math.inf   # when cycle_soon was last called (loop time)
        self._cycle_t = -math.inf   # when the own cycle last ran (loop time)
        self._link_error: str | None = None
        self._bus: can.BusABC | None = None
        self._frames_sent: tuple | None = None   # see _send_frames
        self._frames_text = b""
        self._reader: LoopReader | None = None
        self._sdo_lock: asyncio.Lock | None = None
        #: the outstanding SDO request: (node id, index, sub, future of the answer)
        self._sdo_pending: tuple[int, int, int, asyncio.Future] | None = None
        self._connected = False     # bus open
        self._started = False       # nodes started
        self._closed = False

    async def connect(self) -> None:
        raise NotImplementedError

    async def close(self) -> None:
        raise NotImplementedError

    async def __aenter__(self) -> Self:
        await self.connect()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    # ================================================================== bus
    def _make_bus(self) -> can.BusABC:
        if self._bus_factory is not None:
            return self._bus_factory()
        kw = dict(self.bus_kwargs)
        if self.interface == "socketcand":
            self.host = kw.pop("host", self.host)
            self.port = kw.pop("port", self.port)
            kw.setdefault("tcp_tune", True)
            kw.setdefault("timeout_s", self.connect_timeout_s)
            return SocketcandBus(self.channel, self.host, self.port, **kw)
        if self.interface == "virtual":         # read on the event loop, no thread
            return LoopVirtualBus(channel=self.channel, **kw)
        return can.Bus(interface=self.interface, channel=self.channel, **kw)

    def _bus_description(self) -> str:
        if self._bus_factory is not None:
            return self.factory_description
        if self.interface == "socketcand":
            return f"socketcand {self.host}:{self.port} channel {self.channel}"
        return f"{self.interface} channel {self.channel}"

    def _open_timeout(self, exc: TimeoutError) -> ConnectTimeout:
        """The error for a bus that did not open within ``connect_timeout_s``."""
        return ConnectTimeout(self.name, self._bus_description(), f"bus opening ({exc})",
                              self.connect_timeout_s)

    async def _open_bus(self) -> None:
        """Open the bus (in a thread, bounded) and attach the reader to this event loop."""
        loop = asyncio.get_running_loop()
        self._sdo_lock = asyncio.Lock()
        try:
            # a bus opened after the caller gave up: nobody will use it
            self._bus = await in_thread(self._make_bus, f"{self.name}-open-bus",
                                        orphan=methodcaller("shutdown"))
        except TimeoutError as exc:
            raise self._open_timeout(exc) from None
        except (can.CanError, OSError, ValueError, TypeError, ImportError) as exc:
            raise DeviceFault(self.name, f"cannot open CAN bus {self._bus_description()}: "
                                         f"{exc}") from exc
        self._reader = LoopReader(self._bus, self._on_message, on_error=self._on_link_error,
                                  timeout=_READER_TIMEOUT_S, loop=loop,
                                  name=f"{self.name} can reader")
        self._connected = True

    async def _teardown(self) -> None:
        """Stop the reader, cancel an outstanding SDO request, shut the bus down (in a
        thread: a socketcand connection reads what its server still sends for up to 0.1 s
        before it closes, and the other drivers on this loop keep their cycles meanwhile)."""
        self._started = False
        self._connected = False
        if self._reader is not None:
            self._reader.stop(timeout=1.0)
            self._reader = None
        pending = self._sdo_pending
        if pending is not None and not pending[3].done():
            pending[3].cancel()
        if self._bus is not None:
            bus, self._bus = self._bus, None
            try:
                await in_thread(bus.shutdown, f"{self.name}-close-bus")
            except (can.CanError, OSError) as exc:
                log.warning(f"{self.log_name} bus shutdown failed", device=self.name,
                            error=str(exc))

    def _send(self, can_id: int, data: bytes) -> None:
        bus = self._bus
        if bus is None:
            raise DeviceFault(self.name, "not connected")
        try:
            bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
        except (can.CanError, OSError) as exc:
            raise self._send_failed(exc, [can_id]) from exc

    def _send_failed(self, exc: Exception, can_ids: Sequence[int]) -> DeviceFault:
        """Count and log a failed send; the fault to raise."""
        self.send_errors += 1
        ids = ", ".join(f"0x{c:03X}" for c in can_ids)
        if self.send_errors <= _LOG_FIRST or self.send_errors % _LOG_EVERY == 0:
            log.warning(f"{self.log_name} send failed", device=self.name, cob_id=ids,
                        error=str(exc), count=self.send_errors)
        return DeviceFault(self.name, f"CAN send of COB-ID {ids} failed: {exc}")

    def _send_frames(self, frames: tuple[tuple[int, bytes], ...]) -> None:
        """Send standard frames ``(COB-ID, data)`` in order, as one TCP write on a socketcand
        bus (one system call and one wake-up of the server, not one per frame). The text of
        the last tuple sent is kept: a cycle whose frames did not change costs one write."""
        bus = self._bus
        if not isinstance(bus, SocketcandBus):
            for can_id, data in frames:
                self._send(can_id, data)
            return
        if frames is not self._frames_sent:
            self._frames_text = bus.send_text_of(frames)
            self._frames_sent = frames
        try:
            bus.send_text(self._frames_text)
        except (can.CanError, OSError) as exc:
            raise self._send_failed(exc, [c for c, _ in frames]) from exc

    def _send_nmt(self, command: NmtCommand, node_id: int) -> None:
        """An NMT command (CiA 301) to ``node_id`` (0: every node)."""
        self._send(co.COB_BASE["NMT"], co.encode_nmt(command, node_id))

    async def _cyclic(self, tick: Callable[[], Awaitable[None]]) -> None:
        """Await ``tick`` every ``sync_period_s`` (event loop clock), for ever. A tick failing
        with :class:`~dentibot.errors.DeviceFault` is skipped (it was counted and logged
        where it failed); more than a period late, the cycle skips ahead instead of bursting
        and counts the cycles skipped in ``overruns``.

        Paced by a control task (:meth:`cycle_soon` after each of its ticks), a cycle runs
        right after the tick that asks for it, and the schedule follows the ticks; while
        they come, a cycle that nobody asks for waits half a period longer than its time
        before it runs on its own (a tick a little late does not get a cycle of its own and
        one more right after), and when they stop the cycle keeps its own time again."""
        loop = asyncio.get_running_loop()
        period = self.sync_period_s
        next_t = loop.time()
        while True:
            self._cycle_t = loop.time()
            try:
                await tick()
            except DeviceFault:
                pass
            next_t += period
            now = loop.time()
            if now - next_t > period:   # more than a period late: skip, do not burst
                self.overruns += int((now - next_t) / period)
                next_t = now
            paced = now - self._asked_t < 2.0 * period
            if await self._until(next_t + (0.5 * period if paced else 0.0)):
                next_t = loop.time()    # asked for: the ticks set the schedule

    async def _until(self, t: float) -> bool:
        """Wait until the loop's time ``t`` or until :meth:`cycle_soon`; True when asked."""
        loop = asyncio.get_running_loop()
        fut = self._ask = loop.create_future()
        timer = loop.call_at(t, _resolve, fut, False)
        try:
            return await fut
        finally:
            timer.cancel()
            self._ask = None

    def cycle_soon(self) -> None:
        """Run the own cycle now instead of at its time (a control task calls it after each
        tick, once that tick's commands are set: they go out with the SYNC of that tick,
        not up to a period later, and the SYNC keeps the tick's timing, to the microsecond,
        rather than the event loop's timers, rounded to whole milliseconds). Ignored within
        half a period of the last cycle (a tick faster than the cycle) or when the own cycle
        does not run."""
        self._asked_t = now = asyncio.get_running_loop().time()
        ask = self._ask
        if ask is not None and now - self._cycle_t >= 0.5 * self.sync_period_s:
            _resolve(ask, True)

    # ================================================================== reception
    def _on_message(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            if self.count_error_frames:
                self.errors += 1
            return
        if msg.is_remote_frame or msg.is_extended_id:
            return
        handler = self._handlers.get(msg.arbitration_id)
        if handler is None:
            return
        data = bytes(msg.data)
        try:
            handler(data, time.monotonic())
        except ProtocolError as exc:
            self.errors += 1
            if self.errors <= _LOG_FIRST or self.errors % _LOG_EVERY == 0:
                log.warning(f"{self.log_name} bad frame", device=self.name,
                            cob_id=hex(msg.arbitration_id), data=data.hex(), error=str(exc),
                            count=self.errors)

    def _on_link_error(self, exc: Exception) -> None:
        self._link_error = f"{type(exc).__name__}: {exc}"
        log.error(f"{self.log_name} CAN reader failed", device=self.name,
                  error=self._link_error)

    # ================================================================== SDO client
    async def _sdo_transfer(self, node_id: int, index: int, sub: int, request: bytes,
                            verb: str, *, timeout_error: DeviceFault,
                            abort_device: str) -> SdoFrame:
        """Send the SDO ``request`` to ``node_id`` and wait for its answer, one request at a
        time: ``timeout_error`` after ``sdo_timeout_s``, :class:`SdoAbort` (naming
        ``abort_device``) when the node aborts."""
        if not self._connected or self._sdo_lock is None:
            raise DeviceFault(self.name, "not connected")
        async with self._sdo_lock:
            fut = asyncio.get_running_loop().create_future()
            self._sdo_pending = (node_id, index, sub, fut)
            self.sdo_requests += 1
            try:
                self._send(co.cob_id("SDO_RX", node_id), request)
                frame = await asyncio.wait_for(fut, self.sdo_timeout_s)
            except TimeoutError:
                self.sdo_timeouts += 1
                raise timeout_error from None
            finally:
                self._sdo_pending = None
        if frame.kind == "abort":
            self.sdo_aborts += 1
            raise SdoAbort(abort_device, index, sub, frame.abort_code, verb)
        return frame

    def _on_sdo_response(self, node_id: int, data: bytes, unsolicited: str) -> None:
        """Hand an SDO response of ``node_id`` to the outstanding request; one that answers
        nothing is a :class:`~dentibot.errors.ProtocolError` (``unsolicited`` names it:
        ``{index}``/``{sub}``/``{node}`` are filled in)."""
        frame = co.decode_sdo_response(data)
        pending = self._sdo_pending
        if pending is None or (node_id, frame.index, frame.sub) != pending[:3]:
            raise ProtocolError(self.name, unsolicited.format(
                index=f"0x{frame.index:04X}", sub=f"{frame.sub:02X}", node=f"0x{node_id:02X}"))
        if not pending[3].done():
            pending[3].set_result(frame)


__all__ = ["SOCKETCAND_PORT", "CanOpenMaster", "ConfigurationMismatch", "Handler", "SdoAbort",
           "SocketcandBus"]
