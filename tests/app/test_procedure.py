"""One procedure, one continuous control loop: lock-step time that passes only while a step
waits, one world step per tick across the steps of a run, and a loop that stops everything
however it ends."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import pytest
import structlog

from dentibot.app.procedure import Procedure
from dentibot.app.runner import ProtocolRunner
from dentibot.protocol.loader import load_protocol
from dentibot.runtime.estimate import Devices
from dentibot.runtime.gate import GateClosed
from dentibot.sim.world import WorldConfig

GOLDEN = Path(__file__).resolve().parent / "golden"


@pytest.fixture(autouse=True)
def _quiet():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.CRITICAL))


async def test_lockstep_time_passes_only_while_a_step_waits():
    proc = Procedure.simulated(WorldConfig(seed=1), keep_rows=True)
    rt, w = proc.runtime, proc.world
    async with proc:
        assert await proc.command("drag") is None
        assert rt.ticks == 0 and w.steps == 0          # the command came before any tick
        await proc.run_for(ticks=10)
        # ten ticks: the first on the initial world, then one world step before each next
        assert rt.ticks == 10 and w.steps == 9
        await asyncio.sleep(0.05)                      # nobody waits: time stands still
        assert rt.ticks == 10 and w.steps == 9
        await proc.run_for(0.01)                       # 10 ms at 500 Hz = 5 ticks
        assert rt.ticks == 15 and w.steps == 14
        assert [r["tick"] for r in proc.rows] == list(range(15))
        assert proc.rows[0]["state"] == "dragging"     # entered in the very first tick


async def test_a_wait_until_a_condition_ends_in_the_tick_where_it_holds():
    proc = Procedure.simulated(WorldConfig(seed=2), keep_rows=True)
    async with proc:
        await proc.command("drag")
        held = await proc.run_for(ticks=1000, until=lambda r: r.ticks == 37)
        assert held and proc.runtime.ticks == 37 and len(proc.rows) == 37
        assert not await proc.run_for(ticks=3, until=lambda r: False)
        assert proc.runtime.ticks == 40


async def test_a_protocol_run_steps_the_world_once_per_tick_across_its_steps():
    """The telemetry's time is the world's time in every row, through the step boundaries
    (calibration, drag, align, drilling round, retraction): no tick ever runs twice on one
    world state, and no world step is lost."""
    seen: list[tuple[int, float, float]] = []

    def tap(row: dict) -> None:
        seen.append((row["tick"], row["t"], runner.world.t))

    runner = ProtocolRunner(load_protocol(GOLDEN / "short-root-canal.yaml"), no_record=True,
                            tap=tap)
    result = await runner.run()
    assert result.summary.status == "ok"
    assert len({s["name"] for s in result.summary.to_dict()["steps"]}) == 4
    assert [k for k, _, _ in seen] == list(range(len(seen)))
    bad = [(k, t, wt) for k, t, wt in seen if abs(t - wt) > 1e-9]
    assert not bad, bad[:3]


async def test_a_run_that_only_reads_the_world_after_each_tick_builds_no_row(monkeypatch):
    """With ``on_tick`` alone (no recording, live summary, tap or progress) no telemetry row is
    built, ``on_tick`` sees every tick once and in order, and the run ends as the same
    protocol with a tap does (same status, ticks and world time)."""
    from dentibot.runtime import control_task

    built = []
    real_row = control_task.telemetry_row

    def counting_row(*args, **kwargs):
        built.append(args[1])
        return real_row(*args, **kwargs)

    monkeypatch.setattr(control_task, "telemetry_row", counting_row)
    protocol = load_protocol(GOLDEN / "short-root-canal.yaml")
    seen: list[tuple[int, float]] = []
    runner = ProtocolRunner(protocol, no_record=True, live_summary=False,
                            on_tick=lambda r: seen.append((r.rt.ticks, r.world.t)))
    result = await runner.run()
    assert not built
    assert [k for k, _ in seen] == list(range(1, runner.rt.ticks + 1))
    rows: list[dict] = []
    tapped = ProtocolRunner(protocol, no_record=True, live_summary=False, tap=rows.append)
    again = await tapped.run()
    assert len(built) == len(rows) == len(seen)
    assert (result.summary.status, seen[-1][1]) == (again.summary.status, rows[-1]["t"])


async def test_stopping_the_procedure_leaves_nothing_moving():
    proc = Procedure.simulated(WorldConfig(seed=3))
    w = proc.world
    async with proc:
        assert await proc.command("drill") is None
        await proc.run_for(2.0)
        assert w.handpiece.cmd_rpm > 0.0 and w.arm.mode == "vel"
    assert not proc.running
    assert w.handpiece.cmd_rpm == 0.0 and w.arm.mode == "idle"
    with pytest.raises(GateClosed):
        await proc.command("stop")


async def test_a_control_loop_that_dies_stops_the_devices_and_tells_the_waiting_step():
    class Broken:
        def __init__(self, arm, after: int) -> None:
            self._arm, self._left = arm, after

        def __getattr__(self, name):
            return getattr(self._arm, name)

        async def read(self):
            self._left -= 1
            if self._left < 0:
                raise RuntimeError("driver bug")
            return await self._arm.read()

    proc = Procedure.simulated(
        WorldConfig(seed=4),
        devices=lambda world, d: Devices(Broken(d.arm, 600), d.ft, d.motor, d.aux))
    w = proc.world
    async with proc:
        await proc.command("drill")
        with pytest.raises(GateClosed, match="RuntimeError: driver bug"):
            await proc.run_for(5.0)
    assert proc.error is not None and "driver bug" in proc.error
    assert w.handpiece.cmd_rpm == 0.0 and w.arm.mode == "idle"


async def test_the_safe_stop_withdraws_the_file_then_stops():
    proc = Procedure.simulated(WorldConfig(seed=5), keep_rows=True)
    rt, w = proc.runtime, proc.world
    async with proc:
        await proc.command("drill")
        assert await proc.run_for(60.0, until=lambda r: r.last_row["true_depth_mm"] > 5.0)
        await proc.safe_stop()
        assert rt.state == "idle"
        assert rt.truth()["true_depth_mm"] <= rt.cfg.plan.retract_to_mm + 0.05
        assert abs(w.handpiece.omega_rpm) < 1.0 and w.handpiece.cmd_rpm == 0.0
        states = [r["state"] for r in proc.rows]
        assert "treating.retracting" in states
