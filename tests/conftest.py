"""Suite-wide guards: a test fails if it leaks threads, sockets or asyncio tasks.

- Threads and sockets: compared before and after every test (after a short grace period for
  threads that are already stopping, e.g. python-can notifiers being joined).
- Tasks: every coroutine test also runs the async fixture ``_no_leaked_tasks``, which checks,
  inside the test's own event loop, that the test left no task running.
"""

from __future__ import annotations

import asyncio
import functools
import gc
import inspect
import multiprocessing
import os
import re
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path

import pytest


def _sockets() -> set[str]:
    """Open socket file descriptors of this process (Linux /proc)."""
    out = set()
    try:
        fds = os.listdir("/proc/self/fd")
    except OSError:            # not Linux: nothing to compare
        return out
    for fd in fds:
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:"):
            out.add(f"{fd}:{target}")
    return out


def _threads() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if t.is_alive()}


@pytest.fixture(autouse=True)
def _no_leaked_threads_or_sockets():
    # before: every thread started, including those not yet running (a busy machine can hold
    # a just-started thread back, not alive yet, past this snapshot: it is not the test's)
    threads, socks = set(threading.enumerate()), _sockets()
    yield
    deadline = time.monotonic() + 2.0
    while True:
        gc.collect()
        new_threads = _threads() - threads
        new_socks = _sockets() - socks
        if not (new_threads or new_socks) or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert not new_threads, f"test leaked threads: {sorted(t.name for t in new_threads)}"
    assert not new_socks, f"test leaked {len(new_socks)} socket(s): {sorted(new_socks)}"


@pytest.fixture(scope="module")
def worker_runs():
    """Start long independent runs in two spawned worker processes, for a module's fixture:
    ``worker_runs({key: (fn, *args)})`` submits them in the order given and returns their
    futures; the pool is shut down with the module.

    It returns once the pool's own threads are started: the call queue's feeder thread starts
    at the pool's first put, a moment after ``submit`` returned; started later, inside the
    first test, the thread-leak check would count it as that test's."""
    pools: list[ProcessPoolExecutor] = []

    def start(calls: dict) -> dict[str, Future]:
        before = set(threading.enumerate())    # another pool's feeder may still be ending
        pool = ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn"))
        pools.append(pool)
        futures = {key: pool.submit(*call) for key, call in calls.items()}
        deadline = time.monotonic() + 10.0
        while not any(t.name == "QueueFeederThread" and t not in before
                      for t in threading.enumerate()):
            if time.monotonic() > deadline:
                raise TimeoutError("the worker pool's call queue was never fed")
            time.sleep(0.005)
        return futures

    yield start
    for pool in pools:
        pool.shutdown(cancel_futures=True)


@pytest.fixture
async def _no_leaked_tasks():
    before = asyncio.all_tasks()
    yield
    await asyncio.sleep(0)          # let tasks that were just cancelled finish
    left = [t for t in asyncio.all_tasks() - before
            if t is not asyncio.current_task() and not t.done()]
    assert not left, f"test leaked asyncio tasks: {[t.get_coro() for t in left]}"


def pytest_collection_modifyitems(items):
    for item in items:
        fn = getattr(item, "function", None)
        if fn is not None and inspect.iscoroutinefunction(fn):
            item.fixturenames.insert(0, "_no_leaked_tasks")   # torn down last


@pytest.fixture(autouse=True)
def _no_devices_from_the_environment(monkeypatch):
    """A developer's ``DENTIBOT_DEVICES`` must never send a test's run to their hardware."""
    monkeypatch.delenv("DENTIBOT_DEVICES", raising=False)


#: how a test file marks its tests wire (real time on loopback sockets or a CAN bus): its
#: module-level pytestmark, alone or first in a list
WIRE_MARK = re.compile(r"^pytestmark = \[?pytest\.mark\.wire\b", re.MULTILINE)


@functools.cache
def _on_the_wire(path: Path) -> bool:
    """Whether the test file marks its tests ``wire``."""
    try:
        return WIRE_MARK.search(path.read_text(encoding="utf-8")) is not None
    except OSError:
        return False


def pytest_xdist_make_scheduler(config, log):
    """pytest-xdist's workers take one test file at a time (a module's fixtures run once),
    and every file marked ``wire`` on one worker, one after another: two tests on the wire
    at once, each with its simulators, drivers and child processes, met the drive's 30 ms
    heartbeat consumer; one beside a CPU-bound worker holds its deadlines, as it must on a
    busy machine. (A scheduler of its own: xdist's ``loadgroup`` renames node ids through
    an attribute pytest 9.2 no longer reads.)"""
    from xdist.scheduler import LoadScopeScheduling

    root = config.rootpath

    class WireApart(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            return "wire" if _on_the_wire(root / path) else path

    return WireApart(config, log)
