"""The terminal UI driven through textual's pilot (real key presses, the real app) on the
built-in simulator: connect -> calibrate -> align -> drill -> pause -> retract, a refused
command with its reason, Esc (stop safely), quit while drilling, the software e-stop.

Simulated time advances only through ``SessionController.advance`` (stepped clock), so what
the keys do and what the physics does are separated; the expectations come from the
simulated world (true load, true depth, the file's speed) and the thesis's numbers, not from
what the session printed.
"""

from __future__ import annotations

import math

from dentibot.session.app import PAINT_S, CommandInput, SessionApp
from dentibot.session.controller import ESTOP_CAUSE
from dentibot.sim.world import WorldConfig

SIZE = (130, 44)
GAP_MM = 2.0                    # the default phantom: file tip 2 mm above the orifice
ALIGN_MM_S_PER_N = 500 / 80     # Table 4.3 self-alignment: k/b = 6.25 mm/s per N


async def panel(pilot) -> str:
    """What the panel shows on the screen once it has caught up with the runtime."""
    app = pilot.app
    app.refresh_panel()
    for _ in range(100):
        if not app.painting:
            break
        await pilot.pause(PAINT_S)
    return app.panel_text


async def keys(pilot, text: str) -> None:
    """Type ``text`` key by key, then Enter; wait until the command has run."""
    await pilot.press(*text, "enter")
    await wait_idle(pilot, pilot.app.controller)


async def line(pilot, text: str) -> None:
    """Put ``text`` on the command line (faster than key by key), then Enter; wait until
    the command has run."""
    pilot.app.query_one(CommandInput).value = text
    await pilot.press("enter")
    await wait_idle(pilot, pilot.app.controller)


async def wait_idle(pilot, c) -> None:
    """Let the typed commands finish (they run in a worker, in order)."""
    for _ in range(200):
        await pilot.pause()
        if not pilot.app.pending:
            return
    raise AssertionError(f"commands still pending: {pilot.app.transcript[-3:]}")


async def test_bench_flow_connect_calibrate_align_drill_pause_retract(stepped):
    c = stepped
    app = SessionApp(c)
    async with app.run_test(size=SIZE) as pilot:
        w_cfg = WorldConfig()
        # --- connect: completion with Tab, then Enter
        await pilot.press("c", "o", "n", "tab")
        assert app.query_one(CommandInput).value == "connect"
        await pilot.press("enter")
        await wait_idle(pilot, c)
        assert c.state == "idle" and "idle" in await panel(pilot)
        world = c.world

        # --- a command the state cannot take: refused with the state and what it needs
        await keys(pilot, "drill")
        await wait_idle(pilot, c)
        refused = [s for s in app.transcript if "refused" in s]
        assert refused and "'drill' refused in state 'idle'" in refused[-1]
        assert "calibrate load" in refused[-1]
        assert c.state == "idle" and world.handpiece.omega_rpm == 0.0

        # --- load calibration: the routine identifies the simulated load
        await line(pilot, "calibrate load")
        await wait_idle(pilot, c)
        assert c.state == "calibrating.load"
        assert "calibrating > load" in await panel(pilot)
        await c.advance(60.0, until=lambda r: r.state == "idle")
        assert c.state == "idle" and c.runtime.treatment.gravity_known
        mass_kg = c.runtime.gravity.weight_n / 9.80665
        assert math.isclose(mass_kg, w_cfg.sensor.mass_kg, rel_tol=0.02)   # thesis: 139 g

        # --- self-alignment with f_d = (0, 0, 1 N): the tip crosses the 2 mm gap
        await line(pilot, "align fz=1.0")
        await wait_idle(pilot, c)
        assert c.state == "self_aligning"
        t_gap = GAP_MM / (ALIGN_MM_S_PER_N * 1.0)          # 0.32 s in free space
        await c.advance(t_gap + 0.2)
        snap = c.snapshot()
        assert snap.true_depth_mm > 0.0                    # inside the canal
        assert abs(snap.depth_mm - snap.true_depth_mm) < 0.05

        # --- drilling with the automated strategy (thesis 5.4, 60 rpm, tau_d 40 mNm)
        await line(pilot, "drill strategy=automated tau_d=40 rpm=60")
        await wait_idle(pilot, c)
        assert c.state == "treating.drilling.feeding"
        depth0 = c.snapshot().true_depth_mm
        await c.advance(2.0)
        snap = c.snapshot()
        assert snap.state.startswith("treating.drilling")
        assert math.isclose(world.handpiece.omega_rpm, 60.0, abs_tol=1.0) or \
            snap.state == "treating.drilling.reversing"
        assert snap.true_depth_mm > depth0 + 0.5           # it advanced into the canal
        assert 0.0 < snap.file_torque_mnm < snap.torque_limit_mnm
        assert "treating > drilling" in await panel(pilot)

        # --- space on the empty command line pauses: file stopped, no feed
        await pilot.press("space")
        await wait_idle(pilot, c)
        assert c.state == "treating.paused"
        await c.advance(0.3)
        paused_depth = c.snapshot().true_depth_mm
        await c.advance(0.3)
        assert abs(world.handpiece.omega_rpm) < 0.5
        assert abs(c.snapshot().true_depth_mm - paused_depth) < 0.05   # not feeding
        assert c.runtime.last_row["fz_n"] == 0.0
        assert "treating > paused" in await panel(pilot)

        # --- retract: the file leaves the canal, the treatment is done
        await keys(pilot, "retract")
        await wait_idle(pilot, c)
        assert c.state == "treating.retracting"
        await c.advance(30.0, until=lambda r: r.state == "done")
        await c.advance(0.1)
        assert c.state == "done"
        plan = c.runtime.cfg.plan
        assert c.snapshot().true_depth_mm <= plan.retract_to_mm + 0.05
        assert abs(world.handpiece.omega_rpm) < 0.5

        # --- history: Up brings back the last command
        await pilot.press("up")
        assert app.query_one(CommandInput).value == "retract"
        app.query_one(CommandInput).value = ""

        # --- quit
        await pilot.press("ctrl+q")
        await pilot.pause()
    assert c.closed and not c.connected
    assert any("bye" in s for s in app.transcript)


async def test_escape_stops_safely_while_drilling(stepped):
    c = stepped
    c.opt.calibrated = True                 # load known: straight to the treatment
    app = SessionApp(c)
    async with app.run_test(size=SIZE) as pilot:
        await line(pilot, "connect")
        await line(pilot, "align")
        await c.advance(0.6)
        await line(pilot, "drill")
        await c.advance(1.5)
        assert c.state == "treating.drilling.feeding" and c.snapshot().true_depth_mm > 1.0
        await pilot.press("escape")
        await pilot.pause()
        assert c.state == "treating.retracting"          # not straight to idle: out first
        await c.advance(30.0, until=lambda r: r.state == "idle")
        await c.advance(0.05)
        await wait_idle(pilot, c)
        assert c.state == "idle"
        assert c.snapshot().true_depth_mm <= c.runtime.cfg.plan.retract_to_mm + 0.05
        assert abs(c.world.handpiece.omega_rpm) < 0.5
        assert any("stopped safely" in s for s in app.transcript)
        await line(pilot, "quit")
        await pilot.pause()
    assert c.closed


async def test_quit_while_drilling_withdraws_the_file_first(stepped, tmp_path):
    c = stepped
    c.opt.calibrated = True
    app = SessionApp(c)
    path = tmp_path / "quit.mcap"
    async with app.run_test(size=SIZE) as pilot:
        await line(pilot, "connect")
        await line(pilot, f"record start {path}")
        await wait_idle(pilot, c)
        await line(pilot, "align")
        await c.advance(0.6)
        await line(pilot, "drill")
        await c.advance(1.5)
        assert c.state == "treating.drilling.feeding"
        assert c.snapshot().true_depth_mm > 1.0 and c.world.handpiece.omega_rpm > 50.0
        await pilot.press("ctrl+q")                       # quit while the file turns inside
        for _ in range(200):
            await pilot.pause()
            if c.closed:
                break
    assert c.closed and not c.connected
    world = c.world
    tip_depth = c.runtime.truth()["true_depth_mm"]
    assert tip_depth <= c.runtime.cfg.plan.retract_to_mm + 0.05      # out of the canal
    # file and arm were told to stop: left alone, the simulated devices come to rest
    assert world.handpiece.mode == "vel" and world.handpiece.cmd_rpm == 0.0
    assert world.arm.mode == "idle"
    world.run(0.2)
    assert abs(world.handpiece.omega_rpm) < 0.5
    assert all(abs(v) < 1e-6 for v in world.arm.qdot)
    from dentibot.telemetry.reader import read_recording

    rec = read_recording(path)
    assert rec.complete and rec.status == "ok"
    ticks = [r["tick"] for r in rec.rows]
    assert ticks == list(range(ticks[0], ticks[0] + len(ticks)))     # no tick lost
    states = [r["state"] for r in rec.rows]
    assert "treating.retracting" in states and states[-1] == "idle"


async def test_software_estop_stops_arm_and_file_and_reset_leaves_fault(stepped):
    c = stepped
    c.opt.calibrated = True
    app = SessionApp(c)
    async with app.run_test(size=SIZE) as pilot:
        await line(pilot, "connect")
        await line(pilot, "align")
        await c.advance(0.6)
        await line(pilot, "drill")
        await c.advance(1.0)
        assert c.world.handpiece.omega_rpm > 50.0
        await keys(pilot, "estop")
        assert c.state == "fault"
        assert c.runtime.treatment.fault_causes[-1] == ESTOP_CAUSE
        await c.advance(0.2)
        assert abs(c.world.handpiece.omega_rpm) < 0.5
        assert all(abs(v) < 1e-6 for v in c.world.arm.qdot)
        assert "software emergency stop" in await panel(pilot)
        # in fault only reset is taken; anything else is refused with the reason
        await line(pilot, "drill")
        await wait_idle(pilot, c)
        assert "'drill' refused in state 'fault'" in app.transcript[-1]
        await line(pilot, "reset")
        await wait_idle(pilot, c)
        assert c.state == "idle" and not c.runtime.treatment.fault_causes
        await line(pilot, "quit")
        await pilot.pause()
    assert c.closed
