"""The recorder process's journal: a ring of the messages the control process hands over, in a
file beside the recording, mapped into both processes.

Why. Handing the rows over through a pipe made each block a system call and, whenever the
recorder's process slept, a wake-up on the other core, and it held the recording to a budget
of 50 ticks at risk (what a crash could lose), so that the recorder wrote its file in 25-tick
steps: in lock-step time the control task waited for it every 25 ticks. Here the control
process copies each message into shared memory and goes on; the recorder's process reads
them when it wakes (every few milliseconds) and writes the file in large steps. Because the
ring lives in a file (``run.mcap.journal``), what the recording file does not hold yet is not
at risk: it is in the journal, which outlives a crash of either process (the operating
system keeps what a killed process wrote to a shared file mapping). ``dentibot recover``
adds it to the recording (:mod:`~dentibot.telemetry.recover`); the recorder's process adds it
itself when only the control process died; a recording closed normally deletes its journal.

Layout. A header of :data:`HEADER_BYTES` bytes, int64 cells (little-endian): :data:`MAGIC`,
the ring's capacity in bytes, ``HEAD`` (bytes ever written to the ring, published by the
writer after the bytes themselves), ``TAIL`` (bytes ever released: every message before it
is in the recording file, published by the recorder after each flush), ``SETTLED`` (ticks in
the file, the recorder's count), ``WAITING`` (set by a writer waiting for room: the recorder
tells it when it makes some) and the recorder's counters
(:data:`~dentibot.telemetry.recorder_process.CHILD_COUNTERS`, in :data:`COUNTERS` cells).
Then the ring: messages one after the other, each its length (4 bytes, big-endian, as
multiprocessing frames the same messages on a pipe) and its bytes, wrapping at the end.
A message is a packed :class:`~dentibot.telemetry.blocks.TickBlock` (its wire form) or a
pickled list of ``(kind, payload)`` items (``tick`` rows, ``event`` and ``end``).

Order. One writer, one reader. The writer stores a message's bytes, then ``HEAD``; the reader
loads ``HEAD``, then the bytes. x86-64 keeps stores in order and loads in order (its memory
model), and the compiled writer (:mod:`~dentibot.telemetry.wire_kernels`) calls into the C
library between the two, which the compiler may not reorder stores across.
"""

from __future__ import annotations

import io
import mmap
import os
import pickle
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from dentibot.telemetry.blocks import WIRE_TAG, TickBlock
from dentibot.telemetry.schema import TelemetryError

__all__ = ["COUNTERS", "HEAD", "HEADER_BYTES", "HEADER_CELLS", "LENGTH_BYTES", "SETTLED", "TAIL",
           "WAITING", "Journal", "items_of", "journal_path", "read_journal"]

#: the header's first cell: b"DBJRNL01", little-endian
MAGIC = int.from_bytes(b"DBJRNL01", "little")
#: the header's cells: magic, capacity, head, tail, settled, waiting (the writer waits for
#: room and asks to be told), then the recorder's counters
(_MAGIC, CAPACITY, HEAD, TAIL, SETTLED, WAITING) = range(6)
COUNTERS = 6
HEADER_BYTES = 256
HEADER_CELLS = HEADER_BYTES // 8
LENGTH_BYTES = 4
_LENGTH_MAX = 2**31 - 1
SUFFIX = ".journal"


def journal_path(recording: str | os.PathLike[str]) -> Path:
    """The journal of the recording at ``recording``: ``run.mcap`` -> ``run.mcap.journal``."""
    p = Path(recording)
    return p.with_name(p.name + SUFFIX)


class Journal:
    """The journal file mapped into this process: :meth:`create` (the control process) or
    :meth:`open` (the recorder's process). ``hdr``: the header's cells (int64), ``ring``: the
    ring's bytes (uint8), both views of the mapping."""

    def __init__(self, path: Path, fd: int, capacity: int) -> None:
        self.path = path
        self.capacity = capacity
        try:
            self._map = mmap.mmap(fd, HEADER_BYTES + capacity, mmap.MAP_SHARED,
                                  mmap.PROT_READ | mmap.PROT_WRITE)
        finally:
            os.close(fd)
        self.hdr = np.frombuffer(self._map, dtype="<i8", count=HEADER_CELLS)
        self.ring = np.frombuffer(self._map, dtype=np.uint8, count=capacity,
                                  offset=HEADER_BYTES)

    @classmethod
    def create(cls, path: str | os.PathLike[str], capacity: int) -> Journal:
        """A new, empty journal of ``capacity`` bytes at ``path`` (one left by an earlier
        recording of the same name is replaced: that recording is being replaced too)."""
        path = Path(path)
        if capacity < 64 or capacity > _LENGTH_MAX:
            raise TelemetryError(path, f"journal capacity {capacity} bytes outside 64..."
                                 f"{_LENGTH_MAX}")
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                os.ftruncate(fd, HEADER_BYTES + capacity)
                os.posix_fallocate(fd, 0, HEADER_BYTES + capacity)
                os.pwrite(fd, np.array([MAGIC, capacity], dtype="<i8").tobytes(), 0)
            except OSError:
                os.close(fd)
                raise
            os.replace(tmp, path)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise TelemetryError(path, f"cannot create the journal: {exc}") from exc
        j = cls(path, fd, capacity)
        j.ring[::mmap.PAGESIZE] = 0               # each page's first write, now, not mid-run
        return j

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> Journal:
        """The journal at ``path``, as :meth:`create` made it."""
        path = Path(path)
        fd = os.open(path, os.O_RDWR)
        try:
            head = np.frombuffer(os.pread(fd, 16, 0), dtype="<i8")
        except OSError:
            os.close(fd)
            raise
        if len(head) < 2 or head[0] != MAGIC:
            os.close(fd)
            raise TelemetryError(path, "not a DentiBot journal")
        return cls(path, fd, int(head[1]))

    # -- the writer (the control process) -------------------------------------------------

    def room(self) -> int:
        """Bytes the ring can take now."""
        hdr = self.hdr
        return self.capacity - int(hdr[HEAD] - hdr[TAIL])

    def put(self, data: bytes | bytearray | memoryview) -> None:
        """One message into the ring, then published. The caller made sure there is room
        (:meth:`room` >= ``len(data) + 4``)."""
        head = int(self.hdr[HEAD])
        self._copy_in(head, len(data).to_bytes(LENGTH_BYTES, "big"))
        self._copy_in(head + LENGTH_BYTES, data)
        self.hdr[HEAD] = head + LENGTH_BYTES + len(data)

    def _copy_in(self, at: int, data: bytes | bytearray | memoryview) -> None:
        cap, n = self.capacity, len(data)
        start = at % cap
        first = min(n, cap - start)
        mv = memoryview(self._map)
        mv[HEADER_BYTES + start:HEADER_BYTES + start + first] = memoryview(data)[:first]
        if first < n:
            mv[HEADER_BYTES:HEADER_BYTES + n - first] = memoryview(data)[first:]

    # -- the reader (the recorder's process) ----------------------------------------------

    def messages(self, start: int) -> Iterator[tuple[int, bytes]]:
        """The messages from byte ``start`` (a message's start) up to the published head, each
        as (the byte after it, its bytes)."""
        head = int(self.hdr[HEAD])
        return _messages(self._copy_out, start, head)

    def _copy_out(self, at: int, n: int) -> bytes:
        return _ring_bytes(self._map, self.capacity, at, n)

    def release(self, tail: int, settled: int, counters: list[int]) -> None:
        """Every message before byte ``tail`` is in the recording (``settled`` ticks, the
        recorder's counters): the writer may reuse their bytes."""
        hdr = self.hdr
        hdr[COUNTERS:COUNTERS + len(counters)] = counters
        hdr[SETTLED] = settled
        hdr[TAIL] = tail

    # -- both --------------------------------------------------------------------------------

    def close(self) -> None:
        """Unmap (the file stays)."""
        self.hdr = self.ring = None            # views first: mmap refuses to close under them
        try:
            self._map.close()
        except BufferError:                    # a view still held elsewhere: unmapped at exit
            pass

    def unlink(self) -> None:
        """Delete the file (every message is in the recording)."""
        self.path.unlink(missing_ok=True)


def _ring_bytes(buf: Any, cap: int, at: int, n: int) -> bytes:
    """``n`` bytes of the ring in ``buf`` (the journal's bytes, header first, mapped or read)
    from byte ``at`` of the stream, wrapping at the ring's end (``cap``)."""
    start = at % cap
    first = min(n, cap - start)
    out = buf[HEADER_BYTES + start:HEADER_BYTES + start + first]
    if first < n:
        out += buf[HEADER_BYTES:HEADER_BYTES + n - first]
    return out


def _messages(copy_out, start: int, head: int) -> Iterator[tuple[int, bytes]]:
    at = start
    while head - at >= LENGTH_BYTES:
        n = int.from_bytes(copy_out(at, LENGTH_BYTES), "big")
        end = at + LENGTH_BYTES + n
        if end > head:
            raise TelemetryError("<journal>", f"a message of {n} bytes at byte {at} runs past "
                                 f"the head ({head})")
        yield end, copy_out(at + LENGTH_BYTES, n)
        at = end


def read_journal(path: str | os.PathLike[str]) -> tuple[dict[str, int], list[bytes]]:
    """What a journal left by a crash holds: its header's cells (``tail``, ``head``,
    ``settled``) and the messages between tail and head (those the recording may lack), read
    from the file (not mapped: the reader may not write it)."""
    path = Path(path)
    data = path.read_bytes()
    cells = np.frombuffer(data[:HEADER_BYTES], dtype="<i8") if len(data) >= HEADER_BYTES \
        else np.zeros(0, dtype="<i8")
    if len(cells) < COUNTERS or cells[_MAGIC] != MAGIC:
        raise TelemetryError(path, "not a DentiBot journal")
    cap, head, tail, settled = (int(cells[i]) for i in (CAPACITY, HEAD, TAIL, SETTLED))
    if len(data) < HEADER_BYTES + cap or not 0 <= head - tail <= cap:
        raise TelemetryError(path, f"a damaged journal (capacity {cap}, head {head}, tail "
                             f"{tail}, {len(data)} bytes)")
    return ({"tail": tail, "head": head, "settled": settled},
            [m for _, m in _messages(lambda at, n: _ring_bytes(data, cap, at, n), tail, head)])


class _Unpickler(pickle.Unpickler):
    """Pickles of rows and events only: builtin values and numpy's scalars and arrays; any
    other class is refused (a journal is a file: loading it must not run code)."""

    _ALLOWED = frozenset({("numpy", "dtype"), ("numpy.core.multiarray", "scalar"),
                          ("numpy._core.multiarray", "scalar"),
                          ("numpy.core.multiarray", "_reconstruct"),
                          ("numpy._core.multiarray", "_reconstruct"), ("numpy", "ndarray"),
                          ("builtins", "float"), ("builtins", "int"), ("builtins", "complex")})

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self._ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"{module}.{name} is not a row's value")


def items_of(message: bytes) -> list[tuple[str, Any]]:
    """A journal message as the ``(kind, payload)`` items it carries: ``("block",
    TickBlock)`` for a packed block, else the pickled list."""
    if message[:1] == WIRE_TAG:
        return [("block", TickBlock.unpack(message))]
    return _Unpickler(io.BytesIO(message)).load()
