"""The simulator's compiled feeding ticks give the control task's outcome, number for
number: trial procedures run with them and without them (reversals, patient motion, faults,
a fracture in a compiled world step)."""

from __future__ import annotations

import pytest

import dentibot.app.drill_loop as dl
from dentibot.app import drill_kernels as dk
from dentibot.trials import runner as rn
from dentibot.trials.spec import parse_trial

#: Acrylic canals, the patient swaying: regulated feed at a low tau_d (reversals), no
#: regulation (the torque limit reverses), the PD alone.
MIXED = """name: mixed
seed: 5
n: 1
rounds_s: [20]
population:
  patient:
    motion: {dist: choice, values: [head]}
  anatomy:
    material: {dist: choice, values: [acrylic]}
arms:
  - {name: low, tau_d_mnm: 15}
  - {name: none, strategy: none}
  - {name: fr, strategy: feedrate, tau_d_mnm: 30}
"""
#: Severe curves, no regulation and the limit at the file's strength: files break.
BREAKING = """name: breaking
seed: 9
n: 3
rounds_s: [15]
population:
  anatomy:
    material: {dist: choice, values: [acrylic]}
    curvature_class: {dist: choice, values: [severe]}
arms:
  - {name: none, strategy: none, torque_limit_share: 1.0}
"""


def _run(spec_text: str, monkeypatch, compiled: bool) -> tuple[list[dict], dict]:
    """Every procedure's row (wall time aside), and what the compiled loop did."""
    seen = {"ticks": 0, "codes": []}
    call, ticks = dl.DrillLoop.__call__, dk.drill_ticks

    async def counted(self, rt):
        n = await call(self, rt)
        seen["ticks"] += n
        return n

    def kernel(*args):
        out = ticks(*args)
        seen["codes"].append(out[2])
        return out

    monkeypatch.setattr(dl.DrillLoop, "__call__", counted)
    monkeypatch.setattr(dl.dk, "drill_ticks", kernel)
    spec = parse_trial(spec_text)
    rows = [rn.run_procedure(p, compiled_ticks=compiled) for a in range(len(spec.arms))
            for p in rn.procedures_of(spec, a, range(spec.n))]
    monkeypatch.undo()
    if not compiled:
        assert seen["ticks"] == 0
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in rows], seen


def test_compiled_feeding_ticks_give_the_same_procedures(monkeypatch):
    fast, seen = _run(MIXED, monkeypatch, compiled=True)
    slow, _ = _run(MIXED, monkeypatch, compiled=False)
    assert fast == slow
    ticks = sum(r["simulated_s"] for r in fast) / 0.002
    assert seen["ticks"] > 0.5 * ticks                 # most of the run was compiled
    assert sum(r["reversals"] for r in fast) >= 5      # stopped and resumed around events
    assert {r["status"] for r in fast} == {"ok", "fault"}


@pytest.mark.slow
def test_a_file_that_breaks_in_a_compiled_step(monkeypatch):
    fast, seen = _run(BREAKING, monkeypatch, compiled=True)
    slow, _ = _run(BREAKING, monkeypatch, compiled=False)
    assert fast == slow
    assert all(r["status"] == "fracture" for r in fast)
    assert any(c != 0 for c in seen["codes"])          # one broke inside the compiled loop
