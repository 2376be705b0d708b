"""The session without its screen: the gate between ticks, the clocks, steps, recording,
refusals, and the real-time clock on the built-in simulator."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from dentibot.control.admittance import DRAGGING, SELF_ALIGNMENT
from dentibot.protocol.loader import parse_protocol
from dentibot.runtime.clock import LockStepClock
from dentibot.runtime.gate import GateClosed, TickGate
from dentibot.session.controller import SessionController, SessionOptions
from dentibot.states.modes import DRAGGING_IN_CANAL
from dentibot.telemetry.reader import read_recording
from dentibot.telemetry.summary import summarize_file

pytestmark = pytest.mark.wire


async def say(c: SessionController, line: str):
    replies = await c.execute(line)
    assert len(replies) == 1, replies
    return replies[0]


# ------------------------------------------------------------------ gate and clocks
async def test_gate_runs_actions_between_ticks_in_order_and_counts_waits_exactly():
    gate = TickGate()
    steps = []
    clock = LockStepClock(lambda: steps.append(len(steps)), held=True)
    clock.serve = gate.run_actions
    gate.on_submit = clock.wake
    gate.open(runtime=None)
    ran = []

    async def loop():
        await clock.wait_first()
        for _ in range(50):          # what Runtime.run does: tick, then wait for the next
            await gate.between()
            await clock.wait_next()

    task = asyncio.create_task(loop())
    # held: no step, but the actions are served, in the order submitted
    a = gate.submit(lambda: _record(ran, "a"))
    b = gate.submit(lambda: _record(ran, "b"))
    assert await a == "a" and await b == "b" and ran == ["a", "b"] and steps == []
    clock.grant(1)                         # the first tick takes a grant, with no world step
    assert await gate.submit(lambda: "after the first tick") and steps == []
    w = gate.wait(max_ticks=7, on_done=clock.hold)
    clock.grant(100)
    await w
    assert len(steps) == 7                 # held again in the very tick the wait ended
    for _ in range(5):
        await asyncio.sleep(0)
    assert len(steps) == 7
    clock.release()
    await task
    assert len(steps) == 50
    gate.close("test over")
    with pytest.raises(GateClosed):
        gate.submit(lambda: _record(ran, "c"))


async def _record(ran, x):
    ran.append(x)
    return x


async def test_the_session_clock_for_the_simulator_in_real_time_is_a_realtime_clock(tmp_path):
    c = SessionController(SessionOptions(clock="realtime", calibrated=True, record_dir=tmp_path))
    assert (await say(c, "connect")).kind == "ok"
    try:
        assert c.runtime.clock.realtime                   # paced: real-time deadlines
        assert c.runtime.stats.deadlines                  # lateness and overruns counted
        w0 = c.world.steps
        for _ in range(500):
            await asyncio.sleep(0.01)
            if c.runtime.ticks > 20:
                break
        assert c.runtime.ticks > 20
        assert c.world.steps - w0 >= c.runtime.ticks - 2   # the world steps once per tick
        assert (await say(c, "drag")).kind == "ok"
        assert c.state == "dragging"
    finally:
        await c.shutdown()
    assert c.closed and c.state == "idle"


# ------------------------------------------------------------------ refusals
async def test_refusals_name_the_state_and_what_is_needed(stepped):
    c = stepped
    r = await say(c, "drill")
    assert r.kind == "refused" and "not connected" in r.text and "'connect'" in r.text
    await say(c, "connect")
    r = await say(c, "pause")
    assert r.kind == "refused"
    assert r.text == ("'pause' refused in state 'idle': it needs state treating.drilling or "
                      "treating.patient_moved or treating.retracting")
    r = await say(c, "align")
    assert r.kind == "refused" and "needs a load calibration (calibrate load)" in r.text
    r = await say(c, "drill tau_d=70")
    assert r.kind == "error" and "drill.tau_d_mnm: 70 mNm is not below the torque limit" in r.text
    # nothing moved and nothing changed
    assert c.state == "idle" and c.world.handpiece.cmd_rpm == 0.0
    await say(c, "quit")


async def test_a_refused_drill_leaves_the_running_strategy_alone(stepped):
    c = stepped
    c.opt.calibrated = True
    await say(c, "connect")
    await say(c, "align")
    await c.advance(0.6)
    assert (await say(c, "drill tau_d=40")).kind == "ok"
    await c.advance(0.5)
    strategy = c.runtime.ctx.strategy
    r = await say(c, "drill tau_d=20 strategy=none")
    # the machine refuses it while treating: the running pass goes on as it was
    assert r.kind == "refused" and "in state 'treating.drilling" in r.text
    assert c.runtime.ctx.strategy is strategy and strategy.p.feedrate.tau_d_mnm == 40
    assert c._activity_name == "drill" and c.runtime.cfg.handpiece.drilling_rpm == 60
    await say(c, "quit")


# ------------------------------------------------------------------ steps
async def test_step_drag_moves_the_arm_with_the_dragging_admittance(stepped):
    c = stepped
    c.opt.calibrated = True
    await say(c, "connect")
    y0 = c.world.tip_0[1]
    r = await say(c, "step drag duration_s=0.2 hand_force_n=0,0.5,0")
    assert r.kind == "ok" and c.state == "dragging"
    await c.advance(0.25)
    dy = c.world.tip_0[1] - y0
    # the arm accelerates from rest towards v = k f / b (Table 4.3 dragging: 18.75 mm/s/N):
    # it cannot have moved more than v * t, and does not lag by more than a few tens of ms
    v = DRAGGING.k * 0.5 / DRAGGING.b[1]
    assert 0.5 * v * 0.2 < dy < 1.02 * v * 0.2
    assert c.world.hand_force_0 == (0.0, 0.0, 0.0)          # the scripted hand let go
    while c.messages:
        _, text = c.messages.popleft()
    assert "step drag: finished in state dragging" in text
    await say(c, "quit")


async def test_step_n_runs_the_protocols_step(tmp_path):
    p = parse_protocol("name: p\nseed: 3\nsteps:\n  - calibrate_load: {}\n"
                       "  - align: {duration_s: 0.5, fz_n: 1.0}\n")
    c = SessionController(SessionOptions(protocol=p, clock="stepped", record_dir=tmp_path))
    await say(c, "connect")
    assert (await say(c, "step 3")).kind == "error"
    assert (await say(c, "step 1")).kind == "ok"
    await c.advance(60.0, until=lambda r: r.state == "idle")
    assert c.runtime.treatment.gravity_known
    assert (await say(c, "step 2")).kind == "ok" and c.state == "self_aligning"
    await c.advance(0.6)
    assert c.state == "self_aligning" and c._activity_name is None     # 0.5 s step is over
    await say(c, "quit")


async def test_retract_ends_a_multi_round_drill(stepped):
    c = stepped
    c.opt.calibrated = True
    await say(c, "connect")
    await say(c, "align")
    await c.advance(0.6)
    assert (await say(c, "drill rounds=[60,40]")).kind == "ok"
    assert c.runtime.treatment.passes_left > 0
    await c.advance(1.0)
    assert (await say(c, "retract")).kind == "ok"
    assert c.runtime.treatment.passes_left == 0 and c._activity_name is None
    await c.advance(30.0, until=lambda r: r.state == "done")
    assert c.state == "done"                      # not another pass
    await say(c, "quit")


# ------------------------------------------------------------------ TCP calibration
def _tip_at(world, point, R, q0):
    """Joint angles putting the simulated (true) file tip at ``point`` with orientation R."""
    from scipy.optimize import least_squares

    def res(q):
        T = world.kin.fk_tool(q)
        return np.concatenate([T[:3, 3] - point, 50.0 * (T[:3, :3] - R).ravel()])

    return least_squares(res, q0, xtol=1e-12, ftol=1e-12).x


async def test_calibrate_tcp_with_pedal_presses_finds_the_true_tip(stepped):
    """The runtime's tool is 10 mm too short; the operator (the test, moving the simulated
    arm) holds the tip on one point in four orientations and presses the pedal at each:
    eq 3.21-3.23 give back the simulator's true tip, 90 mm along the flange z."""
    from scipy.spatial.transform import Rotation

    c = stepped
    await say(c, "connect")
    c.runtime.set_tool_tip((0.0, 0.0, 80.0))
    w = c.world
    r = await say(c, "calibrate tcp")
    assert r.kind == "ok" and c.state == "calibrating.tcp" and "press 'pedal'" in r.text
    T0 = w.kin.fk_tool(w.arm.q)
    point = T0[:3, 3] + np.array([0.0, 0.0, -5.0])
    q = np.array(w.arm.q)
    for rx, ry in ((0, 0), (15, 0), (0, 15), (-12, -12)):
        q = _tip_at(w, point, T0[:3, :3] @ Rotation.from_euler(
            "xy", [rx, ry], degrees=True).as_matrix(), q)
        w.teleport_arm(q)
        await c.advance(ticks=3)
        assert (await say(c, "pedal")).kind == "ok"
        await c.advance(ticks=5)
        assert not w.pedal                                 # released by itself
    assert c.state == "idle", list(c.messages)
    np.testing.assert_allclose(c.runtime.cfg.tool.tip_6_mm, (0.0, 0.0, 90.0), atol=0.05)
    events = [text for _, text in c.messages]
    assert sum("tcp_point" in e for e in events) == 3 and "calibration_done: TCP" in events[-1]
    await say(c, "quit")


# ------------------------------------------------------------------ recording
async def test_record_start_stop_writes_every_tick_and_the_events(stepped, tmp_path):
    c = stepped
    c.opt.calibrated = True
    await say(c, "connect")
    await c.advance(8.0)
    path = tmp_path / "s.mcap"
    wall_ns = time.time_ns()
    assert (await say(c, f"record start {path}")).kind == "ok"
    assert (await say(c, "record start")).kind == "info"          # one at a time
    await say(c, "align")
    await c.advance(0.4)
    await say(c, "stop")
    await c.advance(0.1)
    r = await say(c, "record stop")
    assert r.kind == "ok" and "250 ticks" in r.text               # 0.5 s at 500 Hz
    rec = read_recording(path)
    assert rec.complete and rec.status == "ok" and rec.metadata["session"] is True
    # started mid-run: the first recorded tick (t = 8 s) is logged when it ran, not 8 s later
    first_ns = rec.metadata["start_wall_ns"] + round(rec.rows[0]["t"] * 1e9)
    assert abs(first_ns - wall_ns) < 2e9
    ticks = [row["tick"] for row in rec.rows]
    assert len(ticks) == 250 and ticks == list(range(ticks[0], ticks[0] + 250))
    assert {row["step"] for row in rec.rows} >= {"1:align"}
    kinds = [e["kind"] for e in rec.events]
    assert "command" in kinds
    s = summarize_file(path)
    assert s.status == "ok" and round(s.duration_s, 3) == 0.5
    await say(c, "quit")


# ------------------------------------------------------------------ devices
@pytest.mark.timeout(60)
async def test_devices_over_the_wire_connect_refuse_estop_and_close_everything():
    from dentibot.sim.serve import ServePorts, VirtualDentiBot
    from dentibot.sim.world import World, WorldConfig

    # loopback on a shared machine: a few late samples are not a stale stream
    p = parse_protocol("name: wire\nlimits: {stale_periods: {arm: 25, ft: 25, motor: 50, "
                       "aux: 100}}\nsteps:\n  - calibrate_load: {}\n")
    world = World(WorldConfig(seed=5))
    ports = ServePorts(meca_port=0, netft_port=0, netft_http_port=0, modbus_port=0, can_port=0)
    async with VirtualDentiBot(world, ports) as bot:
        c = SessionController(SessionOptions(protocol=p,
                                             devices=bot.devices_config(ft_stale_after_ms=50)))
        try:
            r = await say(c, "connect")
            assert r.kind == "ok" and "devices (arm 127.0.0.1" in r.text
            assert c.state == "idle" and c.runtime.clock.realtime and c.world is None
            # no gravity model on real devices until the load is calibrated
            r = await say(c, "align")
            assert r.kind == "refused" and "needs a load calibration" in r.text
            r = await say(c, "estop")
            assert r.kind == "ok" and c.state == "fault"
            assert c.runtime.treatment.fault_causes[-1] == "software emergency stop"
            assert world.handpiece.cmd_rpm == 0.0
            assert (await say(c, "reset")).kind == "ok" and c.state == "idle"
        finally:
            r = await c.shutdown()
        assert "devices closed" in r.text and c.closed


# ------------------------------------------------------------------ depth reference
async def _align_3_mm_in(c) -> None:
    """Connected and aligning until the file is more than 3 mm in (its estimated depth)."""
    c.opt.calibrated = True
    await say(c, "connect")
    await say(c, "align")
    await c.advance(20.0, until=lambda r: (r.last_row or {}).get("depth_mm") is not None
                    and r.last_row["depth_mm"] > 3.0)


def _depths(c) -> tuple[float, float]:
    """(estimated depth, the simulator's true depth) of the last tick, mm."""
    row = c.runtime.last_row
    return row["depth_mm"], row["true_depth_mm"]


async def test_depth_counts_from_the_same_orifice_after_a_stop_a_drag_and_a_new_alignment(
        stepped):
    """The file goes 3 mm in, the operator stops, drags (without moving it) and aligns again:
    the depth still reads the file's depth in the canal (the simulator's truth is the check),
    and a retraction withdraws the file out of the canal, not to where the second alignment
    began."""
    c = stepped
    await _align_3_mm_in(c)
    est0, true0 = _depths(c)
    assert est0 > 3.0 and true0 > 2.5
    assert (await say(c, "stop")).kind == "ok"
    await c.advance(ticks=10)
    assert c.state == "idle"
    assert (await say(c, "drag")).kind == "ok"
    await c.advance(ticks=50)
    assert (await say(c, "align")).kind == "ok"
    await c.advance(ticks=5)
    est, true = _depths(c)
    # one orifice for the whole stay: the estimate still tracks the truth (within the
    # estimate's own offset measured before the stop), not -orifice_gap from a new start
    assert est == pytest.approx(true + (est0 - true0), abs=0.3)
    assert (await say(c, "retract")).kind == "ok"
    await c.advance(30.0, until=lambda r: r.state in ("done", "idle"))
    assert _depths(c)[1] <= 0.0                         # out of the canal, by the truth
    await say(c, "quit")


async def test_esc_during_alignment_withdraws_a_file_that_is_in_the_canal(stepped):
    """Esc (stop safely) in self-alignment with the file 3 mm in: the file comes out of the
    canal (the simulator's truth), it is not left where it was."""
    c = stepped
    await _align_3_mm_in(c)
    assert _depths(c)[1] > 2.5
    c.procedure.clock.release()                 # the safe stop takes the ticks it needs
    reply = await asyncio.wait_for(c.safe_stop(), 60.0)
    assert reply.kind == "ok"
    assert c.state == "idle"
    assert _depths(c)[1] <= 0.0                 # out, by the truth
    assert ("retract", "self_aligning", "treating.retracting") in c.runtime.treatment.history
    await say(c, "quit")


async def test_esc_after_dragging_the_file_in_before_any_alignment_withdraws_it(stepped):
    """The operator drags the file 7-8 mm down into the canal before any alignment (no depth
    reference: the orifice is only known once alignment starts). Esc withdraws it along its
    axis back past where it was last known out (the start), and the simulator's truth says it
    is out; the old behaviour said "retracted" and left it in."""
    c = stepped
    c.opt.calibrated = True
    await say(c, "connect")
    assert (await say(c, "drag")).kind == "ok"
    w = c.world
    w.hand_force_0 = tuple(1.0 * x for x in w.axis_0)      # push along the file: into the canal
    await c.advance(20.0, until=lambda r: _depths(c)[1] > 8.0)
    w.hand_force_0 = (0.0, 0.0, 0.0)
    await c.advance(ticks=20)
    assert _depths(c)[1] > 7.0 and c.runtime.ctx.depth_ref is None
    c.procedure.clock.release()
    reply = await asyncio.wait_for(c.safe_stop(), 60.0)
    assert reply.kind == "ok" and c.state == "idle"
    assert _depths(c)[1] <= 0.0                             # out, by the truth
    assert ("retract", "dragging", "treating.retracting") in c.runtime.treatment.history
    await say(c, "quit")


def _tip_along(c, axis) -> float:
    """The simulator's file tip along ``axis`` ({0}, unit), mm."""
    return float(np.dot(c.world.tip_0, axis))


async def test_dragging_with_the_file_in_the_canal_yields_at_the_tip_with_self_alignments_gain(
        stepped):
    """The file 3 mm in (the default world: the bench-fitted arm and walls), the operator stops
    and drags. The arm yields at the file tip with self-alignment's gains, not at the grip
    with dragging's (which rang against the walls there until the tip-speed limit faulted):
    a hand pulling 1 N along the file draws it out at no more than self-alignment's
    k/b = 6.25 mm/s per N (the arm realises less, the walls hold some); once out, the grip is
    the reference again and the same hand moves it faster than that, at most at dragging's
    k/b = 18.75 mm/s per N."""
    c = stepped
    await _align_3_mm_in(c)
    assert (await say(c, "stop")).kind == "ok"
    await c.advance(ticks=10)
    assert (await say(c, "drag")).kind == "ok"
    await c.advance(ticks=50)
    rt = c.runtime
    assert rt.mode is DRAGGING_IN_CANAL and rt.admittance.ref_point_h_mm is None
    w = c.world
    axis = np.array(w.axis_0)
    w.hand_force_0 = tuple(-1.0 * axis)                 # pull along the file: out
    await c.advance(0.1)                                 # past the arm's delay and lag
    s0 = _tip_along(c, axis)
    await c.advance(0.2)
    v_in = (s0 - _tip_along(c, axis)) / 0.2
    assert _depths(c)[1] > 0.5                           # still in, by the truth
    k_b_align = SELF_ALIGNMENT.k / SELF_ALIGNMENT.b[2]
    assert 0.25 * k_b_align < v_in < k_b_align
    await c.advance(5.0, until=lambda r: r.mode.ref == "A")
    assert rt.mode.ref == "A" and _depths(c)[1] <= 0.0 and c.state == "dragging"
    await c.advance(0.1)
    s0 = _tip_along(c, axis)
    await c.advance(0.2)
    v_out = (s0 - _tip_along(c, axis)) / 0.2
    assert k_b_align < v_out < DRAGGING.k / DRAGGING.b[2]
    w.hand_force_0 = (0.0, 0.0, 0.0)
    notes = [d for _, kind, d in rt.events_log if kind == "drag_point"]
    assert [n.split(":")[0] for n in notes] == ["tip", "grip"]
    await say(c, "quit")


async def test_the_session_runs_the_trackers_calibration_step(tmp_path):
    """``step N`` of a protocol with the patient tracker runs ``calibrate_tracker``: started
    at once (no command of the machine behind it), finished with the anchors passed, the
    runtime then using them; refused while a treatment step is under way."""
    p = parse_protocol("name: p\nseed: 3\npatient: {tracker: true}\nsteps:\n"
                       "  - calibrate_tracker: {}\n  - align: {duration_s: 5.0, fz_n: 0.2}\n")
    c = SessionController(SessionOptions(protocol=p, clock="stepped", record_dir=tmp_path,
                                         calibrated=True))
    await say(c, "connect")
    geometry = c.runtime.cfg.tooth.geometry
    assert (await say(c, "step 1")).kind == "ok"
    await c.advance(60.0, until=lambda r: c._activity_name is None)
    text = ""
    while c.messages:
        _, text = c.messages.popleft()
    assert "step calibrate_tracker: finished in state idle" in text, text
    assert any(k == "tracker_calibration" for _, k, _ in c.runtime.events_log)
    assert c.runtime.cfg.tooth.geometry is not geometry       # the identified anchors
    assert (await say(c, "step 2")).kind == "ok" and c.state == "self_aligning"
    assert (await say(c, "step 1")).kind == "refused"          # not while aligning
    await say(c, "quit")
