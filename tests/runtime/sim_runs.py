"""Helpers for lock-step runs of the runtime on the built-in simulator."""

from __future__ import annotations

from dentibot.runtime.config import RuntimeConfig, TreatmentPlan
from dentibot.app.simulated import SimHarness
from dentibot.sim.world import WorldConfig

GAP_MM = 2.0  # the world's default orifice gap: the file tip starts 2 mm above the orifice


def harness(seed=1, canal=None, motion="static", plan=None, **kw) -> tuple[SimHarness, list]:
    rows: list[dict] = []
    wc = WorldConfig(seed=seed, motion=motion, **({"canal": canal} if canal else {}))
    plan = plan or TreatmentPlan(orifice_gap_mm=GAP_MM)
    h = SimHarness(wc, RuntimeConfig(plan=plan), sink=rows.append, **kw)
    return h, rows


def finished(rt) -> bool:
    return rt.state in ("done", "fault")
