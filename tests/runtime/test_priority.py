"""The real-time loop's priority: raised where the system permits, restored after."""

from __future__ import annotations

import contextlib
import os
import threading

import pytest

from dentibot.runtime.clock import (
    REALTIME_FIFO_PRIORITY,
    REALTIME_NICE,
    LockStepClock,
    others_raised,
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


@contextlib.contextmanager
def _receiver():
    """A thread of the process (a driver's receiver, waiting on its socket) while the block
    runs; yields its native id."""
    ready, done = threading.Event(), threading.Event()
    tid: list[int] = []

    def receive() -> None:
        tid.append(threading.get_native_id())
        ready.set()
        done.wait(5.0)

    t = threading.Thread(target=receive, daemon=True)
    t.start()
    ready.wait(5.0)
    try:
        yield tid[0]
    finally:
        done.set()
        t.join(5.0)


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="no per-thread priorities")
def test_the_other_threads_are_raised_with_the_loop_and_restored():
    """A thread of the process that shares the interpreter lock with the control loop (a
    driver's receiver) runs at the raised nice value while the loop runs, and at its own
    before and after; the calling thread is left to raised_priority."""
    with _receiver() as tid:
        me_before = os.getpriority(os.PRIO_PROCESS, 0)
        before = os.getpriority(os.PRIO_PROCESS, tid)
        with others_raised():
            inside = os.getpriority(os.PRIO_PROCESS, tid)
            me_inside = os.getpriority(os.PRIO_PROCESS, 0)
        after = os.getpriority(os.PRIO_PROCESS, tid)
    assert after == before and me_inside == me_before
    if _may_raise() and before > REALTIME_NICE:
        assert inside == REALTIME_NICE
    else:
        assert inside == before


@pytest.mark.skipif(not os.path.isdir("/proc/self/task")
                    or not hasattr(os, "sched_setscheduler"), reason="no per-thread policies")
def test_under_a_real_time_loop_the_other_threads_share_its_policy_and_get_theirs_back():
    """With the loop at SCHED_FIFO, a receiver thread runs at the loop's own real-time
    priority while the loop runs (nothing of lower priority can then preempt it while it
    holds the interpreter lock), and at its own policy before and after."""
    def policy(tid: int) -> tuple[int, int]:
        return os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority

    with _receiver() as tid:
        before, me_before = policy(tid), os.sched_getscheduler(0)
        with others_raised(fifo_priority=REALTIME_FIFO_PRIORITY):
            inside, me_inside = policy(tid), os.sched_getscheduler(0)
        after = policy(tid)
    assert after == before and me_inside == me_before
    if _may_fifo():
        reset = getattr(os, "SCHED_RESET_ON_FORK", 0)
        assert inside == (os.SCHED_FIFO | reset, REALTIME_FIFO_PRIORITY)
    else:                                     # refused: the nice value instead, or nothing
        assert inside[0] == before[0]


@pytest.mark.skipif(not os.path.isdir("/proc/self/task")
                    or not hasattr(os, "sched_setscheduler"), reason="no per-thread policies")
@pytest.mark.parametrize("inherit", [False, True])
def test_a_thread_started_under_sched_fifo_inherits_it_only_when_asked(inherit):
    """The control loop's threads and processes start at the ordinary policy (reset on
    fork); the wire simulators' threads inherit the loop's real-time priority."""
    with raised_priority(fifo_priority=REALTIME_FIFO_PRIORITY, threads_inherit=inherit) as how, \
            _receiver() as tid:
        policy = os.sched_getscheduler(tid) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)
    if how != "fifo":
        pytest.skip("SCHED_FIFO not permitted here")
    assert policy == (os.SCHED_FIFO if inherit else os.SCHED_OTHER)
