"""Helpers for lock-step runs of the runtime on the built-in simulator, built by the public
test harness (:func:`dentibot.testing.simulated_procedure`)."""

from __future__ import annotations

from dentibot.app.procedure import Procedure
from dentibot.runtime.config import RuntimeConfig, TreatmentPlan
from dentibot.testing import simulated_procedure
from dentibot.sim.world import WorldConfig

GAP_MM = 2.0  # the world's default orifice gap: the file tip starts 2 mm above the orifice


def harness(seed=1, canal=None, motion="static", plan=None, **kw) -> tuple[Procedure, list]:
    wc = WorldConfig(seed=seed, motion=motion, **({"canal": canal} if canal else {}))
    plan = plan or TreatmentPlan(orifice_gap_mm=GAP_MM)
    proc = procedure(wc, RuntimeConfig(plan=plan), **kw)
    return proc, proc.rows


#: The procedures built by the running test (stopped at its end: tests/runtime/conftest.py).
MADE: list[Procedure] = []


def procedure(*args, **kw) -> Procedure:
    """:func:`dentibot.testing.simulated_procedure`, stopped at the end of the test."""
    proc = simulated_procedure(*args, **kw)
    MADE.append(proc)
    return proc


def finished(rt) -> bool:
    return rt.state in ("done", "fault")
