"""The control task's clocks (docs/architecture.md, "Time") and its deadline accounting.

- :class:`RealTimeClock`: absolute deadlines ``t0 + k * period``. It waits on a kernel timer
  armed at the deadline (Linux ``timerfd``, watched by the event loop), so the loop keeps
  serving the device streams while it waits, sleeps, and wakes within microseconds; it
  wakes a little early and spins to the deadline without yielding, so that no stream's
  callback runs between the deadline and the tick (they run in the slack after it); without
  one it sleeps coarsely with ``asyncio.sleep`` until ``spin_s`` before the deadline, then
  yields to the loop (``asyncio.sleep(0)``) until the deadline passes. Plain
  ``asyncio.sleep(period)`` rounds its timeout up to whole milliseconds (epoll), which at
  500 Hz is most of a period.
  A tick that starts more than a whole period late is counted as missed and the schedule
  skips ahead (no burst of catch-up ticks).
- :class:`LockStepClock`: simulated time; ``wait_next`` steps the world by exactly one period
  and is never late. Free running (as fast as the machine allows), ``paced`` (also waits for
  each tick's wall-clock deadline: the built-in simulator at the speed of the real world) or
  ``held`` (time passes only by the ticks granted to it: a procedure driven by its steps, or a
  test driving a session's time separately from its terminal).
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import gc
import math
import operator
import os
import threading
import time
from collections.abc import Awaitable, Callable

from dentibot.errors import ConfigError
from dentibot.runtime.deadline_timer import deadline_timer

#: the kernel timer wakes the loop this long before the deadline, which it then reaches by
#: spinning: a thread's wake-up takes tens of microseconds (timer slack, scheduling). Not by
#: yielding to the loop: each yield let the streams' callbacks that had just become ready
#: run first (measured at 500 Hz under load: 5.4 resumptions per tick, p99 lateness 140-210
#: us and 1-7 overruns a minute; spinning: p99 125 us and none in the same conditions)
_WAKE_EARLY_S = 100e-6

#: Upper edges (us) of the lateness histogram bins; the last bin is open.
LATENESS_BINS_US = (5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000, 20000, 50000)


class DeadlineStats:
    """Lateness histogram, overruns and compute time of the control task.

    An overrun is a tick that did not finish before the next deadline (lateness + compute time
    > period), or a deadline skipped entirely.
    """

    def __init__(self, period_s: float, deadlines: bool = True) -> None:
        self.period_s = period_s
        self.deadlines = deadlines   # False in lock-step time: nothing can overrun
        self.reset()

    def reset(self) -> None:
        self.ticks = 0
        self.overruns = 0
        self.skipped = 0
        self.max_lateness_us = 0.0
        self.max_compute_us = 0.0
        self.hist = [0] * (len(LATENESS_BINS_US) + 1)
        self._compute_sum_us = 0.0

    def add(self, lateness_s: float, compute_s: float) -> bool:
        """Account one tick; returns True when it overran."""
        late_us = max(lateness_s, 0.0) * 1e6
        comp_us = compute_s * 1e6
        self.ticks += 1
        self.hist[bisect.bisect_left(LATENESS_BINS_US, late_us)] += 1
        self.max_lateness_us = max(self.max_lateness_us, late_us)
        self.max_compute_us = max(self.max_compute_us, comp_us)
        self._compute_sum_us += comp_us
        over = self.deadlines and lateness_s + compute_s > self.period_s
        self.overruns += over
        return over

    def add_lockstep(self, ticks: int, compute_s: float) -> None:
        """Account ``ticks`` ticks of lock-step time, on time by definition, that took
        ``compute_s`` together (the simulator's compiled ticks)."""
        comp_us = compute_s * 1e6 / ticks
        self.ticks += ticks
        self.hist[0] += ticks
        self.max_compute_us = max(self.max_compute_us, comp_us)
        self._compute_sum_us += compute_s * 1e6

    def lateness_quantile_us(self, q: float) -> float:
        """Upper edge of the histogram bin holding quantile ``q`` (a bound, not an estimate)."""
        if not self.ticks:
            return 0.0
        need = math.ceil(q * self.ticks)
        seen = 0
        for i, n in enumerate(self.hist):
            seen += n
            if seen >= need:
                return float(LATENESS_BINS_US[i]) if i < len(LATENESS_BINS_US) \
                    else self.max_lateness_us
        return self.max_lateness_us

    def as_dict(self) -> dict:
        return {
            "ticks": self.ticks, "overruns": self.overruns, "skipped": self.skipped,
            "lateness_us_p50": self.lateness_quantile_us(0.5),
            "lateness_us_p99": self.lateness_quantile_us(0.99),
            "lateness_us_max": self.max_lateness_us,
            "compute_us_mean": self._compute_sum_us / self.ticks if self.ticks else 0.0,
            "compute_us_max": self.max_compute_us,
            "histogram_us": dict(zip([*map(str, LATENESS_BINS_US), "inf"], self.hist)),
        }


class Clock:
    """``now()`` (s since start) and ``wait_next()`` -> lateness of the new tick (s)."""

    period_s: float
    #: True when ticks have deadlines in wall-clock time (lateness and overruns mean something).
    realtime: bool = True
    #: True when its deadlines are waited for on the kernel's timer (the loop sleeps)
    kernel_timer: bool = False

    def start(self) -> None:
        raise NotImplementedError

    def now(self) -> float:
        raise NotImplementedError

    async def wait_first(self) -> None:
        """Called once before the first tick (which is not waited for)."""

    async def wait_next(self) -> float:
        raise NotImplementedError


def _check_period(period_s: float) -> float:
    if not 0.0002 <= period_s <= 0.1:
        raise ConfigError("control.period_s", period_s, "0.0002..0.1 s (10..5000 Hz)")
    return float(period_s)


class RealTimeClock(Clock):
    """Absolute deadlines ``t0 + k * period`` on ``clock``. On Linux with the monotonic clock
    (``time.perf_counter``, the default) it waits on a kernel timer armed at the deadline
    (:class:`~dentibot.runtime.deadline_timer.DeadlineTimer`): the event loop sleeps,
    serving the device streams, and wakes within microseconds of the deadline, leaving the
    CPU to everything else meanwhile; the last ``_WAKE_EARLY_S`` it spins. Elsewhere (or
    ``timer=False``) it sleeps coarsely and spins the last ``spin_s``."""

    def __init__(self, period_s: float = 0.002, spin_s: float = 0.0015,
                 clock: Callable[[], float] = time.perf_counter, timer: bool = True) -> None:
        self.period_s = _check_period(period_s)
        self.spin_s = min(spin_s, period_s)
        self._clock = clock
        self.skipped = 0
        self._timer = deadline_timer() \
            if timer and clock in (time.perf_counter, time.monotonic) else None
        self.start()

    @property
    def kernel_timer(self) -> bool:  # type: ignore[override]
        """True when deadlines are waited for on the kernel's timer (no spinning)."""
        return self._timer is not None

    def start(self) -> None:
        self._t0 = self._clock()
        self._k = 0

    def now(self) -> float:
        return self._clock() - self._t0

    async def wait_next(self) -> float:
        self._k += 1
        p = self.period_s
        deadline = self._t0 + self._k * p
        now = self._clock()
        if now - deadline >= p:                 # a whole period late: skip ahead
            missed = int((now - deadline) / p)
            self.skipped += missed
            self._k += missed
            deadline += missed * p
        if self._timer is not None:
            if deadline - now > _WAKE_EARLY_S:
                await self._timer.wait_until(deadline - _WAKE_EARLY_S)
            clock = self._clock
            while clock() < deadline:            # the last microseconds, if any
                pass
            return clock() - deadline
        coarse = deadline - self.spin_s - now
        if coarse > 0.0:
            await asyncio.sleep(coarse)
        while self._clock() < deadline:
            await asyncio.sleep(0)
        return self._clock() - deadline


class LockStepClock(Clock):
    """Simulated time: ``step()`` advances the world by one period per tick.

    ``paced``: each tick then also waits for its wall-clock deadline (a
    :class:`RealTimeClock`'s waiting): the built-in simulator at the speed of the real world,
    e.g. for an interactive session; ticks then have deadlines (``realtime``).

    ``held``: no tick runs until ticks are granted (``grant(n)``); ``hold()`` takes back what is
    left, ``release()`` lets ticks run freely from then on. While held, ``wait_next`` awaits
    ``serve()`` whenever it is woken (``wake()``): the owner does the work submitted between
    two ticks there (see :class:`~dentibot.runtime.gate.TickGate`). ``halt()`` makes a held
    ``wait_next`` return without stepping (the loop is being stopped).
    """

    def __init__(self, step: Callable[[], None], period_s: float = 0.002,
                 yield_every: int = 10, *, paced: bool = False, held: bool = False) -> None:
        self.period_s = _check_period(period_s)
        self._step = step
        self._yield_every = max(1, int(yield_every))
        self._pace = RealTimeClock(period_s) if paced else None
        self.realtime = paced
        self.skipped = 0
        self._credits = 0.0 if held else math.inf
        self._wake: asyncio.Event | None = None
        self._halted = False
        #: awaited while held, each time the clock is woken
        self.serve: Callable[[], Awaitable[None]] | None = None
        self.start()

    @property
    def kernel_timer(self) -> bool:  # type: ignore[override]
        """Paced on the kernel's timer (a held or free-running clock has no deadlines)."""
        return self._pace is not None and self._pace.kernel_timer

    def start(self) -> None:
        self._k = 0
        self._next_yield = self._yield_every
        self._halted = False
        if self._pace is not None:
            self._pace.start()

    def now(self) -> float:
        return self._k * self.period_s

    # ------------------------------------------------------------ holding
    @property
    def held(self) -> bool:
        """True while no tick may run (nothing granted)."""
        return self._credits <= 0

    def grant(self, ticks: int) -> None:
        self._credits += ticks
        self.wake()

    def hold(self) -> None:
        """No more ticks until the next grant (unless released)."""
        if self._credits != math.inf:
            self._credits = 0

    def release(self) -> None:
        self._credits = math.inf
        self.wake()

    def wake(self) -> None:
        if self._wake is not None:
            self._wake.set()

    def halt(self) -> None:
        self._halted = True
        self.wake()

    async def _granted(self) -> bool:
        """Wait (serving) until a tick is granted; False when halted meanwhile."""
        while self._credits <= 0:
            if self._halted:
                return False
            if self._wake is None:
                self._wake = asyncio.Event()
            self._wake.clear()
            if self.serve is not None:
                await self.serve()
            if self._credits <= 0 and not self._halted:
                await self._wake.wait()
        return True

    def ticks_left(self) -> float:
        """Ticks that may run now without a wait: the granted ticks left (infinite when
        released), 0 when halted or paced (a paced tick waits for its deadline)."""
        if self._halted or self._pace is not None:
            return 0
        return max(self._credits, 0)

    def stepped(self, ticks: int) -> None:
        """``ticks`` granted ticks' steps were taken by their owner (the compiled drilling
        loop steps the world between its ticks itself)."""
        self._credits -= ticks
        self._k += ticks

    async def wait_first(self) -> None:
        """Before the first tick: held, it takes a granted tick too (no world step)."""
        if await self._granted():
            self._credits -= 1

    async def wait_next(self) -> float:
        if not await self._granted():
            return 0.0
        self._credits -= 1
        self._step()
        self._k += 1
        if self._pace is not None:
            lateness = await self._pace.wait_next()
            self.skipped = self._pace.skipped
            return lateness
        if self._k >= self._next_yield:
            # let the other tasks (UI, operator commands) run: every ``yield_every`` ticks,
            # and after each call of the compiled drilling ticks (which steps many at once)
            self._next_yield = self._k + self._yield_every
            await asyncio.sleep(0)
        return 0.0


#: Nice value the real-time control loop asks for when it cannot have a real-time policy: ahead
#: of every ordinary job on the machine (their 0), behind the kernel's own threads.
REALTIME_NICE = -10
#: SCHED_FIFO priority of a control loop that waits on the kernel timer: low among real-time
#: threads (the kernel's interrupt threads run at 50), above every ordinary job.
REALTIME_FIFO_PRIORITY = 10
#: SCHED_FIFO priority of the wire simulators where permitted (``dentibot sim serve``, the
#: wire self-test's simulators): ahead of every ordinary job, as the hardware they stand for
#: never stalls, and one below a control loop, whose deadlines come first on a shared machine
SIMULATOR_FIFO_PRIORITY = REALTIME_FIFO_PRIORITY - 1


@contextlib.contextmanager
def raised_priority(nice: int = REALTIME_NICE, fifo_priority: int | None = None,
                    threads_inherit: bool = False):
    """The calling thread's scheduling raised while the block runs, where the system permits
    (CAP_SYS_NICE: root, or the ``RLIMIT_RTPRIO``/``RLIMIT_NICE`` a robot cell's account is
    given); yields how: ``"fifo"`` (SCHED_FIFO at ``fifo_priority``), ``"nice"`` (the nice
    value ``nice``) or ``""`` (neither permitted: the thread runs as it is). Restored on exit.
    Linux sets these per thread: the recorder's and the UI's threads keep theirs.

    Why: on a machine loaded by other jobs a control loop at their priority shares its core
    with them, and its 2 ms deadlines slip by a scheduler slice (milliseconds); the device
    streams then go stale. SCHED_FIFO only for a loop that sleeps between ticks
    (:class:`RealTimeClock` on the kernel timer): a real-time thread that spun would take a
    core from everything else.

    The threads and processes the thread starts get the ordinary policy (SCHED_RESET_ON_FORK),
    unless ``threads_inherit``: a process whose threads all serve its loop (the wire
    simulators) lets them inherit SCHED_FIFO, so that none of them is preempted by an
    ordinary job while it holds the interpreter lock."""
    if fifo_priority is not None and hasattr(os, "sched_setscheduler"):
        try:
            policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
            reset = 0 if threads_inherit else getattr(os, "SCHED_RESET_ON_FORK", 0)
            os.sched_setscheduler(0, os.SCHED_FIFO | reset, os.sched_param(fifo_priority))
        except OSError:                         # not permitted (or no RT time): try nice
            pass
        else:
            try:
                yield "fifo"
            finally:
                with contextlib.suppress(OSError):
                    os.sched_setscheduler(0, policy, param)
            return
    try:
        before = os.getpriority(os.PRIO_PROCESS, 0)
    except (AttributeError, OSError):          # no such call on this platform
        yield ""
        return
    granted = False
    if nice < before:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
            granted = True
        except OSError:                         # not permitted: run as we are
            pass
    try:
        yield "nice" if granted or nice >= before else ""
    finally:
        if granted:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, 0, before)


def _thread_ids() -> list[int]:
    """The native ids of this process's threads (Linux ``/proc/self/task``); empty where
    the system does not list them."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return []


@contextlib.contextmanager
def others_raised(nice: int = REALTIME_NICE, fifo_priority: int | None = None):
    """The process's other threads (the drivers' receivers, the recorder's writer) raised
    while the block runs, where permitted (Linux: per thread, from ``/proc/self/task``):
    to SCHED_FIFO at ``fifo_priority`` when given (the control thread's own), else (or where
    that is refused) to the nice value ``nice``; restored on exit. Why: every thread of the
    process takes the interpreter lock, and a thread that holds it when something of higher
    priority preempts it stalls the raised control thread until it runs again. At a nice
    value it still yields its core to other raised processes (such as the wire simulators
    where they could not have a real-time policy) and the control thread waits a scheduler
    slice or more for the lock.
    On the wire at 500 Hz with one CPU-bound job beside, 60 s: with the receivers at nice
    -10, 12 and 30 overruns, stalls of 14 and 53 ms; at the loop's real-time priority, 3
    overruns and 5.9 ms, where a bare loop on the same machine had 5 and 9.4 ms. At the
    control thread's own real-time priority nothing below it preempts the lock's holder. These threads sleep on
    their sockets between frames, so at SCHED_FIFO they take no more of the core than
    before."""
    me = threading.get_native_id()
    before: dict[int, tuple[str, object]] = {}
    tids = _thread_ids()
    fifo = fifo_priority is not None and hasattr(os, "sched_setscheduler")
    for tid in tids:
        if tid == me:
            continue
        if fifo:
            try:
                was = (os.sched_getscheduler(tid), os.sched_getparam(tid))
                os.sched_setscheduler(tid, os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0),
                                      os.sched_param(fifo_priority))
                before[tid] = ("fifo", was)
                continue
            except OSError:                     # gone, or not permitted: try nice
                pass
        try:
            was_nice = os.getpriority(os.PRIO_PROCESS, tid)
            if nice < was_nice:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
                before[tid] = ("nice", was_nice)
        except OSError:                         # gone, or not permitted
            pass
    try:
        yield
    finally:
        for tid, (how, was) in before.items():
            with contextlib.suppress(OSError):
                if how == "fifo":
                    os.sched_setscheduler(tid, was[0], was[1])
                else:
                    os.setpriority(os.PRIO_PROCESS, tid, was)


def check_cpus(field: str, cpus) -> tuple[int, ...] | None:
    """``cpus`` (CPU numbers, or None) as a sorted tuple, each one a CPU this process may run
    on; else a :class:`~dentibot.errors.ConfigError` naming ``field``, the value and the CPUs
    there are (raised before anything runs)."""
    if cpus is None:
        return None
    allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    items = () if isinstance(cpus, str | bytes) else cpus
    try:                     # integers only (numpy's too): not a float, not "1"
        chosen = tuple(sorted({operator.index(c) for c in items}))
    except TypeError:        # (a single number is not a collection of them either)
        chosen = ()
    if not chosen or any(isinstance(c, bool) for c in items) or allowed is None \
            or not set(chosen) <= set(allowed):
        where = "no CPU affinity on this system" if allowed is None else \
            f"one or more of this machine's CPUs the process may use: {allowed}"
        raise ConfigError(field, cpus, where)
    return chosen


@contextlib.contextmanager
def pinned(cpus: tuple[int, ...] | None):
    """Every thread of the process (and those it starts meanwhile, which inherit it) kept to
    ``cpus`` while the block runs; each thread's own set restored on exit. Linux sets CPU
    affinity per thread, so each one of ``/proc/self/task`` is set. Why: a control loop on a
    core of its own (one the kernel keeps other jobs off, ``isolcpus``, or simply one the
    simulators are not on) is not queued behind them, and its caches stay warm; the
    standard practice for a real-time loop. None: nothing changes."""
    if cpus is None or not hasattr(os, "sched_setaffinity"):
        yield
        return
    before: dict[int, set[int]] = {}
    for tid in _thread_ids() or [0]:             # (0: the calling thread alone)
        try:
            was = os.sched_getaffinity(tid)
            os.sched_setaffinity(tid, cpus)
            before[tid] = was
        except OSError:                          # gone meanwhile
            pass
    try:
        yield
    finally:
        for tid, was in before.items():
            with contextlib.suppress(OSError):
                os.sched_setaffinity(tid, was)


@contextlib.contextmanager
def realtime_policy(clock: Clock, cpus: tuple[int, ...] | None = None):
    """The control loop's policy under ``clock``. In real time: the thread's priority raised
    (:func:`raised_priority`: SCHED_FIFO when the clock waits on the kernel timer, else a
    nice value), the process's other threads raised with it (:func:`others_raised`: to its
    real-time priority when it has one, else to the nice value), and the garbage collector
    kept out of ticks, and the process kept to ``cpus`` when given (:func:`pinned`). Yields
    ``collect(n)`` to call in the slack after tick ``n``.

    In real time the cyclic collector runs only there (young generation every 50 ticks, older
    every 5000), never in the middle of a tick: a full collection triggered by allocation can
    take milliseconds (tens with the simulators in the same process). Objects alive at the
    start are frozen out of the collector's sight (``gc.freeze``, which collects nothing
    itself). In lock-step time nothing changes.
    """
    if not clock.realtime:
        yield lambda n: None
        return
    was_enabled = gc.isenabled()
    gc.freeze()
    gc.disable()

    def collect(n: int) -> None:
        if n % 50 == 0:
            gc.collect(1 if n % 5000 == 0 else 0)

    try:
        fifo = REALTIME_FIFO_PRIORITY if clock.kernel_timer else None
        with pinned(cpus), raised_priority(fifo_priority=fifo) as how, \
                others_raised(fifo_priority=fifo if how == "fifo" else None):
            yield collect
    finally:
        gc.unfreeze()
        if was_enabled:
            gc.enable()
