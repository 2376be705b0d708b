"""What the experiments share besides running (:mod:`dentibot.app.batch`): summarising
populations and the thesis's claims checked."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any


def distribution(values: Iterable[float | None], worst: str = "max") -> dict[str, Any]:
    """Median, worst case (``"max"`` or ``"min"`` is the worst), best case and count of the
    finite values; None for each figure when there is none."""
    vals = sorted(float(v) for v in values if v is not None and math.isfinite(float(v)))
    if not vals:
        return {"median": None, "worst": None, "best": None, "n": 0}
    n = len(vals)
    median = vals[n // 2] if n % 2 else 0.5 * (vals[n // 2 - 1] + vals[n // 2])
    hi, lo = vals[-1], vals[0]
    return {"median": median, "worst": hi if worst == "max" else lo,
            "best": lo if worst == "max" else hi, "n": n}


@dataclass(frozen=True)
class Check:
    """One of the thesis's claims for an experiment, and whether this run shows it."""

    claim: str
    passed: bool
    detail: str

    def to_dict(self) -> dict:
        return {"claim": self.claim, "passed": self.passed, "detail": self.detail}
