"""A CAN bus's frames handed to an asyncio event loop in batches.

A bus with a file descriptor (kernel SocketCAN, a socketcand connection) is watched by the
event loop itself, as python-can's :class:`can.Notifier` does with a loop: when it is
readable, the loop takes every frame already waiting (a batch) and hands them over, in the
thread that handles them. No thread of its own, so no hand-over of the interpreter lock and
no wake-up pipe per batch. Measured on the wire at 500 Hz (EPOS4 through socketcand, one
CPU-bound job beside): a reader thread cost the control process a second wake-up per
batch, the pipe's read and the lock's hand-overs, about a fifth of its work between ticks,
and the control thread waited for the lock whenever the reader held it.

A bus without one (python-can's own ``virtual`` bus, most vendor interfaces) is read in a
thread of its own (:class:`~dentibot.io.virtual_bus.LoopVirtualBus` is the ``virtual`` bus
with a file descriptor). python-can's :class:`can.Notifier` then hands every frame over on its
own: one ``call_soon_threadsafe`` (a write to the loop's wake-up pipe) per frame, and one
hand-over of the interpreter lock between its reader thread and the loop per frame. When the
loop is busy (a 500 Hz control task, the simulators of a whole robot in the same process)
the reader thread gets the lock only at the interpreter's switch interval, a few frames per
millisecond at best, and at a few thousand frames per second its queue grows: measured on a
python-can ``virtual`` bus carrying a second master's 1 kHz set-points, 100 frames queued
and 30-40 ms of latency within 50 ms, longer than a drive's 30 ms heartbeat consumer.
:class:`LoopReader`'s thread takes every frame already waiting once it holds the lock (a
batch) and hands the batch over in one call: the cost per frame no longer includes a thread
switch, and the latency stays one switch interval under load.

Either way frames keep their order; a receive error ends the reader and is handed to
``on_error`` in the loop, once.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable

import can
import structlog

log = structlog.get_logger(__name__)

#: Frames handed over in one call at most (bounds the time one delivery holds the loop).
MAX_BATCH = 512


def bus_fileno(bus: can.BusABC) -> int | None:
    """The file descriptor the event loop can watch for ``bus``'s frames, or None when it
    has none (python-can's ``BusABC.fileno`` raises :class:`NotImplementedError`; some
    interfaces answer -1)."""
    try:
        fd = bus.fileno()
    except (NotImplementedError, OSError, ValueError):
        return None
    return fd if isinstance(fd, int) and fd >= 0 else None


class LoopReader:
    """Reads ``bus`` for ``loop``: on the loop itself when the bus has a file descriptor
    (:func:`bus_fileno`; ``threaded`` False), else in a thread of its own; ``on_frame(msg)``
    runs in ``loop`` for every frame, in order. ``timeout`` (s) bounds how long
    :meth:`stop` waits for the thread. Created in the loop's thread."""

    def __init__(self, bus: can.BusABC, on_frame: Callable[[can.Message], object], *,
                 loop: asyncio.AbstractEventLoop,
                 on_error: Callable[[Exception], object] | None = None,
                 timeout: float = 0.05, name: str | None = None) -> None:
        self.bus = bus
        self.on_frame = on_frame
        self.on_error = on_error
        self.timeout = float(timeout)
        self.loop = loop
        self.frames = 0                  # frames delivered
        self.batches = 0                 # deliveries (frames / batches: frames per hand-over)
        self.exception: Exception | None = None
        self._stopped = False
        self._thread: threading.Thread | None = None
        self._fd = bus_fileno(bus)
        if self._fd is not None:
            loop.add_reader(self._fd, self._on_readable)
            loop.call_soon(self._on_readable)      # what the bus holds already
            return
        self._thread = threading.Thread(
            target=self._run, daemon=True,
            name=name or f"can reader {getattr(bus, 'channel_info', '?')}")
        self._thread.start()

    @property
    def stopped(self) -> bool:
        return self._stopped

    @property
    def threaded(self) -> bool:
        """True when the bus is read in a thread of its own (it has no file descriptor)."""
        return self._thread is not None

    def stop(self, timeout: float = 1.0) -> None:
        """No more deliveries from now on; the thread is joined (at most ``timeout`` s), or
        the loop stops watching the bus."""
        self._stopped = True
        self._unwatch()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    # ------------------------------------------------------------ on the loop
    def _unwatch(self) -> None:
        fd, self._fd = self._fd, None
        if fd is None or self.loop.is_closed():
            return
        try:
            running = asyncio.get_running_loop() is self.loop
        except RuntimeError:
            running = False
        if running:
            self.loop.remove_reader(fd)
        else:                            # (stopped from another thread)
            self.loop.call_soon_threadsafe(self.loop.remove_reader, fd)

    def _on_readable(self) -> None:
        """The bus is readable: the frames waiting, through the bus's ``drain(limit)`` where
        it has one (:class:`~dentibot.io.canopen_master.SocketcandBus`) and no receive
        filters are set, else ``recv(0)`` until none is left."""
        if self._stopped:
            return
        bus = self.bus
        drain = getattr(bus, "drain", None) if bus.filters is None else None
        batch: list[can.Message] = []
        try:
            if drain is not None:               # every frame there is, in one read
                batch = drain(MAX_BATCH)
            else:
                while len(batch) < MAX_BATCH and (msg := bus.recv(0)) is not None:
                    batch.append(msg)
        except Exception as exc:  # noqa: BLE001 - the link is gone: told to the loop
            self.exception = exc
            self._unwatch()
            if batch:
                self._deliver(batch)
            self._error(exc)
            return
        if batch:
            self._deliver(batch)
            if len(batch) == MAX_BATCH:   # more may wait in the bus's own buffer
                self.loop.call_soon(self._on_readable)

    # ------------------------------------------------------------ in a thread
    def _run(self) -> None:
        bus, recv_timeout = self.bus, self.timeout
        while not self._stopped:
            try:
                msg = bus.recv(recv_timeout)
                if msg is None:
                    continue
                batch = [msg]
                while len(batch) < MAX_BATCH and (msg := bus.recv(0)) is not None:
                    batch.append(msg)
            except Exception as exc:  # noqa: BLE001 - the link is gone: told to the loop
                self.exception = exc
                if not self._stopped:
                    self._call(self._error, exc)
                return
            if not self._call(self._deliver, batch):
                return

    def _call(self, fn: Callable, arg: object) -> bool:
        try:
            self.loop.call_soon_threadsafe(fn, arg)
        except RuntimeError:             # the loop is closed: nobody left to tell
            self._stopped = True
            return False
        return True

    # ------------------------------------------------------------ both
    def _deliver(self, batch: list[can.Message]) -> None:
        self.batches += 1
        for msg in batch:
            if self._stopped:
                return
            self.frames += 1
            try:
                self.on_frame(msg)
            except Exception as exc:  # noqa: BLE001 - one bad frame must not drop the rest
                self.loop.call_exception_handler({
                    "message": "CAN frame handler failed", "exception": exc, "frame": msg})

    def _error(self, exc: Exception) -> None:
        if self._stopped:
            return
        if self.on_error is None:
            log.error("can reader stopped", bus=getattr(self.bus, "channel_info", "?"),
                      error=str(exc))
        else:
            self.on_error(exc)
