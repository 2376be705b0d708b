"""The real-time loop's priority: raised where the system permits, restored after."""

from __future__ import annotations

import os

import pytest

from dentibot.runtime.clock import (
    REALTIME_FIFO_PRIORITY,
    REALTIME_NICE,
    LockStepClock,
    raised_priority,
    realtime_policy,
)

pytestmark = pytest.mark.skipif(not hasattr(os, "getpriority"), reason="no priorities here")


def _may_raise() -> bool:
    """Whether this process may lower its nice value (CAP_SYS_NICE or RLIMIT_NICE)."""
    before = os.getpriority(os.PRIO_PROCESS, 0)
    try:
        os.setpriority(os.PRIO_PROCESS, 0, before - 1)
    except OSError:
        return False
    os.setpriority(os.PRIO_PROCESS, 0, before)
    return True


def test_raised_where_permitted_and_restored():
    before = os.getpriority(os.PRIO_PROCESS, 0)
    allowed = _may_raise()
    with raised_priority() as granted:
        inside = os.getpriority(os.PRIO_PROCESS, 0)
    assert os.getpriority(os.PRIO_PROCESS, 0) == before
    if allowed and before > REALTIME_NICE:
        assert granted == "nice" and inside == REALTIME_NICE
    elif not allowed:
        assert not granted and inside == before


def _may_fifo() -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (OSError, AttributeError):
        return False
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return True


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="no scheduling policies")
def test_a_sleeping_loop_gets_sched_fifo_where_permitted_and_gives_it_back():
    policy = os.sched_getscheduler(0)
    with raised_priority(fifo_priority=REALTIME_FIFO_PRIORITY) as how:
        inside = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
    assert os.sched_getscheduler(0) == policy
    if _may_fifo():
        # reset on fork: the threads and processes it starts get the ordinary policy
        reset = getattr(os, "SCHED_RESET_ON_FORK", 0)
        assert how == "fifo" and inside == (os.SCHED_FIFO | reset, REALTIME_FIFO_PRIORITY)
    else:
        assert how in ("nice", "") and inside[0] == policy


def test_an_unprivileged_thread_runs_as_it_is(monkeypatch):
    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "setpriority", refuse)
    before = os.getpriority(os.PRIO_PROCESS, 0)
    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with raised_priority(fifo_priority=REALTIME_FIFO_PRIORITY) as granted:
        assert os.getpriority(os.PRIO_PROCESS, 0) == before
    assert granted == ("nice" if before <= REALTIME_NICE else "")


def test_lock_step_leaves_the_priority_alone():
    before = os.getpriority(os.PRIO_PROCESS, 0), os.sched_getscheduler(0)
    with realtime_policy(LockStepClock(lambda: None)):
        assert (os.getpriority(os.PRIO_PROCESS, 0), os.sched_getscheduler(0)) == before


def _policy(tid: int) -> tuple[int, int, int]:
    """(policy without the reset-on-fork flag, real-time priority, nice) of thread ``tid``."""
    reset = getattr(os, "SCHED_RESET_ON_FORK", 0)
    return (os.sched_getscheduler(tid) & ~reset, os.sched_getparam(tid).sched_priority,
            os.getpriority(os.PRIO_PROCESS, tid))


@pytest.mark.skipif(not os.path.isdir("/proc/self/task")
                    or not hasattr(os, "sched_setscheduler"), reason="no per-thread priorities")
def test_the_other_threads_are_raised_with_the_loop_and_restored():
    """While the loop runs, a driver's receiver runs at SCHED_FIFO just below the control
    thread, any other thread of the process at the raised nice value; each at its own before
    and after. The calling thread is left to raised_priority."""
    import threading

    from dentibot.io import receivers
    from dentibot.runtime.clock import others_raised

    ready, done = threading.Barrier(3), threading.Event()
    tids: dict[str, int] = {}

    def thread(name: str) -> None:
        tids[name] = threading.get_native_id()
        ready.wait(5.0)
        done.wait(5.0)

    threads = {n: threading.Thread(target=thread, args=(n,), daemon=True)
               for n in ("receiver", "writer")}
    for t in threads.values():
        t.start()
    ready.wait(5.0)
    receivers.register(threads["receiver"])
    me_before = _policy(0)
    before = {n: _policy(tid) for n, tid in tids.items()}
    try:
        with others_raised(fifo_priority=REALTIME_FIFO_PRIORITY):
            inside = {n: _policy(tid) for n, tid in tids.items()}
            me_inside = _policy(0)
        after = {n: _policy(tid) for n, tid in tids.items()}
    finally:
        done.set()
        for t in threads.values():
            t.join(5.0)
    assert after == before and me_inside == me_before
    if _may_fifo():
        assert inside["receiver"][:2] == (os.SCHED_FIFO, REALTIME_FIFO_PRIORITY - 1)
    else:
        assert inside["receiver"] == before["receiver"] or inside["receiver"][2] == REALTIME_NICE
    if _may_raise() and before["writer"][2] > REALTIME_NICE:
        assert inside["writer"] == (os.SCHED_OTHER, 0, REALTIME_NICE)
    else:
        assert inside["writer"] == before["writer"]
