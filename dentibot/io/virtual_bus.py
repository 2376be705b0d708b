"""python-can's ``virtual`` bus with a file descriptor, read by the event loop itself.

python-can's :class:`~can.interfaces.virtual.VirtualBus` connects the buses of one process
opened on the same channel: ``send`` puts a copy of the frame in every other bus's queue.
It has no file descriptor, so :class:`~dentibot.io.can_reader.LoopReader` reads each such
bus in a thread of its own, and every frame wakes that thread and hands the interpreter lock
to it and back. The wire simulators (``dentibot sim serve``) keep three buses on one channel
(the EPOS4 node, the socketcand endpoint, the patient tracker): measured at 500 Hz, the
node's ``send`` spent most of its time waiting for the lock its readers had just taken, and
the reader threads and those hand-overs were well over half of the simulators' process.

:class:`LoopVirtualBus` is the same bus on the same channels (it talks to plain ``virtual``
buses of the process both ways, frames keep their order), whose queue also raises a
counter the event loop can watch (an ``eventfd``; a pipe where there is none): the loop
takes every frame waiting when it is readable (:meth:`LoopVirtualBus.drain`), with no
thread. A frame put in the empty queue raises the counter; the reader clears it only after
it found the queue empty, then looks once more: a frame put meanwhile is taken then or has
raised the counter again, so none is left behind unsignalled.
"""

from __future__ import annotations

import os
import queue
import time

import can
from can.interfaces.virtual import VirtualBus, channels_lock


class _Doorbell:
    """A file descriptor that is readable once :meth:`ring` was called, until :meth:`clear`
    (Linux ``eventfd``; a non-blocking pipe elsewhere). Safe from any thread."""

    def __init__(self) -> None:
        if hasattr(os, "eventfd"):
            self.fd = self._wfd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
            self._ring = (1).to_bytes(8, "little")
        else:                                       # pragma: no cover - not Linux
            self.fd, self._wfd = os.pipe()
            os.set_blocking(self.fd, False)
            os.set_blocking(self._wfd, False)
            self._ring = b"\x01"

    def ring(self) -> None:
        try:
            os.write(self._wfd, self._ring)
        except BlockingIOError:                     # already readable (a full pipe)
            pass

    def clear(self) -> None:
        try:
            while os.read(self.fd, 4096):
                if self.fd == self._wfd:            # an eventfd resets in one read
                    return
        except BlockingIOError:
            pass

    def close(self) -> None:
        for fd in {self.fd, self._wfd}:
            os.close(fd)


class _RingingQueue(queue.Queue):
    """A frame queue that rings its doorbell when a frame arrives in it empty (under the
    queue's lock: one system call per batch, not per frame)."""

    def __init__(self, bell: _Doorbell, maxsize: int) -> None:
        super().__init__(maxsize)
        self.bell = bell

    def _put(self, item) -> None:
        if not self.queue:
            self.bell.ring()
        self.queue.append(item)


class LoopVirtualBus(VirtualBus):
    """python-can's ``virtual`` bus (same arguments) with :meth:`fileno` and :meth:`drain`:
    a :class:`~dentibot.io.can_reader.LoopReader` reads it on the event loop."""

    def __init__(self, channel: can.typechecking.Channel = None, **kwargs) -> None:
        super().__init__(channel=channel, **kwargs)
        self._bell = _Doorbell()
        ringing = _RingingQueue(self._bell, self.queue.maxsize)
        with channels_lock:
            # the queue the base class listed for this bus, by identity (Queue has no __eq__)
            i = next(i for i, q in enumerate(self.channel) if q is self.queue)
            self.channel[i] = self.queue = ringing

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """As python-can's: a copy of ``msg`` in every other queue of the channel, each its
        own data, stamped now (``preserve_timestamps``: the frame's own), ``is_rx`` set; the
        copy is built directly (``deepcopy``'s generic walk was a third of a frame's way
        from the socketcand endpoint to the node)."""
        self._check_if_open()
        stamp = msg.timestamp if self.preserve_timestamps else time.time()
        own = self.queue
        failed = False
        for q in self.channel:
            if q is own and not self.receive_own_messages:
                continue
            copy = can.Message(
                timestamp=stamp, arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                is_error_frame=msg.is_error_frame, channel=self.channel_id, dlc=msg.dlc,
                data=bytearray(msg.data), is_fd=msg.is_fd, is_rx=q is not own,
                bitrate_switch=msg.bitrate_switch,
                error_state_indicator=msg.error_state_indicator)
            try:
                q.put(copy, block=True, timeout=timeout)
            except queue.Full:
                failed = True
        if failed:
            raise can.CanOperationError("Could not send message to one or more recipients")

    def fileno(self) -> int:
        return self._bell.fd

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if timeout is not None and timeout <= 0:
            self._check_if_open()
            return self._take(), False
        return super()._recv_internal(timeout)

    def _take(self) -> can.Message | None:
        """The next frame waiting, or None; clears the doorbell when there is none (and
        looks once more, for a frame put meanwhile)."""
        q = self.queue
        try:
            return q.get_nowait()
        except queue.Empty:
            pass
        self._bell.clear()
        try:
            return q.get_nowait()
        except queue.Empty:
            return None

    def drain(self, limit: int) -> list[can.Message]:
        """Every frame waiting, at most ``limit``, in order (what the event loop takes when
        the bus is readable)."""
        self._check_if_open()
        out: list[can.Message] = []
        while len(out) < limit and (msg := self._take()) is not None:
            out.append(msg)
        return out

    def shutdown(self) -> None:
        was_open = self._open
        super().shutdown()
        if was_open:
            self._bell.close()
