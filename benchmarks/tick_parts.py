"""The real-time tick's parts timed where they run (``realtime_loop.py --parts``).

While the control loop runs, each part of the tick is wrapped in a timer: the devices' reads,
the supervisor's checks, the estimate and its compiled call, the arm's command and its
driver, the telemetry row. After the loop, the compiled calls are run again back to back with
the arguments of the loop's last tick (copies: the runtime's state is not touched), so that
the same call is timed twice: in place, as the loop pays for it, and hot. Their ratio is
what running once per period costs beyond the call's own work: between two ticks the core
serves other work and the tick's code and data have to come back.

The wrappers add about a microsecond per part; the figures are for comparing parts and the
two ways of calling, not for the tick's total (``compute_us`` is that).
"""

from __future__ import annotations

import functools
import inspect
import statistics
import time
from contextlib import contextmanager

import numpy as np

from dentibot.control import tick_kernels
from dentibot.io import meca500
from dentibot.runtime import control_task, estimate, supervisor
from dentibot.runtime import supervisor_kernels as sk

#: (owner, attribute, label) of each part timed in place
PARTS = (
    (control_task.Runtime, "tick", "whole tick"),
    (estimate.Devices, "read", "devices.read"),
    (supervisor.Supervisor, "check_inputs", "supervisor.check_inputs"),
    (control_task.Runtime, "_estimate", "estimate"),
    (supervisor.Supervisor, "observe", "supervisor.observe"),
    (supervisor.Supervisor, "check_estimate", "supervisor.check_estimate"),
    (control_task, "arm_command", "arm command"),
    (meca500.Meca500Driver, "_send", "arm driver: encode and write"),
    (control_task, "telemetry_row", "telemetry row"),
)
#: (module, kernel, label) of the compiled calls timed in place and hot
KERNELS = (
    (tick_kernels, "sense", "estimate's compiled call"),
    (sk, "inputs", "input checks' compiled call"),
    (sk, "estimate_checks", "estimate checks' compiled call"),
)
#: back-to-back calls of each kernel for its hot time
HOT_CALLS = 2000


def _timed(f, record, keep_args=None):
    """``f`` wrapped: each call's duration (s) to ``record``, and its positional arguments
    to ``keep_args`` when given (for the hot replay)."""
    if inspect.iscoroutinefunction(f):
        @functools.wraps(f)
        async def timed_async(*a, **k):
            t = time.perf_counter()
            try:
                return await f(*a, **k)
            finally:
                record(time.perf_counter() - t)
        return timed_async

    @functools.wraps(f)
    def timed(*a, **k):
        if keep_args is not None:
            keep_args(a)
        t = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            record(time.perf_counter() - t)
    return timed


@contextmanager
def timed_parts():
    """Time every part of :data:`PARTS` and every kernel of :data:`KERNELS` while the block
    runs; yields a dict that :func:`figures` reads afterwards."""
    times: dict[str, list[float]] = {}
    last_args: dict[str, tuple] = {}
    saved = []
    for owner, name, label in PARTS:
        saved.append((owner, name, getattr(owner, name)))
        setattr(owner, name, _timed(getattr(owner, name), times.setdefault(label, []).append))
    for module, name, label in KERNELS:
        saved.append((module, name, getattr(module, name)))
        setattr(module, name, _timed(getattr(module, name), times.setdefault(label, []).append,
                                     functools.partial(last_args.__setitem__, label)))
    state = {"times": times, "last_args": last_args}
    try:
        yield state
    finally:
        for owner, name, f in reversed(saved):
            setattr(owner, name, f)


def figures(state: dict, skip: int = 200) -> dict:
    """Per part: calls, p50 and mean (us) in place, leaving out the first ``skip`` calls;
    per kernel also its hot p50 and the ratio in place / hot."""
    out = {}
    for label, ts in state["times"].items():
        ts = ts[skip:] or ts
        if not ts:
            continue
        out[label] = {"n": len(ts), "p50_us": statistics.median(ts) * 1e6,
                      "mean_us": statistics.fmean(ts) * 1e6}
    for module, name, label in KERNELS:
        args = state["last_args"].get(label)
        if args is None or label not in out:
            continue
        f = getattr(module, name)
        args = tuple(a.copy() if isinstance(a, np.ndarray) else a for a in args)
        hot = []
        for _ in range(HOT_CALLS):
            t = time.perf_counter()
            f(*args)
            hot.append(time.perf_counter() - t)
        out[label]["hot_p50_us"] = statistics.median(hot) * 1e6
        out[label]["in_place_over_hot"] = out[label]["p50_us"] / out[label]["hot_p50_us"]
    return out


def print_figures(parts: dict, indent: str = "") -> None:
    for label, f in parts.items():
        hot = (f"; hot {f['hot_p50_us']:.1f} us, in place {f['in_place_over_hot']:.1f}x"
               if "hot_p50_us" in f else "")
        print(f"{indent}{label:>32}: p50 {f['p50_us']:6.1f} us, mean {f['mean_us']:6.1f} us "
              f"(n {f['n']}){hot}")
