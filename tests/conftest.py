"""Suite-wide guards: a test fails if it leaks threads, sockets or asyncio tasks.

- Threads and sockets: compared before and after every test (after a short grace period for
  threads that are already stopping, e.g. python-can notifiers being joined).
- Tasks: every coroutine test also runs the async fixture ``_no_leaked_tasks``, which checks,
  inside the test's own event loop, that the test left no task running.
"""

from __future__ import annotations

import asyncio
import gc
import inspect
import os
import threading
import time

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
    threads, socks = _threads(), _sockets()
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
