"""A retraction is waited for as long as it brings the file out: a canal that drags the file
slows it (the -0.5 N retraction withdraws about 3 mm/s in a drag-free canal, 1.5 mm/s 14 mm
deep with the bench's drag, which acts along the file's length in the canal) without ending
the wait; a file that does not come out is said to be stuck, with where it is."""

from __future__ import annotations

import logging
from dataclasses import replace

import pytest
import structlog

from dentibot.app.procedure import RETRACT_PROGRESS_MM, RETRACT_STALL_S, Procedure
from dentibot.sim.bench_physics import BENCH
from dentibot.sim.canal import CanalParams
from dentibot.sim.world import WorldConfig


@pytest.fixture(autouse=True)
def _quiet():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.CRITICAL))


async def _retract_from(proc: Procedure,
                        depth_mm: float) -> tuple[str | None, float, float]:
    """Drill past ``depth_mm``, retract: (why the wait ended, how long it took, the depth the
    retraction started from)."""
    rt = proc.runtime
    assert await proc.command("drill") is None
    assert await proc.run_for(120.0, until=lambda r: r.last is not None
                              and r.last.depth_mm is not None and r.last.depth_mm > depth_mm)
    assert await proc.command("retract") is None
    t0, s0 = proc.world.t, rt.last.depth_mm
    why = await proc.finish_retraction()
    return why, proc.world.t - t0, s0


async def test_a_dragging_canal_slows_the_retraction_and_the_wait_goes_on():
    canal = BENCH.canal_drag(CanalParams())
    proc = Procedure.simulated(WorldConfig(seed=1, canal=canal))
    async with proc:
        why, took_s, s0 = await _retract_from(proc, 14.0)
        rt = proc.runtime
        assert why is None and rt.state == "done"
        assert rt.last.depth_mm <= rt.cfg.plan.retract_to_mm
    # The admittance withdraws at k/b (0.5 N - c(s) v) = v (6.25 mm/s per N, the ideal arm),
    # the drag c(s) = c s / D at depth s (D the depth it was fitted at): 1/v = (1 + 6.25 c s
    # / D) / 3.125, so from s0 to 0.5 mm out the wait is ((s0 + 0.5) + 6.25 c s0^2 / (2 D)) /
    # 3.125 s, against (s0 + 0.5) / 3.125 without drag
    c, d = BENCH.drag_n_s_per_mm, BENCH.drag_depth_mm
    free_s = (s0 + 0.5) / 3.125
    assert took_s == pytest.approx(free_s + 6.25 * c * s0 * s0 / (2.0 * d) / 3.125, rel=0.15)
    assert took_s > 1.3 * free_s


async def test_a_file_that_does_not_come_out_is_reported_stuck():
    """The bench's drag 14 mm deep against a retraction of 0.05 N: the file comes out at
    about 0.1 mm/s (k/b 0.05 N / (1 + 6.25 c 14 / D)), too slowly for the wait (1 mm in
    5 s): it is said to stall."""
    proc = Procedure.simulated(WorldConfig(seed=1, canal=BENCH.canal_drag(CanalParams())))
    rt = proc.runtime
    async with proc:
        await proc.call(lambda: rt.configure(plan=replace(rt.cfg.plan, retract_fz_n=0.05)))
        why, took_s, _ = await _retract_from(proc, 14.0)
        assert rt.state == "treating.retracting"
    assert why is not None and why.startswith("retraction stalled"), why
    assert f"in {RETRACT_STALL_S:g} s" in why
    withdrawn = float(why.split("withdrew ")[1].split(" mm")[0])
    assert withdrawn < RETRACT_PROGRESS_MM
    assert took_s == pytest.approx(RETRACT_STALL_S, abs=0.01)
