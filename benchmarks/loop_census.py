"""What the control process's event loop runs, callback by callback (``realtime_loop.py
--census``).

A real-time loop overruns when its work of one period, not only its tick, outlasts the
period: between two ticks the same thread parses the four devices' streams, runs the
drive's SYNC cycle and polls the Modbus I/O. While the block runs, every callback the event
loop runs is timed and counted under a name: the task it resumes (``task: <name>``), the
protocol whose socket was readable (``read: <protocol class>``), or the function called.
Per name, :func:`figures` gives the calls per tick, the p50 and the time per tick; their
sum against the tick's own time says how much of the period the streams take.

The timer adds about a microsecond per callback.
"""

from __future__ import annotations

import statistics
import time
from asyncio import events
from contextlib import contextmanager

#: What resumes a task: the wake-up of an awaited future, a step (C tasks: a wrapper with no
#: qualified name of its own)
_TASK_STEPS = ("Task.task_wakeup", "Task.__step", "TaskStepMethWrapper")


def callback_name(cb) -> str:
    """A callback's name in the census: the task a wake-up resumes, the protocol a socket's
    readiness feeds, else the callable's qualified name."""
    owner = getattr(cb, "__self__", None)
    name = getattr(cb, "__qualname__", None) or type(cb).__name__
    if name in _TASK_STEPS and owner is not None:
        return f"task: {owner.get_name()}"
    if name.endswith("._read_ready") and owner is not None:
        protocol = getattr(owner, "_protocol", None)
        if protocol is not None:
            return f"read: {type(protocol).__qualname__}"
    return name


@contextmanager
def census():
    """Time every callback the event loop runs while the block runs; yields the record
    (name -> durations, s) that :func:`figures` reads."""
    times: dict[str, list[float]] = {}
    run = events.Handle._run
    clock = time.perf_counter

    def timed_run(handle) -> None:
        t = clock()
        run(handle)
        d = clock() - t
        name = callback_name(handle._callback)
        ts = times.get(name)
        if ts is None:
            ts = times[name] = []
        ts.append(d)

    events.Handle._run = timed_run
    try:
        yield times
    finally:
        events.Handle._run = run


def figures(times: dict[str, list[float]], ticks: int) -> dict:
    """Per name, largest time per tick first: ``calls_per_tick``, ``p50_us`` and
    ``us_per_tick`` over ``ticks`` ticks."""
    out = {}
    for name, ts in sorted(times.items(), key=lambda kv: -sum(kv[1])):
        out[name] = {"calls_per_tick": len(ts) / max(ticks, 1),
                     "p50_us": statistics.median(ts) * 1e6,
                     "us_per_tick": sum(ts) * 1e6 / max(ticks, 1)}
    return out


def print_figures(fig: dict, indent: str = "", top: int = 12) -> None:
    total = sum(f["us_per_tick"] for f in fig.values())
    for name, f in list(fig.items())[:top]:
        print(f"{indent}{name[:56]:>56}: {f['us_per_tick']:6.1f} us per tick "
              f"({f['calls_per_tick']:.2f} calls, p50 {f['p50_us']:.1f} us)")
    print(f"{indent}{'all callbacks':>56}: {total:6.1f} us per tick")
