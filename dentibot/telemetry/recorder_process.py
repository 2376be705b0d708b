"""The MCAP recorder in a process of its own: the control task hands rows over and goes on.

Why. :class:`~dentibot.telemetry.recorder.McapRecorder`'s writer spends 20-30 us of CPU per
tick (JSON, the ``/tf`` view, the mcap library's records, compression), all of it holding the
interpreter lock the control task needs. :class:`RecorderProcess` runs that same recorder in a
child process, on another core and under another interpreter lock, writing in the child's
one thread. The control task pays for pickling its rows in batches (about 3 us a row), or a
block of rows in its wire form (:meth:`RecorderProcess.record_block`,
:meth:`~dentibot.telemetry.blocks.TickBlock.packed`: a header and the columns' bytes, about
1 us where a pickle of the block took 20-50), and one pipe write per batch.

Same guarantees as :class:`~dentibot.telemetry.recorder.McapRecorder`, with the same
parameters:

- the budget is kept in ticks and covers everything a crash could lose: rows still in this
  process's batch, in the pipe, queued in the child, in its unfinished chunk. The child reports
  each flush; ``record()`` waits for one when ``budget`` ticks are at risk, at most
  ``max_wait_s``, then drops the row and raises
  :class:`~dentibot.telemetry.recorder.TelemetryOverflow`;
- a batch leaves this process after ``send_ticks`` rows (a fifth of the budget, at most 10) or
  half of ``flush_interval_s`` after its first row, whichever is first; events ride along;
- if the child's writer dies, the next ``record()``, ``event()`` or ``close()`` raises
  :class:`~dentibot.telemetry.schema.TelemetryError` with the cause;
- errors of the arguments (file exists, bad compression...) are raised by the constructor,
  as the in-process recorder raises them (the child builds the recorder and sends them back).

What the child does on its own. It ignores SIGINT (Ctrl-C belongs to the control process,
which stops the procedure safely and then closes the recording). If the control process dies
(``kill -9``, a crash), the child sees its pipe close, writes out every row it received and
closes the file without ``/run/end`` or summary: readers flag the recording incomplete, and
it has lost only the rows that had not left the dead process (at most ``send_ticks``).

The child is started by multiprocessing's fork server (``forkserver``; ``spawn`` where there is
none): it inherits no sockets or files of the control process, so a device connection closed
there is closed. The first recorder of a process starts the server (about 0.2 s, the imports of
this module); later ones fork from it in a few milliseconds.

:func:`open_recorder` chooses: a file path and picklable options get a
:class:`RecorderProcess`, a stream (or a view with an unpicklable ``frames`` callable) stays in
this process with a :class:`~dentibot.telemetry.recorder.McapRecorder`.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import pickle
import select
import signal
import struct
import sys
import threading
import time
import types
import weakref
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from dentibot.errors import ConfigError
from dentibot.logs import configure_default, configure_logging, logging_settings
from dentibot.telemetry import wire_kernels as wk
from dentibot.telemetry.blocks import WIRE_K0_AT, WIRE_N_AT, WIRE_TAG, TickBlock
from dentibot.telemetry.recorder import McapRecorder, RecorderBase, TelemetryOverflow
from dentibot.telemetry.schema import END_STATUSES, TelemetryError

__all__ = ["Recorder", "RecorderProcess", "Wire", "open_recorder"]

log = structlog.get_logger("dentibot.telemetry")

#: counters kept by the child's recorder, reported with each flush (McapRecorder's names)
CHILD_COUNTERS = ("ticks_written", "events_written", "rows_rejected", "rows_invalid",
                  "nonfinite_rows", "flushes", "rows_flushed", "bytes_flushed",
                  "transforms_written", "scenes_written", "view_errors")
#: A flush's report, the child's most frequent message, packed rather than pickled (a
#: pickled tuple with the counters' dict cost 20-30 us a flush at each end): this tag, the
#: ticks settled, then CHILD_COUNTERS in order (int64). Other reports are pickles.
_FLUSHED = wk.FLUSHED_TAG
_FLUSHED_BODY = struct.Struct(f"<{1 + len(CHILD_COUNTERS)}q")
START_TIMEOUT_S = 30.0       # the fork server's first start imports this module
CLOSE_TIMEOUT_S = 120.0      # the child writes out at most a budget of rows, then the summary
_PRELOAD = ["dentibot.telemetry.recorder_process"]
_PICKLE = pickle.HIGHEST_PROTOCOL


def _context() -> multiprocessing.context.BaseContext:
    """The fork server where the platform has one (no inherited sockets, fast), else spawn."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(_PRELOAD)
        return ctx
    return multiprocessing.get_context("spawn")


def _start_without_main(proc: multiprocessing.process.BaseProcess) -> None:
    """Start ``proc`` without making the child import the parent's ``__main__``: by default
    multiprocessing re-runs the parent's main script in every child (the whole CLI, a
    benchmark...), seconds of imports the recorder does not need. Its target lives in this
    module, which the fork server has imported already. The helper processes multiprocessing
    starts the first time are given the real standard error: a terminal UI (textual) replaces
    ``sys.stderr`` with an object that has no file descriptor, which they refuse."""
    main, err = sys.modules["__main__"], sys.stderr
    sys.modules["__main__"] = types.ModuleType("__main__")
    if _fileno(err) < 0 and sys.__stderr__ is not None:
        sys.stderr = sys.__stderr__
    try:
        proc.start()
    finally:
        sys.modules["__main__"], sys.stderr = main, err


def _fileno(stream: Any) -> int:
    try:
        return stream.fileno()
    except (AttributeError, OSError, ValueError):
        return -1


def open_recorder(path: str | os.PathLike[str] | Any, metadata: dict[str, Any] | None = None,
                  **options: Any) -> McapRecorder | RecorderProcess:
    """The recorder for ``path``: a :class:`RecorderProcess` for a file path whose options can
    cross to another process, else an in-process
    :class:`~dentibot.telemetry.recorder.McapRecorder` (same arguments, same guarantees)."""
    if hasattr(path, "write"):
        return McapRecorder(path, metadata, **options)
    if not _pickles((metadata, options)):       # e.g. a view's frames given as a lambda
        return McapRecorder(path, metadata, **options)
    try:
        return RecorderProcess(path, metadata, **options)
    except _StartError as exc:                   # no process to be had: record here
        log.warning("telemetry.in_process", path=str(path), reason=str(exc))
        return McapRecorder(path, metadata, **options)


class _StartError(TelemetryError):
    """The recorder process could not be started (no fork server, no file descriptors...)."""


_Child = tuple[multiprocessing.process.BaseProcess, Connection, Connection]
_spare: _Child | None = None


def _spawn() -> _Child:
    """A recorder process waiting for its file: (process, rows pipe, acks pipe)."""
    ctx = _context()
    rows_r, rows_w = ctx.Pipe(duplex=False)
    acks_r, acks_w = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child_main, name="mcap-writer", args=(rows_r, acks_w),
                       daemon=True)
    try:
        _start_without_main(proc)
    except (OSError, ValueError) as exc:
        for conn in (rows_r, rows_w, acks_r, acks_w):
            conn.close()
        raise _StartError("<recorder process>", f"cannot start it: {exc}") from exc
    rows_r.close()
    acks_w.close()
    return proc, rows_w, acks_r


def prestart_recorder_process() -> None:
    """Start the next recorder's process now. A caller about to begin real-time work (a drive
    whose heartbeat consumer expects a message every 30 ms) calls this first: the first
    recorder process of a program starts multiprocessing's fork server (about 0.2 s), which
    must not happen while the control task is due. The next :class:`RecorderProcess` takes
    this process and only waits for its file to be created (milliseconds). Never raises: a
    recorder that cannot have a process records in this one (:func:`open_recorder`)."""
    global _spare
    if _spare is not None and _spare[0].is_alive():
        return
    try:
        _spare = _spawn()
    except _StartError as exc:
        log.warning("telemetry.no_recorder_process", reason=str(exc))


def _take_spare() -> _Child | None:
    global _spare
    spare, _spare = _spare, None
    if spare is not None and not spare[0].is_alive():
        _release(spare[1], spare[2])
        return None
    return spare


class RecorderProcess(RecorderBase):
    """:class:`~dentibot.telemetry.recorder.McapRecorder` run in a child process (see the
    module docstring). Same constructor arguments (a file path only), same methods
    (``record``, ``event``, ``close``, ``duration_s``, context manager) and counters; the
    counters the writer keeps are those of the child's last reported flush, final after
    :meth:`close`.
    """

    WRITER = "the recorder process"

    def __init__(self, path: str | os.PathLike[str], metadata: dict[str, Any] | None = None,
                 **options: Any) -> None:
        if hasattr(path, "write"):
            raise ConfigError("telemetry.path", path, "a file path (a stream is written in "
                              "this process: use McapRecorder)")
        self.path = Path(path)
        max_wait_s = options.get("max_wait_s", 1.0)
        flush_interval_s = options.get("flush_interval_s", 0.05)
        self._proc, rows_w, acks_r = _take_spare() or _spawn()
        self._rows: Connection = rows_w
        self._acks: Connection = acks_r
        # one poll object for the acks (Connection.poll builds a selector each call: 15 us)
        self._acks_poll = select.poll()
        self._acks_poll.register(acks_r.fileno(), select.POLLIN)
        # dropped without close(): the pipes close, the child writes out what it has
        self._release = weakref.finalize(self, _release, rows_w, acks_r)
        rows_w.send((str(path), metadata, options, logging_settings()))
        ready = self._first_message()
        if ready[0] == "error":
            self._release()
            self._proc.join()
            raise ready[1]
        _, self.metadata, self.budget, self.period_s = ready
        self.start_wall_ns: int = self.metadata["start_wall_ns"]
        self.max_wait_s = float(max_wait_s)
        self.send_ticks = max(1, min(10, self.budget // 5))
        self._send_after_s = flush_interval_s / 2

        self.rows_queued = 0
        self.events_queued = 0
        self.rows_dropped = 0
        self.queue_depth_max = 0
        self.at_risk_max = 0
        self.backpressure_waits = 0
        self._counters = dict.fromkeys(CHILD_COUNTERS, 0)
        self._settled = 0                        # ticks the child has flushed (or rejected)
        self._pending: list[tuple[str, Any]] = []
        self._pending_since = 0.0
        self._last_t = 0.0
        self._dead: TelemetryError | None = None
        self._dead_reported = False
        self._closed = False
        self.end: dict[str, Any] | None = None

    def _first_message(self) -> tuple:
        if not self._acks.poll(START_TIMEOUT_S):
            self._proc.kill()
            self._proc.join()
            raise TelemetryError(self.path, f"the recorder process did not start within "
                                 f"{START_TIMEOUT_S:g} s")
        try:
            while True:
                msg = _ack(self._acks.recv_bytes())
                if msg[0] != "flushed":           # the constructor's first flush (/run)
                    return msg
        except EOFError:
            self._proc.join()
            raise TelemetryError(self.path, f"the recorder process died at start (exit code "
                                 f"{self._proc.exitcode})") from None

    # -- caller side (the control task) ----------------------------------------------------

    def record(self, row: dict[str, Any]) -> None:
        """Hand one tick row over. Returns at once unless ``budget`` ticks are at risk; then
        waits for the child's next flush, at most ``max_wait_s`` (then the row is dropped and
        TelemetryOverflow raised). The row must not be changed afterwards."""
        if self._dead is not None or self._closed:
            self._raise_dead()
        if self.rows_queued - self._settled >= self.budget:
            self._wait_for_room(row)
        pending = self._pending
        if not pending:
            self._pending_since = time.monotonic()
        pending.append(("tick", row))
        self.rows_queued += 1
        at_risk = self.rows_queued - self._settled
        if at_risk > self.at_risk_max:
            self.at_risk_max = at_risk
        if len(pending) > self.queue_depth_max:
            self.queue_depth_max = len(pending)
        t = row.get("t")
        if isinstance(t, (int, float)):
            self._last_t = t
        if len(pending) >= self.send_ticks or \
                time.monotonic() - self._pending_since >= self._send_after_s:
            self._send()

    def record_block(self, block: TickBlock) -> None:
        """Hand a block of tick rows over (:class:`~dentibot.telemetry.blocks.TickBlock`, in
        its wire form, after anything still in the batch): the same as :meth:`record` of
        each of its rows, with one wait for room for all of them (a block larger than the
        budget goes in parts)."""
        if self._dead is not None or self._closed:
            self._raise_dead()
        if self._in_parts_or_empty(block):
            return
        n = len(block)
        if self._pending:                         # what came before it, first
            self._send()
        self.rows_queued += n
        self.at_risk_max = max(self.at_risk_max, self.rows_queued - self._settled)
        self.queue_depth_max = max(self.queue_depth_max, n)
        self._last_t = (block.k0 + n - 1) * block.ts
        self._write(b"".join(block.packed()))     # its wire form: no pickle

    def event(self, kind: str, detail: str = "", *, t: float | None = None,
              tick: int | None = None) -> None:
        """Hand an ``/events`` message over (with the next batch); ``t``/``tick`` default to
        the last recorded row's. Never waits."""
        if self._dead is not None or self._closed:
            self._raise_dead()
        if not self._pending:
            self._pending_since = time.monotonic()
        self._pending.append(("event", (kind, detail, t, tick)))
        self.events_queued += 1

    def _send(self, raise_dead: bool = True) -> None:
        items, self._pending = self._pending, []
        try:
            data = pickle.dumps(items, _PICKLE)
        except (pickle.PicklingError, TypeError, AttributeError):
            data = pickle.dumps([it for it in items if _picklable(it, self.path)], _PICKLE)
        self._write(data, raise_dead)

    def _write(self, data: bytes, raise_dead: bool = True) -> None:
        """One message to the child (a pickled list of items, or a packed block); then
        read what it reported."""
        try:
            self._rows.send_bytes(data)
        except OSError as exc:                    # the child is gone
            self._gone(str(exc))
            if raise_dead:
                self._raise_dead()
            return
        self._read_acks()

    def _gone(self, why: str) -> None:
        """Writing to the child failed (``why``): what it reported last is read, and the
        recorder is dead, with the child's own report if it sent one."""
        self._read_acks()
        if self._dead is None:
            self._dead = TelemetryError(self.path, f"the recorder process is gone (exit code "
                                        f"{self._proc.exitcode}): {why}")

    def _read_acks(self, timeout: float = 0.0) -> bool:
        """Read what the child reported; wait up to ``timeout`` for the first message.
        True if anything was read."""
        acks, ready = self._acks, self._acks_poll.poll
        got = False
        try:
            while ready(max(timeout, 0.0) * 1000.0):
                self._on_ack(_ack(acks.recv_bytes()))
                got = True
                timeout = 0.0
        except (EOFError, OSError):
            if self._dead is None and not (self._closed and self.end is not None):
                self._dead = TelemetryError(self.path, f"the recorder process died (exit code "
                                            f"{self._proc.exitcode}); rows since its last "
                                            f"flush ({self._counters['rows_flushed']} ticks on "
                                            f"disk) are lost")
        return got

    def _on_ack(self, msg: tuple) -> None:
        kind = msg[0]
        if kind == "flushed":
            self._settled, counters = msg[1], msg[2]
            self._counters.update(counters)
        elif kind == "dead":
            self._dead = msg[1]
            self._counters.update(msg[2])
        elif kind == "closed":
            self.end = msg[1]
            self._counters.update(msg[2])
            if msg[3] is not None and self._dead is None:
                self._dead = msg[3]

    def _wait_for_room(self, row: Any, n: int = 1) -> None:
        """Wait until ``n`` more ticks fit in the budget."""
        self.backpressure_waits += 1
        if self._pending:
            self._send()
        deadline = time.monotonic() + self.max_wait_s
        while self.rows_queued - self._settled + n > self.budget and self._dead is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._overflow(row, n)
            self._read_acks(remaining)
        if self._dead is not None:
            self._raise_dead()

    def _raise_dead(self) -> None:
        if self._dead is not None:
            self._dead_reported = True
            raise self._dead
        raise TelemetryError(self.path, "recorder is closed")

    def __getattr__(self, name: str) -> Any:
        if name in CHILD_COUNTERS:
            self._read_acks()
            return self._counters[name]
        raise AttributeError(name)

    @property
    def at_risk(self) -> int:
        """Ticks handed over and not yet flushed to the OS: what a crash now could lose."""
        self._read_acks()
        return max(self.rows_queued - self._settled, 0)

    @property
    def error(self) -> BaseException | None:
        self._read_acks()
        return self._dead

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def pid(self) -> int | None:
        """The recorder process's id."""
        return self._proc.pid

    def close(self, status: str = "ok", reason: str = "",
              duration_s: float | None = None) -> dict[str, Any] | None:
        """Write ``/run/end``, finish the file, wait for the child to exit. Idempotent.
        Raises TelemetryError if the writer died and that was not reported yet."""
        if self._closed:
            return self.end
        if status not in END_STATUSES:
            raise ConfigError("run.status", status, f"one of {list(END_STATUSES)}")
        self._closed = True
        self._pending.append(("end", (status, reason,
                                      self.duration_s() if duration_s is None else duration_s)))
        self._send(raise_dead=False)              # a dead writer is reported below, once
        deadline = time.monotonic() + CLOSE_TIMEOUT_S
        while self.end is None and self._proc.is_alive() and time.monotonic() < deadline:
            self._read_acks(0.1)
        self._read_acks()
        self._proc.join(max(0.0, deadline - time.monotonic()))
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join()
            self._dead = self._dead or TelemetryError(
                self.path, f"the recorder process did not finish within {CLOSE_TIMEOUT_S:g} s")
        self._release()
        if self.end is None and self._dead is None:
            self._dead = TelemetryError(self.path, f"the recorder process ended without "
                                        f"finishing the file (exit code {self._proc.exitcode})")
        if self._dead is not None and not self._dead_reported:
            self._raise_dead()
        return self.end


#: what :func:`open_recorder` returns
Recorder = McapRecorder | RecorderProcess


class Wire:
    """A :class:`RecorderProcess`'s pipe for compiled code
    (:func:`~dentibot.telemetry.wire_kernels.send_block`): the blocks of a compiled call's
    ticks go to the recorder's process from the call itself, as
    :meth:`RecorderProcess.record_block` hands them over (the same bytes, the same budget of
    ticks at risk, its flush reports read), while the call runs without the interpreter
    lock. :meth:`begin` before the call gives the kernel's arguments; :meth:`end` after it
    brings the recorder up to date."""

    def __init__(self, rec: RecorderProcess, width: int, max_ticks: int) -> None:
        self.rec = rec
        self.width = int(width)
        self.st = np.zeros(wk.ST_SIZE, dtype=np.int64)
        report = 1 + _FLUSHED_BODY.size
        self.flush = np.zeros(report, dtype=np.uint8)
        self.incoming = np.zeros(4 + report, dtype=np.uint8)
        self._max_ticks = int(max_ticks)
        self.msg = np.zeros(0, dtype=np.uint8)
        self._head: tuple | None = None

    def begin(self, step: str, state: str, ts: float, working_length_mm: float,
              reversals: int, phantom_euler: tuple) -> tuple:
        """Before a call whose blocks share these (a :class:`~dentibot.telemetry.blocks.TickBlock`'s
        fields): what was handed over before goes first; the kernel's arguments
        ``(st, msg, head_size, k0_at, n_at, incoming, flush)``."""
        rec = self.rec
        if rec._dead is not None or rec._closed:
            rec._raise_dead()
        if rec._pending:                       # what came before the call, first
            rec._send()
        rec._read_acks()
        key = (step, state, ts, working_length_mm, reversals, tuple(phantom_euler))
        if key != self._head:
            # the header of a block of these (its first tick and count written per block)
            head = TickBlock(np.zeros((1, self.width)), 0, ts, step, state, working_length_mm,
                             reversals, tuple(phantom_euler)).packed()[0]
            size = 4 + len(head) + 8 * self.width * self._max_ticks
            if self.msg.shape[0] < size:
                self.msg = np.zeros(size, dtype=np.uint8)
            self.msg[4:4 + len(head)] = np.frombuffer(head, dtype=np.uint8)
            self._head_size = 4 + len(head)
            self._head = key
        st = self.st
        st[:] = 0
        st[wk.QUEUED], st[wk.SETTLED], st[wk.BUDGET] = rec.rows_queued, rec._settled, rec.budget
        st[wk.ROWS_FD], st[wk.ACKS_FD] = rec._rows.fileno(), rec._acks.fileno()
        st[wk.MAX_WAIT_MS] = max(1, round(rec.max_wait_s * 1000))
        st[wk.AT_RISK_MAX] = rec.at_risk_max
        return (st, self.msg, self._head_size, 4 + WIRE_K0_AT, 4 + WIRE_N_AT, self.incoming,
                self.flush)

    def end(self, last_tick: int, ts: float, group: int) -> None:
        """After the call (``last_tick``: the last tick it handed over, ``group``: its blocks'
        size): the recorder's counts and the reports read; a report that is not a flush is
        taken as :meth:`RecorderProcess.record_block` takes it. Raises what it would raise:
        the recorder dead or closed, or no room within its longest wait (an overflow of the
        block that found none)."""
        rec, st = self.rec, self.st
        sent = int(st[wk.QUEUED]) - rec.rows_queued
        if sent:
            rec.rows_queued = int(st[wk.QUEUED])
            rec.queue_depth_max = max(rec.queue_depth_max, min(sent, group))
            rec._last_t = last_tick * ts
        rec.at_risk_max = max(rec.at_risk_max, int(st[wk.AT_RISK_MAX]))
        if st[wk.FLUSHES]:
            rec._on_ack(_ack(self.flush.tobytes()))
        status = int(st[wk.STATUS])
        if status == wk.OTHER:
            size = int(st[wk.OTHER_LEN])
            try:
                data = (self.incoming[4:4 + size].tobytes() if st[wk.OTHER_READ]
                        else _read_exactly(rec._acks.fileno(), size))
            except (EOFError, OSError):
                status = wk.PIPE
            else:
                rec._on_ack(_ack(data))
                rec._read_acks()
        if status == wk.PIPE:
            rec._gone("its pipe failed")
        if rec._dead is not None:
            rec._raise_dead()
        if status == wk.NO_ROOM:
            rec.backpressure_waits += 1
            rec._overflow({"tick": last_tick + 1}, group)


def _read_exactly(fd: int, size: int) -> bytes:
    parts, left = [], size
    while left:
        part = os.read(fd, left)
        if not part:
            raise EOFError
        parts.append(part)
        left -= len(part)
    return b"".join(parts)


def _release(*conns: Connection) -> None:
    for conn in conns:
        conn.close()


def _picklable(item: tuple[str, Any], path: Path) -> bool:
    if _pickles(item):
        return True
    log.error("telemetry.unserialisable", path=str(path), what=item[0])
    return False


# -- the child process -----------------------------------------------------------------------

def _flushed(settled: int, counters: dict[str, int]) -> bytes:
    """A flush's report, packed (read back by :func:`_ack`)."""
    return _FLUSHED + _FLUSHED_BODY.pack(settled, *(counters[n] for n in CHILD_COUNTERS))


def _ack(data: bytes) -> tuple:
    """A report of the child as the tuple it stands for (a packed flush, or a pickle)."""
    if data[:1] == _FLUSHED:
        settled, *counters = _FLUSHED_BODY.unpack_from(data, 1)
        return "flushed", settled, dict(zip(CHILD_COUNTERS, counters, strict=True))
    return pickle.loads(data)


def _counters(rec: McapRecorder) -> dict[str, int]:
    return {name: getattr(rec, name) for name in CHILD_COUNTERS}


def _child_main(rows: Connection, acks: Connection) -> None:
    """The recorder process: wait for its file's arguments, build the recorder, feed it what
    arrives, report flushes. It logs as the control process does (level, format, on stderr:
    never on the standard output that ``--json`` reports own)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _terminated)
    try:
        path, metadata, options, logs = rows.recv()
    except (EOFError, OSError, _Terminated):     # a spare never used
        return
    if logs is not None:
        configure_logging(logs[0], json=logs[1])
    else:
        configure_default()
    lock = threading.Lock()                  # the writer thread reports flushes too

    def send(data: bytes) -> None:
        with lock:
            acks.send_bytes(data)

    def report(msg: tuple) -> None:
        send(pickle.dumps(msg, _PICKLE))

    def flushed(rec: McapRecorder) -> None:
        try:
            send(_flushed(rec._settled, _counters(rec)))   # noqa: SLF001 - our own
        except OSError:
            pass                                 # the parent is gone: the main loop sees it

    try:
        # written here, in the process's one thread: no writer thread to hand the rows to
        rec = McapRecorder(path, metadata, on_flush=flushed, writer_thread=False, **options)
    except BaseException as exc:  # noqa: BLE001 - sent to the parent, raised there
        report(("error", exc if _pickles(exc) else TelemetryError(path, repr(exc))))
        return
    rate = rec.metadata.get("rate_hz")
    period = 1.0 / rate if isinstance(rate, (int, float)) and math.isfinite(rate) and rate > 0 \
        else None
    report(("ready", rec.metadata, rec.budget, period))
    dead: TelemetryError | None = None
    poller = select.poll()               # made once (Connection.poll builds one a call)
    poller.register(rows.fileno(), select.POLLIN)
    ready, wait_ms = poller.poll, rec.flush_interval_s * 1000.0
    while True:
        try:
            if not ready(wait_ms):
                if dead is None:
                    try:
                        rec.flush_due()          # the rows of a pause reach the file
                    except TelemetryError as exc:
                        dead = exc
                        report(("dead", exc if _pickles(exc) else TelemetryError(path, repr(exc)),
                                _counters(rec)))
                continue
            data = rows.recv_bytes()
            items = ([("block", TickBlock.unpack(data))] if data[:1] == WIRE_TAG
                     else pickle.loads(data))
        except (EOFError, OSError, _Terminated):  # the control process is gone, or ending
            rec.close_unfinished()               # without closing (daemon: terminated)
            return
        for kind, payload in items:
            if kind == "end":
                status, reason, duration = payload
                error = None
                try:
                    end = rec.close(status, reason, duration)
                except TelemetryError as exc:
                    end, error = rec.end, (None if dead is not None else exc)
                report(("closed", end, _counters(rec), error))
                return
            if dead is not None:
                continue                         # the parent knows; wait for its close
            try:
                if kind == "tick":
                    rec.record(payload)
                elif kind == "block":
                    rec.record_block(payload)
                else:
                    ev_kind, detail, t, tick = payload
                    rec.event(ev_kind, detail, t=t, tick=tick)
            except TelemetryError as exc:
                dead = exc
                report(("dead", exc if _pickles(exc) else TelemetryError(path, repr(exc)),
                        _counters(rec)))


class _Terminated(Exception):  # noqa: N818 - a signal, not an error
    """SIGTERM in the recorder process (its parent ends without closing it)."""


def _terminated(signum: int, frame: Any) -> None:
    raise _Terminated


def _pickles(obj: Any) -> bool:
    try:
        pickle.dumps(obj, _PICKLE)
    except Exception:  # noqa: BLE001
        return False
    return True
