"""Checks made every tick, independent of the state's control law.

Freshness: each stream's sequence number must advance within its bound (in control periods);
a stale stream is a fault, never a held value. Emergency stop (aux input). Values: a sample
with NaN/inf is a fault. Each finding names its cause, the value and the limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Finding:
    """A fault cause: ``kind`` (short key), ``detail`` (cause, value, limit)."""

    kind: str
    detail: str

    def __str__(self) -> str:
        return f"{self.kind}: {self.detail}"


class Freshness:
    """Tracks the last tick at which each stream's ``seq`` changed."""

    def __init__(self, bounds_periods: dict[str, int]) -> None:
        self.bounds = dict(bounds_periods)
        self._seq: dict[str, int] = {}
        self._tick: dict[str, int] = {}

    def reset(self) -> None:
        self._seq.clear()
        self._tick.clear()

    def check(self, name: str, seq: int, tick: int) -> Finding | None:
        last = self._seq.get(name)
        if last is None or seq != last:
            self._seq[name] = seq
            self._tick[name] = tick
            return None
        age = tick - self._tick[name]
        bound = self.bounds.get(name, 10)
        if age > bound:
            return Finding(f"stale_{name}",
                           f"{name} stream: seq {seq} unchanged for {age} periods "
                           f"(limit {bound})")
        return None


def non_finite(name: str, values) -> Finding | None:
    for i, v in enumerate(values):
        if not math.isfinite(v):
            return Finding(f"nonfinite_{name}", f"{name}[{i}] = {v} (must be finite)")
    return None
