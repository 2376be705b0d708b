"""The MCAP recorder in a process of its own: the control task hands rows over and goes on.

Why. :class:`~dentibot.telemetry.recorder.McapRecorder`'s writer spends 5-20 us of CPU per
tick (the ``/tf`` and ``/scene`` views, the mcap library's records, compression), all of it
holding the interpreter lock the control task needs. :class:`RecorderProcess` runs that same
recorder in a child process, on another core and under another interpreter lock, writing in
the child's one thread.

How rows cross. Through the journal (:mod:`~dentibot.telemetry.journal`): a ring in a file
beside the recording (``run.mcap.journal``), mapped into both processes. The control task
copies each message into it (a pickled batch of rows and events, about 3 us a row, or a block
of rows in its wire form, :meth:`RecorderProcess.record_block`, about 11 us for 256 ticks) and
publishes it: no system call, no wake-up of the other process. The child looks every
:data:`DRAIN_S` (or when rung: at close, or when the control task waits for room), writes what
it finds and publishes each flush in the journal's header. Before the journal, the rows went
through a pipe, 25 ticks at a time under a budget of 50 ticks at risk, and in lock-step time
the control task waited for the child every 25 ticks: the recorder made the main job's
drilling 1.7-2.5 times slower; with the journal, 1.1-1.3 (``benchmarks/real_tick.py``).

What a crash can cost: nothing handed over. What the file does not hold yet is in the
journal, which outlives the death of either process (the system keeps what a process wrote
to a shared file mapping):

- the control process dies (``kill -9``, a crash): the child sees its pipe close, writes out
  everything in the journal and closes the file without ``/run/end`` or summary (readers flag
  the recording incomplete), then deletes the journal;
- the child dies: the next ``record()``, ``event()`` or ``close()`` raises
  :class:`~dentibot.telemetry.schema.TelemetryError`, which says how many ticks the journal
  keeps; ``dentibot recover`` writes the file with them
  (:mod:`~dentibot.telemetry.recover`);
- a closed recording has no journal.

The budget. At most ``budget`` ticks handed over and not yet in the file:
``journal_s`` [4.0] of procedure at the run's rate (2,000 ticks at 500 Hz), or ``max_queue``
when given. The child writes the file at least every half budget (``flush_ticks``) and every
``flush_interval_s`` of wall time; ``record()`` waits when the budget is full, at most
``max_wait_s``, then drops the row and raises
:class:`~dentibot.telemetry.recorder.TelemetryOverflow`. The journal's bytes
(:data:`JOURNAL_BYTES_PER_TICK` per tick of budget) hold a full budget of rows. Other
arguments are the in-process recorder's; errors of them (file exists, bad compression...) are
raised by the constructor, as the in-process recorder raises them (the child builds the
recorder and sends them back). Batches of rows leave this process after ``send_ticks`` items
(a fifth of the budget, at most 10) or half of ``flush_interval_s`` after the first.

What the child does on its own. It ignores SIGINT (Ctrl-C belongs to the control process,
which stops the procedure safely and then closes the recording).

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
import sys
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
from dentibot.telemetry.blocks import WIRE_K0_AT, WIRE_N_AT, TickBlock
from dentibot.telemetry.journal import (
    COUNTERS,
    LENGTH_BYTES,
    SETTLED,
    WAITING,
    Journal,
    items_of,
    journal_path,
)
from dentibot.telemetry.recorder import (
    DEFAULT_RATE_HZ,
    McapRecorder,
    RecorderBase,
    TelemetryOverflow,
)
from dentibot.telemetry.schema import END_STATUSES, TelemetryError

__all__ = ["Recorder", "RecorderProcess", "Wire", "open_recorder"]

log = structlog.get_logger("dentibot.telemetry")

#: counters kept by the child's recorder, published in the journal's header at each flush
#: (McapRecorder's names)
CHILD_COUNTERS = ("ticks_written", "events_written", "rows_rejected", "rows_invalid",
                  "nonfinite_rows", "flushes", "rows_flushed", "bytes_flushed",
                  "transforms_written", "scenes_written", "view_errors")
#: procedure time the journal holds beyond the file by default (the budget: 2,000 ticks at
#: 500 Hz). The file is written every half of it, or every ``flush_interval_s`` of wall time
#: when the run is slower: in lock-step time, steps of 1,000 ticks instead of 25, where the
#: writer spends half the CPU per tick
JOURNAL_S = 4.0
#: the journal's bytes per tick of budget: a tick row pickled with the others of its batch
#: takes about 1.6 kB, a block's tick 336 bytes
JOURNAL_BYTES_PER_TICK = 4096
#: the child's longest sleep between two looks at the journal: in lock-step time a few
#: hundred ticks arrive meanwhile, written in one go
DRAIN_S = 0.005
#: the longest wait of the control process for room before it looks again (the child tells
#: it when it flushes; this is for a flush that came between its look and its request)
_ROOM_POLL_S = 0.005
#: the control process's message saying the journal exists (then only doorbell bytes follow)
_JOURNAL_READY = b"journal"
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
    (``record``, ``event``, ``close``, ``duration_s``, context manager) and counters, plus
    ``journal_s``: the procedure time the journal holds beyond the file (the budget);
    the counters the writer keeps are those of the child's last flush, final after
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
        self.journal: Journal | None = None
        # dropped without close(): the pipes close, the child writes out what it has
        self._release = weakref.finalize(self, _release, rows_w, acks_r)
        rows_w.send((str(path), metadata, options, logging_settings()))
        ready = self._first_message()
        if ready[0] == "error":
            self._release()
            self._proc.join()
            raise ready[1]
        _, self.metadata, self.budget, self.period_s, capacity = ready
        try:
            self.journal = Journal.create(journal_path(self.path), capacity)
        except TelemetryError:
            self._release()                       # the child sees its pipe close: it ends
            self._proc.join()
            raise
        self._release.detach()                   # replaced: the journal is unmapped too
        self._release = weakref.finalize(self, _release, rows_w, acks_r, self.journal)
        rows_w.send_bytes(_JOURNAL_READY)
        os.set_blocking(rows_w.fileno(), False)   # from now on, doorbells only
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
        self._final: dict[str, int] | None = None   # the child's counters at its end
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
            return pickle.loads(self._acks.recv_bytes())
        except EOFError:
            self._proc.join()
            raise TelemetryError(self.path, f"the recorder process died at start (exit code "
                                 f"{self._proc.exitcode})") from None

    @property
    def _settled(self) -> int:
        """Ticks the child has written to the file (or rejected)."""
        j = self.journal
        return 0 if j is None or j.hdr is None else int(j.hdr[SETTLED])

    @property
    def _counters(self) -> dict[str, int]:
        """The child's counters: those of its last flush, or of its end."""
        if self._final is not None:
            return self._final
        j = self.journal
        if j is None or j.hdr is None:
            return dict.fromkeys(CHILD_COUNTERS, 0)
        cells = j.hdr[COUNTERS:COUNTERS + len(CHILD_COUNTERS)].tolist()
        return dict(zip(CHILD_COUNTERS, cells, strict=True))

    # -- caller side (the control task) ----------------------------------------------------

    def record(self, row: dict[str, Any]) -> None:
        """Hand one tick row over. Returns at once unless ``budget`` ticks are not in the
        file yet; then waits for the child's next flush, at most ``max_wait_s`` (then the row
        is dropped and TelemetryOverflow raised). The row must not be changed afterwards."""
        if self._dead is not None or self._closed:
            self._raise_dead()
        if self.rows_queued - self._settled >= self.budget:
            self._wait_for_room(row)
        pending = self._pending
        if not pending:
            self._pending_since = time.monotonic()
        pending.append(("tick", row))
        self.rows_queued += 1
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
        self.queue_depth_max = max(self.queue_depth_max, n)
        self._last_t = (block.k0 + n - 1) * block.ts
        self._write(b"".join(block.packed()), n, {"tick": block.k0})   # no pickle

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
        ticks = [payload for kind, payload in items if kind == "tick"]
        self._write(data, len(ticks), ticks[0] if ticks else None, raise_dead)

    def _write(self, data: bytes, ticks: int, first: Any, raise_dead: bool = True) -> None:
        """One message into the journal (a pickled list of items, or a packed block of
        ``ticks`` ticks from row ``first``), after waiting for room in it; then read what the
        child reported. Without room within ``max_wait_s``, its ticks are dropped (and
        TelemetryOverflow raised)."""
        j = self.journal
        size = len(data) + LENGTH_BYTES
        if size > j.capacity:
            self.rows_queued -= ticks
            raise TelemetryError(self.path, f"a message of {size} bytes exceeds the "
                                 f"journal's {j.capacity}")
        if j.room() < size:
            try:
                self._wait_until(lambda: j.room() >= size, first, max(ticks, 1))
            except TelemetryOverflow:
                self.rows_queued -= ticks
                raise
            if self._dead is not None:
                if raise_dead:
                    self._raise_dead()
                return
        j.put(data)
        self.at_risk_max = max(self.at_risk_max, self.rows_queued - self._settled)
        self._read_acks()

    def _ring(self) -> None:
        """Wake the child now (it wakes every few milliseconds anyway)."""
        try:
            os.write(self._rows.fileno(), b"\0")
        except BlockingIOError:                   # doorbells enough are waiting
            pass
        except OSError as exc:                    # the child is gone
            self._gone(str(exc))

    def _gone(self, why: str) -> None:
        """The child cannot be reached (``why``): what it reported last is read, and the
        recorder is dead, with the child's own report if it sent one."""
        self._read_acks()
        if self._dead is None:
            self._dead = TelemetryError(self.path, f"the recorder process is gone (exit code "
                                        f"{self._proc.exitcode}): {why}; {self._kept()}")

    def _kept(self) -> str:
        """Where the ticks not in the file are."""
        return (f"the {self.rows_queued - self._settled} ticks handed over and not in the "
                f"file are kept in {journal_path(self.path).name}: 'dentibot recover' adds "
                f"them")

    def _read_acks(self, timeout: float = 0.0) -> bool:
        """Read what the child reported; wait up to ``timeout`` for the first message.
        True if anything was read."""
        acks, ready = self._acks, self._acks_poll.poll
        got = False
        try:
            while ready(max(timeout, 0.0) * 1000.0):
                self._on_ack(pickle.loads(acks.recv_bytes()))
                got = True
                timeout = 0.0
        except (EOFError, OSError):
            if self._dead is None and not (self._closed and self.end is not None):
                self._dead = TelemetryError(self.path, f"the recorder process died (exit code "
                                            f"{self._proc.exitcode}); {self._kept()}")
        return got

    def _on_ack(self, msg: tuple) -> None:
        kind = msg[0]
        if kind == "dead":
            self._dead = msg[1]
        elif kind == "closed":
            self.end = msg[1]
            self._final = msg[2]
            if msg[3] is not None and self._dead is None:
                self._dead = msg[3]

    def _wait_for_room(self, row: Any, n: int = 1) -> None:
        """Wait until ``n`` more ticks fit in the budget."""
        if self._pending:
            self._send()
        self._wait_until(lambda: self.rows_queued - self._settled + n <= self.budget, row, n)
        if self._dead is not None:
            self._raise_dead()

    def _wait_until(self, room: Any, row: Any, count: int) -> None:
        """Wait until ``room()``, waking the child; after ``max_wait_s``, ``count`` ticks from
        ``row`` are dropped (TelemetryOverflow). Returns early when the child is dead."""
        self.backpressure_waits += 1
        deadline = time.monotonic() + self.max_wait_s
        hdr = self.journal.hdr
        while not room() and self._dead is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._overflow(row, count)
            hdr[WAITING] = 1                      # the child says when it flushes
            if room():                            # (it may have, just before)
                break
            self._ring()
            self._read_acks(min(remaining, _ROOM_POLL_S))
        hdr[WAITING] = 0

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
        """Ticks handed over and not yet in the file: they are in the journal."""
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
        self._ring()
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
        if self.end is None and self._dead is None:
            self._dead = TelemetryError(self.path, f"the recorder process ended without "
                                        f"finishing the file (exit code {self._proc.exitcode}); "
                                        f"{self._kept()}")
        self._final = self._counters             # read before the journal is unmapped
        self._release()
        if self._dead is not None and not self._dead_reported:
            self._raise_dead()
        return self.end


#: what :func:`open_recorder` returns
Recorder = McapRecorder | RecorderProcess


class Wire:
    """A :class:`RecorderProcess`'s journal for compiled code
    (:func:`~dentibot.telemetry.wire_kernels.send_block`): the blocks of a compiled call's
    ticks go into the journal from the call itself, as
    :meth:`RecorderProcess.record_block` puts them (the same bytes, the same budget of
    ticks, the same waits for room), while the call runs without the interpreter lock.
    :meth:`begin` before the call gives the kernel's arguments; :meth:`end` after it brings
    the recorder up to date."""

    def __init__(self, rec: RecorderProcess, width: int, max_ticks: int) -> None:
        self.rec = rec
        self.width = int(width)
        self.st = np.zeros(wk.ST_SIZE, dtype=np.int64)
        self._max_ticks = int(max_ticks)
        self.msg = np.zeros(0, dtype=np.uint8)
        self._head: tuple | None = None

    def begin(self, step: str, state: str, ts: float, working_length_mm: float,
              reversals: int, phantom_euler: tuple) -> tuple:
        """Before a call whose blocks share these (a :class:`~dentibot.telemetry.blocks.TickBlock`'s
        fields): what was handed over before goes first; the kernel's arguments
        ``(st, hdr, ring, msg, head_size, k0_at, n_at)``."""
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
            size = LENGTH_BYTES + len(head) + 8 * self.width * self._max_ticks
            if self.msg.shape[0] < size:
                self.msg = np.zeros(size, dtype=np.uint8)
            self.msg[LENGTH_BYTES:LENGTH_BYTES + len(head)] = np.frombuffer(head, dtype=np.uint8)
            self._head_size = LENGTH_BYTES + len(head)
            self._head = key
        st = self.st
        st[:] = 0
        st[wk.QUEUED], st[wk.BUDGET] = rec.rows_queued, rec.budget
        st[wk.ROWS_FD], st[wk.ACKS_FD] = rec._rows.fileno(), rec._acks.fileno()
        st[wk.MAX_WAIT_MS] = max(1, round(rec.max_wait_s * 1000))
        st[wk.AT_RISK_MAX] = rec.at_risk_max
        j = rec.journal
        return (st, j.hdr, j.ring, self.msg, self._head_size, LENGTH_BYTES + WIRE_K0_AT,
                LENGTH_BYTES + WIRE_N_AT)

    def end(self, last_tick: int, ts: float, group: int) -> None:
        """After the call (``last_tick``: the last tick it handed over, ``group``: its blocks'
        size): the recorder's counts and the child's reports read. Raises what
        :meth:`RecorderProcess.record_block` would raise: the recorder dead or closed, or no
        room within its longest wait (an overflow of the block that found none)."""
        rec, st = self.rec, self.st
        sent = int(st[wk.QUEUED]) - rec.rows_queued
        if sent:
            rec.rows_queued = int(st[wk.QUEUED])
            rec.queue_depth_max = max(rec.queue_depth_max, min(sent, group))
            rec._last_t = last_tick * ts
        rec.at_risk_max = max(rec.at_risk_max, int(st[wk.AT_RISK_MAX]))
        status = int(st[wk.STATUS])
        rec._read_acks()                          # a report stopped the call, or may be there
        if status == wk.PIPE:
            rec._gone("its pipe failed")
        if rec._dead is not None:
            rec._raise_dead()
        if status == wk.NO_ROOM:
            rec.backpressure_waits += 1
            rec._overflow({"tick": last_tick + 1}, group)


def _release(*conns: Connection) -> None:
    for conn in conns:
        conn.close()


def _picklable(item: tuple[str, Any], path: Path) -> bool:
    if _pickles(item):
        return True
    log.error("telemetry.unserialisable", path=str(path), what=item[0])
    return False


# -- the child process -----------------------------------------------------------------------

def _counters(rec: McapRecorder) -> dict[str, int]:
    return {name: getattr(rec, name) for name in CHILD_COUNTERS}


def _check_journal_s(journal_s: Any) -> float:
    if not (isinstance(journal_s, (int, float)) and not isinstance(journal_s, bool)
            and math.isfinite(journal_s) and journal_s > 0):
        raise ConfigError("telemetry.journal_s", journal_s, "a finite number > 0 (s)")
    return float(journal_s)


def _journal_budget(rec: McapRecorder, options: dict[str, Any], journal_s: float) -> int:
    """The process's budget in ticks: ``max_queue`` when given, else ``journal_s`` of
    procedure at the run's rate (the in-process recorder's default rate without one)."""
    if options.get("max_queue") is not None:
        return rec.budget
    period = rec.period_s or 1.0 / DEFAULT_RATE_HZ
    return max(1, math.floor(journal_s / period + 1e-9))


def _child_main(rows: Connection, acks: Connection) -> None:
    """The recorder process: wait for its file's arguments, build the recorder, then write
    what the journal brings (waking every :data:`DRAIN_S`, or when the control process rings),
    publishing each flush in the journal's header. It logs as the control process does (level,
    format, on stderr: never on the standard output that ``--json`` reports own)."""
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

    def report(msg: tuple) -> None:
        acks.send_bytes(pickle.dumps(msg, _PICKLE))

    journal: Journal | None = None
    done_at = 0                                   # the byte after the last message written

    def flushed(rec: McapRecorder) -> None:
        if journal is not None:
            journal.release(done_at, rec._settled, list(_counters(rec).values()))
            if journal.hdr[WAITING]:             # the control process waits for room
                journal.hdr[WAITING] = 0
                try:
                    report(("room",))
                except OSError:                  # it is gone: the main loop sees it
                    pass

    options = dict(options)
    try:
        journal_s = _check_journal_s(options.pop("journal_s", JOURNAL_S))
        # written here, in the process's one thread: no writer thread to hand the rows to
        rec = McapRecorder(path, metadata, on_flush=flushed, writer_thread=False, **options)
    except BaseException as exc:  # noqa: BLE001 - sent to the parent, raised there
        report(("error", exc if _pickles(exc) else TelemetryError(path, repr(exc))))
        return
    budget = _journal_budget(rec, options, journal_s)
    rec.budget = budget                          # its flush_ticks follow: half of it
    report(("ready", rec.metadata, budget, rec.period_s, _capacity(budget)))
    try:
        if rows.recv_bytes() != _JOURNAL_READY:
            raise EOFError
        journal = Journal.open(journal_path(path))
    except (EOFError, OSError, TelemetryError, _Terminated):   # the parent could not make it
        rec.close_unfinished()                   # nothing recorded: no file left behind
        Path(path).unlink(missing_ok=True)
        return
    bell = rows.fileno()
    poller = select.poll()
    poller.register(bell, select.POLLIN)
    dead: TelemetryError | None = None
    wait_ms = min(DRAIN_S, rec.flush_interval_s / 2) * 1000.0
    parent_gone = False

    def died(exc: TelemetryError) -> None:
        nonlocal dead
        dead = exc
        report(("dead", exc if _pickles(exc) else TelemetryError(path, repr(exc))))

    try:
        busy = False
        while True:
            if poller.poll(0 if busy else wait_ms):   # sleep only when nothing came
                try:
                    parent_gone = not os.read(bell, 4096)   # doorbells, or the pipe closed
                except OSError:
                    parent_gone = True
            busy = False
            for end, message in journal.messages(done_at):
                busy = True
                for kind, payload in items_of(message):
                    if kind == "end":
                        _close(rec, journal, payload, dead, report)
                        return
                    if dead is not None:
                        continue                 # the parent knows; wait for its close
                    try:
                        if kind == "tick":
                            rec.record(payload)
                        elif kind == "block":
                            rec.record_block(payload)
                        else:
                            ev_kind, detail, t, tick = payload
                            rec.event(ev_kind, detail, t=t, tick=tick)
                    except TelemetryError as exc:
                        died(exc)
                done_at = end
            if dead is None:
                try:
                    rec.flush_due()              # the rows of a pause reach the file
                except TelemetryError as exc:
                    died(exc)
            if parent_gone:                      # every message it wrote is read: close
                rec.close_unfinished()           # without /run/end (the run did not end)
                if dead is None and rec.error is None:
                    journal.unlink()             # all of it is in the file
                return
    except (_Terminated, OSError):                # ending with the parent (daemon), or it is
        rec.close_unfinished()                    # gone mid-report: the journal keeps the rest


def _close(rec: McapRecorder, journal: Journal, payload: tuple, dead: TelemetryError | None,
           report: Any) -> None:
    """The run's end: the file finished, the journal deleted once all it held is in it."""
    status, reason, duration = payload
    error = None
    try:
        end = rec.close(status, reason, duration)
    except TelemetryError as exc:
        end, error = rec.end, (None if dead is not None else exc)
    if error is None and dead is None:
        journal.unlink()
    journal.close()
    report(("closed", end, _counters(rec), error))


def _capacity(budget: int) -> int:
    """The journal's bytes for ``budget`` ticks: room for them as pickled rows (the larger
    form; a block's tick is 336 bytes), and never less than 1 MiB."""
    return max(1 << 20, budget * JOURNAL_BYTES_PER_TICK)


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
