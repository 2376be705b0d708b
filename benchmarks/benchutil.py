"""Helpers shared by the benchmarks: timing loops, percentiles, a description of the machine.

The benchmark scripts run from a checkout (``python benchmarks/run.py``); ``benchmarks/`` is
not a package, so each script puts its own folder on ``sys.path`` and imports its siblings by
plain name (``import benchutil``).
"""

from __future__ import annotations

import os
import platform
import sys
import time
from collections.abc import Callable, Sequence

import numpy as np


def timeit_us(fn: Callable[[], object], n: int, warmup: int = 200) -> np.ndarray:
    """Per-call wall times (us) of ``fn()``, ``n`` calls after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    out = np.empty(n)
    clock = time.perf_counter_ns
    for i in range(n):
        t0 = clock()
        fn()
        out[i] = clock() - t0
    return out / 1000.0


def dist_us(samples: Sequence[float] | np.ndarray) -> dict:
    """n, median, p99, max of a sample (same unit as the samples, named ``*_us``)."""
    a = np.asarray(samples, dtype=float)
    if a.size == 0:
        return {"n": 0, "median_us": None, "p99_us": None, "max_us": None}
    return {"n": int(a.size), "median_us": float(np.median(a)),
            "p99_us": float(np.percentile(a, 99)), "max_us": float(a.max())}


def quantiles(samples: Sequence[float] | np.ndarray, qs=(50, 99, 99.9)) -> dict:
    """``{"p50": .., "p99": .., "p99.9": .., "max": ..}`` of a sample (None when empty)."""
    a = np.asarray(samples, dtype=float)
    if a.size == 0:
        return {**{f"p{q:g}": None for q in qs}, "max": None}
    return {**{f"p{q:g}": float(np.percentile(a, q)) for q in qs}, "max": float(a.max())}


def load_average() -> list[float] | None:
    """1, 5 and 15 minute load averages (None where the OS has none)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (OSError, AttributeError):
        return None


def machine() -> dict:
    """What ran the benchmark: CPU model, cores, Python and numpy versions."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": sys.version.split()[0],
            "numpy": np.__version__, "platform": platform.platform()}


def fmt(x, spec: str = ".1f", none: str = "-") -> str:
    """``format(x, spec)``, or ``none`` for a missing figure."""
    return none if x is None else format(x, spec)
