"""Many simulated runs: one protocol run with a light per-tick tap, many runs in parallel
local processes, and the measures the experiments and the trials take of them alike.

Runs are in lock-step simulated time (:class:`~dentibot.app.runner.ProtocolRunner` on the
built-in simulator, no recording). Parallel runs use a :class:`ProcessPoolExecutor` with the
"spawn" start method (a clean interpreter per worker: no inherited threads, event loops or
logging state); every run is a picklable spec in and a picklable result out, and results come
back in the order of the specs whatever the number of workers, so ``--workers`` never changes
a number.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import sys
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextvars import ContextVar
from typing import Any, TypeVar

import numpy as np
import structlog

from dentibot.app.runner import ProtocolRunner, RunResult
from dentibot.protocol.schema import Protocol


#: Stall: feeding while the deepest point gains less than this (mm) ...
STALL_GAIN_MM = 0.1
#: ... over this window (s).
STALL_WINDOW_S = 10.0

S = TypeVar("S")
R = TypeVar("R")

#: The ``cancel`` of the :func:`run_all` running runs in this thread: :func:`run_protocol`
#: stops its run safely once it is set.
_CANCEL: ContextVar[threading.Event | None] = ContextVar("dentibot_run_all_cancel",
                                                         default=None)


def quiet_logs(level: int = logging.WARNING) -> None:
    """A worker process's logging: ``level`` and above only (default: warnings and errors),
    on stderr (structlog's default prints everything to stdout, where ``--json`` output
    goes)."""
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(level),
                        logger_factory=structlog.PrintLoggerFactory(sys.stderr))


def default_workers() -> int:
    return max(1, os.cpu_count() or 1)


def run_all(fn: Callable[[S], R], specs: Sequence[S], workers: int = 1,
            done: Callable[[S, R], None] | None = None,
            cancel: threading.Event | None = None,
            log_level: int = logging.WARNING) -> list[R]:
    """``[fn(s) for s in specs]``, in ``workers`` local processes when ``workers > 1``.

    ``fn`` must be a module-level function (it is pickled by name). ``done(spec, result)`` is
    called in this process as each run finishes (progress display). Results are in the order
    of ``specs``. An exception in a run (or Ctrl-C) cancels the runs not started yet.
    ``cancel``: once set (from another thread), KeyboardInterrupt as after Ctrl-C; a run in
    this process (``workers == 1``) first stops safely after its current tick, runs in worker
    processes finish first. ``log_level``: what worker processes log (:func:`quiet_logs`).
    """
    specs = list(specs)
    workers = max(1, min(int(workers), len(specs)))
    results: list[Any] = [None] * len(specs)
    if workers == 1:
        token = _CANCEL.set(cancel)
        try:
            for i, s in enumerate(specs):
                _raise_if_set(cancel)
                results[i] = fn(s)
                _raise_if_set(cancel)
                if done is not None:
                    done(s, results[i])
        finally:
            _CANCEL.reset(token)
        return results
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx,
                             initializer=quiet_logs, initargs=(log_level,)) as pool:
        futures = {pool.submit(fn, s): i for i, s in enumerate(specs)}
        pending = set(futures)
        try:
            while pending:
                finished, pending = wait(pending, timeout=None if cancel is None else 0.1,
                                         return_when=FIRST_COMPLETED)
                _raise_if_set(cancel)
                for f in finished:
                    i = futures[f]
                    results[i] = f.result()
                    if done is not None:
                        done(specs[i], results[i])
        except BaseException:
            pool.shutdown(wait=True, cancel_futures=True)
            raise
    return results


def _raise_if_set(cancel: threading.Event | None) -> None:
    if cancel is not None and cancel.is_set():
        raise KeyboardInterrupt("cancelled")


def run_protocol(protocol: Protocol, tap: Callable[[dict, ProtocolRunner], None] | None,
                 prepare: Callable[[ProtocolRunner], None] | None = None,
                 feed_summary: bool = False,
                 limit_share: float | None = None,
                 on_tick: Callable[[ProtocolRunner], None] | None = None,
                 compiled_ticks: bool = True) -> tuple[RunResult, ProtocolRunner]:
    """Run ``protocol`` on the built-in simulator without a recording; ``tap(row, runner)``
    sees every telemetry row, ``on_tick(runner)`` is called after every tick.

    ``prepare(runner)`` is called once before the run (to set what the protocol schema does
    not describe, e.g. when the patient's motion starts). Unless ``feed_summary``, the rows go
    to ``tap`` only, not to the runner's live summary (it would cost about a third of the run
    time): the result's summary then carries the status and its reason, the figures come from
    the tap. With neither a tap nor ``feed_summary`` no row is built at all (a study that
    reads the runtime and the world in ``on_tick``: a trial procedure ran about 15 % faster).
    ``limit_share``, ``compiled_ticks`` (an ``on_tick`` with a ``ticks`` method): see
    :class:`~dentibot.app.runner.ProtocolRunner`.
    """
    cancel = _CANCEL.get()

    def check_cancel(r: ProtocolRunner) -> None:
        if cancel is not None and cancel.is_set():
            r.abort("cancelled")

    def after(r: ProtocolRunner) -> None:
        if on_tick is not None:
            on_tick(r)
        check_cancel(r)

    bulk = getattr(on_tick, "ticks", None)
    if bulk is not None:             # it takes compiled drilling ticks in bulk too
        def ticks(r: ProtocolRunner, out, n: int, k0: int, state: str) -> None:
            bulk(r, out, n, k0, state)
            check_cancel(r)

        after.ticks, after.every = ticks, getattr(on_tick, "every", None)

    runner = ProtocolRunner(protocol, no_record=True,
                            tap=None if tap is None else (lambda row: tap(row, runner)),
                            on_tick=after, live_summary=feed_summary,
                            compiled_ticks=compiled_ticks,
                            **({} if limit_share is None else {"limit_share": limit_share}))
    if prepare is not None:
        prepare(runner)
    result = asyncio.run(runner.run())
    return result, runner


def stalled_seconds(t: np.ndarray, depth: np.ndarray, feeding: np.ndarray,
                    until_s: float | None = None, window_s: float = STALL_WINDOW_S,
                    gain_mm: float = STALL_GAIN_MM) -> float:
    """Time (s) spent feeding before ``until_s`` (the first arrival at working length; None:
    the whole run) at samples where the deepest point reached so far had grown by less than
    ``gain_mm`` over the last ``window_s``. Samples evenly spaced in ``t`` (s)."""
    t = np.asarray(t, float)
    if len(t) < 2:
        return 0.0
    dt = float(t[1] - t[0])
    deepest = np.maximum.accumulate(np.asarray(depth, float))
    end = len(t) if until_s is None else int(np.searchsorted(t, until_s))
    lag = max(1, round(window_s / dt))
    idx = np.arange(lag, end)
    gained = deepest[idx] - deepest[idx - lag]
    stalled = (gained < gain_mm) & np.asarray(feeding, bool)[idx]
    return float(stalled.sum()) * dt
