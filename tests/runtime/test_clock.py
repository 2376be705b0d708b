"""Clocks and deadline accounting (functional checks; speed is measured in benchmarks/)."""

from __future__ import annotations

import asyncio
import dataclasses
import gc
import os
import threading
import time

import pytest

from dentibot.app.procedure import Procedure
from dentibot.errors import ConfigError
from dentibot.runtime.clock import (
    DeadlineStats,
    LockStepClock,
    RealTimeClock,
    check_cpus,
    pinned,
)
from dentibot.runtime.config import RuntimeConfig
from dentibot.runtime.deadline_timer import deadline_timer
from dentibot.sim.world import WorldConfig

pytestmark = pytest.mark.wire


def test_deadline_stats_quantiles_and_overruns_from_known_lateness():
    s = DeadlineStats(0.002)
    # 98 ticks 3 us late, one 150 us, one 3 ms late (with 0.1 ms compute: an overrun)
    for _ in range(98):
        s.add(3e-6, 1e-4)
    s.add(150e-6, 1e-4)
    s.add(3e-3, 1e-4)
    assert s.ticks == 100
    assert s.lateness_quantile_us(0.5) == 5.0        # bin (0, 5] us
    assert s.lateness_quantile_us(0.99) == 200.0     # the 99th tick is in (100, 200] us
    assert s.max_lateness_us == pytest.approx(3000.0)
    assert s.overruns == 1
    d = s.as_dict()
    assert d["histogram_us"]["5"] == 98 and d["compute_us_mean"] == pytest.approx(100.0)


def test_compute_longer_than_the_period_is_an_overrun():
    s = DeadlineStats(0.002)
    assert s.add(0.0, 0.0021) and not s.add(0.0, 0.0019)


async def test_lockstep_clock_steps_the_world_once_per_tick():
    steps = []
    c = LockStepClock(lambda: steps.append(1), 0.002)
    for _ in range(10):
        assert await c.wait_next() == 0.0
    assert len(steps) == 10 and c.now() == pytest.approx(0.02)


async def test_realtime_clock_keeps_absolute_deadlines_and_skips_missed_ones():
    t0 = time.perf_counter()               # before the clock's own start: t0 <= its t0
    c = RealTimeClock(0.002)
    lateness = [await c.wait_next() for _ in range(20)]
    # never early, and the 20th deadline is 40 ms after start (absolute schedule: no drift)
    assert min(lateness) >= 0.0
    assert time.perf_counter() - t0 >= 0.040
    time.sleep(0.011)  # noqa: ASYNC251 - a deliberate stall of 5.5 periods: at least 4 deadlines are skipped
    await c.wait_next()
    assert c.skipped >= 4


def test_period_out_of_range_is_refused_with_field_and_limit():
    with pytest.raises(ConfigError) as e:
        RealTimeClock(0.5)
    assert "control.period_s" in str(e.value) and "0.1" in str(e.value)


@pytest.mark.skipif(deadline_timer() is None, reason="no timerfd on this system")
async def test_the_kernel_timer_wakes_at_the_deadline_without_spinning():
    """Waiting on the timerfd: never early, and the loop sleeps meanwhile (the process uses
    a small part of the CPU time that passes, where spinning used all of it)."""
    cpu0, t0 = time.process_time(), time.perf_counter()
    c = RealTimeClock(0.002)                                       # starts after t0
    assert c.kernel_timer
    lateness = [await c.wait_next() for _ in range(250)]          # 0.5 s
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    assert min(lateness) >= 0.0 and wall >= 0.5
    assert cpu < 0.5 * wall, (cpu, wall)
    spin = RealTimeClock(0.002, timer=False)
    assert not spin.kernel_timer
    cpu0, t0 = time.process_time(), time.perf_counter()
    for _ in range(250):
        await spin.wait_next()
    assert time.process_time() - cpu0 > cpu                          # it spun


@pytest.mark.skipif(deadline_timer() is None, reason="no timerfd on this system")
async def test_a_cancelled_wait_does_not_wake_the_next_one_early():
    """The descriptor stays registered between waits: the expiry of a wait that was
    cancelled, whose callback the loop has already queued, must not end the next wait
    before its own deadline (nor leave it waiting for ever)."""
    timer = deadline_timer()
    try:
        first = asyncio.ensure_future(timer.wait_until(time.perf_counter() + 0.001))
        await asyncio.sleep(0)                                   # armed, waiting
        time.sleep(0.003)  # noqa: ASYNC251 - the loop held past its expiry on purpose
        await asyncio.sleep(0)        # the loop sees it: its callback queued behind this task
        first.cancel()
        due = time.perf_counter() + 0.02
        async with asyncio.timeout(1.0):                         # (entered in this step)
            await timer.wait_until(due)
        assert time.perf_counter() >= due
        again = time.perf_counter() + 0.005                       # and the timer still works
        async with asyncio.timeout(1.0):
            await timer.wait_until(again)
        assert time.perf_counter() >= again
    finally:
        timer.close()


@pytest.mark.skipif(deadline_timer() is None, reason="no timerfd on this system")
def test_one_timer_waits_in_successive_event_loops():
    """A clock outlives an event loop (a session's procedure after another): its timer
    registers itself with whichever loop waits on it."""
    timer = deadline_timer()
    try:
        for _ in range(3):
            due = time.perf_counter() + 0.003
            asyncio.run(timer.wait_until(due))
            assert time.perf_counter() >= due
    finally:
        timer.close()


@pytest.mark.skipif(deadline_timer() is None, reason="no timerfd on this system")
async def test_a_timer_nobody_keeps_leaves_the_loop_and_releases_its_descriptor():
    """Registered with the loop between waits, a timer is still collected once its clock is
    gone (a session makes a clock per procedure in one long-lived loop): it is taken out of
    the loop and its descriptor closed."""
    loop = asyncio.get_running_loop()
    timer = deadline_timer()
    fd = timer.fd
    await timer.wait_until(time.perf_counter() + 0.001)
    del timer
    gc.collect()
    assert loop.remove_reader(fd) is False                      # no longer watched
    with pytest.raises(OSError):
        os.fstat(fd)                                              # and closed


async def test_the_timer_serves_other_tasks_while_it_waits():
    """A task scheduled during the wait runs before the deadline (the loop is not blocked)."""
    c = RealTimeClock(0.01)
    seen = []

    async def other():
        await asyncio.sleep(0.002)
        seen.append(time.perf_counter())

    task = asyncio.ensure_future(other())
    await c.wait_next()
    t_tick = time.perf_counter()
    await task
    assert seen and seen[0] < t_tick


async def test_lockstep_ticks_left_and_steps_taken_by_their_owner():
    steps: list[int] = []
    held = LockStepClock(lambda: steps.append(1), 0.002, held=True)
    assert held.ticks_left() == 0
    held.grant(5)
    assert held.ticks_left() == 5
    held.stepped(3)                       # three steps taken by someone else
    assert held.ticks_left() == 2 and held.now() == pytest.approx(0.006) and not steps
    await held.wait_next()                # the clock's own step
    assert held.ticks_left() == 1 and steps == [1]
    held.halt()
    assert held.ticks_left() == 0
    free = LockStepClock(lambda: None, 0.002)
    assert free.ticks_left() == float("inf")
    assert LockStepClock(lambda: None, 0.002, paced=True).ticks_left() == 0


async def test_lockstep_clock_serves_the_other_tasks_every_ten_ticks_and_after_bulk_steps():
    clock = LockStepClock(lambda: None, 0.002, yield_every=10)
    turns = [0]

    async def other():
        while True:
            turns[0] += 1
            await asyncio.sleep(0)
    task = asyncio.create_task(other())
    await asyncio.sleep(0)
    served = []
    for _ in range(30):                   # tick by tick: a turn every ten ticks
        before = turns[0]
        await clock.wait_next()
        served.append(turns[0] > before)
    assert served.count(True) == 3 and served[9] and served[19] and served[29]
    for n in (256, 37, 25):               # many ticks stepped at once: a turn after each
        clock.stepped(n)
        before = turns[0]
        await clock.wait_next()
        assert turns[0] > before
    task.cancel()


def test_lockstep_stats_in_bulk():
    s = DeadlineStats(0.002, deadlines=False)
    s.add_lockstep(100, 0.001)
    d = s.as_dict()
    assert d["ticks"] == 100 and d["overruns"] == 0
    assert d["compute_us_mean"] == pytest.approx(10.0) and d["lateness_us_max"] == 0.0


async def test_the_gate_says_when_its_next_waiter_is_due_and_counts_ticks_run_elsewhere():
    from dentibot.runtime.gate import TickGate

    gate = TickGate()
    gate.open(object())
    assert gate.ticks_to_next_waiter() is None
    woken: list[str] = []
    fut = gate.wait(lambda rt: False, 10)
    gate.call_after(4, lambda: woken.append("pedal up"))
    gate.wait(lambda rt: False)               # no tick count: not due by ticks
    assert gate.ticks_to_next_waiter() == 4
    gate.skip(3)                              # three ticks ran in one compiled call
    assert gate.ticks_to_next_waiter() == 1
    gate.after_tick()                         # the fourth: the pedal is released
    assert woken == ["pedal up"] and gate.ticks_to_next_waiter() == 6
    fut.cancel()                              # a cancelled wait is no longer due
    assert gate.ticks_to_next_waiter() is None


_CPUS = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
needs_two_cpus = pytest.mark.skipif(len(_CPUS) < 2, reason="needs CPU affinity and 2 CPUs")


@needs_two_cpus
def test_pinning_keeps_every_thread_to_the_cpus_and_gives_each_its_own_back():
    """Linux sets CPU affinity per thread: a helper thread started before the block (a
    driver's receiver) is kept to the CPUs as well; each thread's own set comes back."""
    last = _CPUS[-1]
    ready, done = threading.Event(), threading.Event()
    tid: list[int] = []

    def helper():
        tid.append(threading.get_native_id())
        ready.set()
        done.wait(5.0)

    t = threading.Thread(target=helper)
    t.start()
    ready.wait(5.0)
    try:
        os.sched_setaffinity(tid[0], {_CPUS[0]})             # its own set, not the process's
        with pinned((last,)):
            assert os.sched_getaffinity(0) == {last}
            assert os.sched_getaffinity(tid[0]) == {last}
        assert os.sched_getaffinity(0) == set(_CPUS)
        assert os.sched_getaffinity(tid[0]) == {_CPUS[0]}
    finally:
        done.set()
        t.join()


@pytest.mark.skipif(not _CPUS, reason="no CPU affinity on this system")
def test_cpus_are_checked_against_those_the_process_may_use():
    assert check_cpus("control.cpus", None) is None
    assert check_cpus("control.cpus", [_CPUS[-1], _CPUS[0], _CPUS[0]]) == \
        tuple(sorted({_CPUS[0], _CPUS[-1]}))
    import numpy as np
    assert check_cpus("control.cpus", [np.int64(_CPUS[-1])]) == (_CPUS[-1],)
    for bad in ([max(_CPUS) + 1], [-1], [], [True], ["x"], [str(_CPUS[0])],
                [float(_CPUS[0])], "01", 1):
        with pytest.raises(ConfigError) as e:
            check_cpus("control.cpus", bad)
        msg = str(e.value)
        assert "control.cpus" in msg and str(_CPUS) in msg, msg
    with pytest.raises(ConfigError, match="control.cpus"):
        RuntimeConfig(cpus=(max(_CPUS) + 1,))


@needs_two_cpus
async def test_a_real_time_run_is_kept_to_its_cpus_while_it_ticks():
    """``control.cpus`` in force while the control task ticks in real time (the built-in
    simulator paced at the real world's speed), and the process's own set back after."""
    last = _CPUS[-1]
    seen: list[set[int]] = []
    proc = Procedure.simulated(WorldConfig(seed=1), time="paced")
    proc.runtime.cfg = dataclasses.replace(proc.runtime.cfg, cpus=(last,))
    proc.runtime.on_tick = lambda rt: seen.append(os.sched_getaffinity(0))
    async with proc:
        await proc.run_for(0.05)
    assert seen and all(s == {last} for s in seen)
    assert os.sched_getaffinity(0) == set(_CPUS)


@pytest.mark.skipif(deadline_timer() is None, reason="no timerfd on this system")
async def test_the_waiter_runs_before_the_streams_that_became_ready_after_its_deadline():
    """The deadline first: when the timer's expiry and a stream's data are seen in the same
    turn of the loop, the waiting task (the tick) resumes before the stream's callback,
    which still runs right after it."""
    import socket

    loop = asyncio.get_running_loop()
    timer = deadline_timer()
    a, b = socket.socketpair()
    order: list[str] = []

    def on_data() -> None:
        b.recv(16)
        order.append("stream")

    loop.add_reader(b.fileno(), on_data)
    try:
        async def tick() -> None:
            await timer.wait_until(due)
            order.append("tick")

        due = time.perf_counter() + 0.005
        waiter = asyncio.ensure_future(tick())
        await asyncio.sleep(0)                                   # armed, waiting
        time.sleep(0.01)   # noqa: ASYNC251 - the loop held: the timer expires first ...
        a.send(b"x")       # ... then the stream's data arrive, both seen in one turn
        async with asyncio.timeout(1.0):
            await waiter
            while len(order) < 2:
                await asyncio.sleep(0)
        assert order == ["tick", "stream"]
    finally:
        loop.remove_reader(b.fileno())
        a.close()
        b.close()
        timer.close()
