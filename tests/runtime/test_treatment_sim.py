"""The automated root canal algorithm on the lock-step simulator."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sim_runs import finished, harness, procedure

from dentibot.control.feedrate import FILE_STRENGTH_MNM
from dentibot.runtime.config import TreatmentPlan
from dentibot.states.strategies import StrategyParams
from dentibot.sim.canal import CanalParams
from dentibot.sim.faults import Jerk as MotionJerk

CANALS = {
    "straight": CanalParams(),
    "curved": CanalParams(curve_start_mm=8.0, curve_radius_mm=8.0, curve_angle_deg=25.0),
    "tilted": CanalParams(tilt_deg=10.0),
}


@pytest.mark.parametrize("name", list(CANALS))
async def test_automated_algorithm_prepares_the_canal_to_working_length(name):
    h, rows = harness(seed=3, canal=CANALS[name])
    rt = h.runtime
    assert await h.command("drill") is None
    await h.run_for(until=finished, ticks=60_000)
    assert rt.state == "done", rt.treatment.fault_causes
    assert not any(r["fractured"] for r in rows)
    peak = max(r["file_torque_mnm"] for r in rows)
    assert peak < FILE_STRENGTH_MNM
    # the true tip depth (simulator's geometry, not the runtime's estimate) reached the
    # working length, but not the canal bottom 0.5 mm beyond it
    deepest = max(r["true_depth_mm"] for r in rows)
    assert 15.9 <= deepest < 16.5
    # completeness (eq 6.1) rose from 0 and is reported on every row
    assert rows[0]["completeness"] == 0.0 and rows[-1]["completeness"] > 0.5
    # it retracted: the tip is out of the canal again
    assert rows[-1]["true_depth_mm"] < 0.0


async def test_a_torque_spike_triggers_reversal_within_one_tick():
    h, rows = harness(seed=4)
    rt = h.runtime
    await h.command("drill")
    # drill until the file is well engaged, then bind it: debris packs the flutes
    await h.run_for(until=lambda r: r.last_row and r.last_row["true_depth_mm"] > 6.0,
                 ticks=20_000)
    assert rt.state == "treating.drilling.feeding"
    k0 = rt.ticks
    h.world.canal.debris_mm3 += 1.0          # +30 mNm of resistance (torque_mnm_per_mm3)
    await h.run_for(ticks=200)
    after = rows[k0:]
    limit = rt.cfg.plan.strategy.feedrate.reversal_threshold_n
    first = next(i for i, r in enumerate(after)
                 if r["fz_star_n"] < limit or r["file_torque_mnm"] > rt.cfg.thresholds.torque_limit_mnm)
    assert after[first]["state"] == "treating.drilling.reversing"
    assert "reversal_needed" in after[first]["events"]
    assert first <= 10   # the current reflects the new load within a few motor time constants
    assert not any(r["fractured"] for r in after)


class Jerk:
    """The patient jerks the tooth sideways: 3 mm along base x at 40 mm/s from t0, then holds."""

    def __init__(self, t0: float) -> None:
        self.t0 = t0

    def offset_mm(self, t: float):
        return (min(max(t - self.t0, 0.0) * 40.0, 3.0), 0.0, 0.0)


async def test_patient_movement_stops_the_file_tracks_and_resumes():
    jerk = Jerk(t0=6.0)
    h, rows = harness(seed=5, motion=jerk)
    rt = h.runtime
    await h.command("drill")
    await h.run_for(ticks=int(9.0 / 0.002))
    fnorm = [float(np.linalg.norm(r["wrench_h"])) for r in rows]
    first_over = next(i for i, f in enumerate(fnorm)
                      if f > 1.5 and rows[i]["t"] >= jerk.t0)
    # entered patient_moved in the very tick the force crossed 1.5 N
    assert rows[first_over]["state"] == "treating.patient_moved"
    assert rows[first_over - 1]["state"].startswith("treating.drilling")
    # the file was stopped: it spins down from 60 rpm from that tick on
    assert rows[first_over + 10]["motor_rpm"] < 0.9 * rows[first_over]["motor_rpm"]
    moved = [r for r in rows if r["state"] == "treating.patient_moved"]
    assert moved[-1]["motor_rpm"] < 5.0
    # it tracked the phantom: the tip followed most of the 3 mm jump sideways (the rest is
    # the lumen's clearance around the file and the file's bending, where no force arises)
    end, start = rows[-1], rows[first_over - 1]
    tip_dx = end["tool_pose"][0] - start["tool_pose"][0]
    assert 2.0 < tip_dx < 3.5, tip_dx
    assert float(np.linalg.norm(end["wrench_h"][:2])) < rt.cfg.thresholds.patient_release_n
    # and resumed drilling afterwards
    assert any(r["state"] == "treating.drilling.feeding" for r in rows[first_over:])
    assert rt.ctx.patient_episodes >= 1 and not any(r["fractured"] for r in rows)


async def test_emergency_stop_halts_arm_and_file_in_one_tick_and_latches():
    h, rows = harness(seed=6)
    rt, w = h.runtime, h.world
    await h.command("drill")
    await h.run_for(ticks=2000)
    assert rt.state == "treating.drilling.feeding" and w.handpiece.cmd_rpm == 60.0
    w.estop = True
    await h.run_for(ticks=1)
    assert rows[-1]["state"] == "fault"
    assert w.handpiece.cmd_rpm == 0.0 and w.handpiece.mode == "vel"
    assert all(v == 0.0 for v in w.arm.vel_cmd) or not w.arm.moving
    assert any("emergency stop" in c for c in rt.treatment.fault_causes)
    await h.run_for(ticks=500)
    assert rt.state == "fault" and max(abs(x) for x in w.arm.qdot) < 1e-3
    refusal = await h.command("reset")
    assert refusal is not None and "emergency stop" in refusal.reason
    w.estop = False
    await h.run_for(ticks=5)
    assert await h.command("reset") is None
    await h.run_for(ticks=500)
    # nothing restarts by itself
    assert rt.state == "idle" and w.handpiece.cmd_rpm == 0.0
    assert max(abs(x) for x in w.arm.qdot) < 1e-3


async def test_same_seed_same_run():
    def strip(rows):
        return [{k: v for k, v in r.items() if k not in ("compute_us", "lateness_us", "overrun")}
                for r in rows]

    runs = []
    for _ in range(2):
        h, rows = harness(seed=11, motion="head")
        await h.command("drill")
        await h.run_for(ticks=3000)
        runs.append(strip(rows))
    assert runs[0] == runs[1]
    h, rows = harness(seed=12, motion="head")
    await h.command("drill")
    await h.run_for(ticks=3000)
    assert strip(rows) != runs[0]


async def test_load_calibration_routine_identifies_the_handpiece():
    h, rows = harness(seed=7, calibrated=False)
    rt = h.runtime
    refusal = await h.command("drill")
    assert refusal is not None and "calibrat" in refusal.reason
    await h.command("calibrate_load")
    await h.run_for(until=lambda r: r.state != "calibrating.load", ticks=20_000)
    assert rt.state == "idle", rt.treatment.fault_causes
    g = rt.gravity
    # the simulated handpiece: 139 g, sensor turned 15 deg, centroid (3, -2, 45) mm
    assert g.mass_kg == pytest.approx(0.139, abs=0.002)
    assert g.mount_angle_deg == pytest.approx(15.0, abs=1.0)
    np.testing.assert_allclose(g.centroid_mm, (3.0, -2.0, 45.0), atol=2.0)
    # with it, the compensated wrench at rest is near zero (sensor noise ~0.02 N)
    await h.run_for(ticks=100)
    assert math.hypot(*rows[-1]["wrench_h"][:3]) < 0.1
    assert await h.command("drill") is None


async def test_sectioned_reversal_strategy_reaches_a_short_working_length():
    plan = TreatmentPlan(working_length_mm=6.0, orifice_gap_mm=2.0,
                         strategy=StrategyParams(name="reversal", section_mm=3.0, min_rounds=3))
    h, rows = harness(seed=8, canal=CanalParams(working_length_mm=6.0), plan=plan)
    rt = h.runtime
    await h.command("drill")
    await h.run_for(until=finished, ticks=60_000)
    assert rt.state == "done", rt.treatment.fault_causes
    finished_sections = sum("section_finished" in r["events"] for r in rows)
    assert finished_sections == 1      # two sections of 3 mm: one hand-over, then WL
    assert max(r["true_depth_mm"] for r in rows) >= 5.9
    assert not any(r["fractured"] for r in rows)


async def test_dragging_moves_the_grip_at_k_over_b_per_newton():
    """Operator hand: 1 N along base x at the grip (reference point A). Table 4.3 dragging:
    k/b = 1500/80 = 18.75 mm/s per N, no moment about A, so the grip translates."""
    h, rows = harness(seed=9)
    rt, w = h.runtime, h.world
    assert await h.command("drag") is None
    await h.run_for(ticks=10)
    w.hand_force_0 = (1.0, 0.0, 0.0)
    start = np.array(rows[-1]["tool_pose"][:3])
    await h.run_for(ticks=500)                       # 1 s
    w.hand_force_0 = (0.0, 0.0, 0.0)
    moved = np.array(rows[-1]["tool_pose"][:3]) - start
    # the tip moves with the grip (pure translation): 18.75 mm minus the servo lag (8 ms)
    assert moved[0] == pytest.approx(18.75 * (1.0 - 0.008 - 0.002), rel=0.03)
    assert abs(moved[1]) < 0.3 and abs(moved[2]) < 0.3
    rot = np.array(rows[-1]["tool_pose"][3:]) - np.array(rows[10]["tool_pose"][3:])
    assert np.max(np.abs((rot + 180.0) % 360.0 - 180.0)) < 0.5   # angles wrap at 180 deg


async def test_the_depth_limit_retracts_even_if_the_strategy_would_push_on():
    """A strategy that never stops feeding (a bug, or a mis-set working length): the
    supervisor's depth limit (working length + 0.5 mm) withdraws the file."""
    from dentibot.states.strategies import Decision, DrillingStrategy, StrategyParams

    class PushForever(DrillingStrategy):
        def step(self, tau_mnm, depth_mm):
            return Decision(0.5, 0.5, ())

    h, rows = harness(seed=10, canal=CanalParams(working_length_mm=6.0),
                      plan=TreatmentPlan(working_length_mm=6.0, orifice_gap_mm=2.0))
    rt = h.runtime
    rt.ctx.strategy = PushForever(StrategyParams(), 6.0, rt.ts)
    await h.command("drill")
    await h.run_for(until=lambda r: r.state != "treating.drilling.feeding", ticks=30_000)
    assert rt.state == "treating.retracting"
    assert any("depth_limit" in r["events"] for r in rows)
    assert max(r["depth_mm"] for r in rows) <= 6.5 + 0.05      # one tick of feed past it


def _ik_tip_at(world, point, R_target, q0):
    """Joint angles putting the (true) file tip at ``point`` with orientation ``R_target``."""
    from scipy.optimize import least_squares

    def res(q):
        T = world.kin.fk_tool(q)
        return np.concatenate([T[:3, 3] - point, 50.0 * (T[:3, :3] - R_target).ravel()])
    sol = least_squares(res, q0, xtol=1e-12, ftol=1e-12)
    assert np.abs(res(sol.x)[:3]).max() < 1e-6
    return sol.x


async def test_tcp_calibration_by_pedal_presses_finds_the_true_tool_tip():
    """The runtime starts with a tool 10 mm too short; the operator holds the tip on a fixed
    point in five orientations and presses the pedal at each (eq 3.21-3.23)."""
    from scipy.spatial.transform import Rotation

    from dentibot.runtime.config import RuntimeConfig, ToolGeometry
    from dentibot.sim.world import WorldConfig

    h = procedure(WorldConfig(seed=12),
                            RuntimeConfig(tool=ToolGeometry(tip_6_mm=(0, 0, 80.0)), tcp_points=5))
    rt, w = h.runtime, h.world
    assert rt.cfg.tool.tip_6_mm == (0, 0, 80.0)
    T0 = w.kin.fk_tool(w.arm.q)
    point = T0[:3, 3] + np.array([0.0, 0.0, 5.0])    # in the air, 7 mm above the orifice
    assert await h.command("calibrate_tcp") is None
    q = np.array(w.arm.q)
    for rx, ry in ((0, 0), (15, 0), (-15, 0), (0, 15), (0, -15)):
        R = T0[:3, :3] @ Rotation.from_euler("xy", [rx, ry], degrees=True).as_matrix()
        q = _ik_tip_at(w, point, R, q)
        w.teleport_arm(q)
        await h.run_for(ticks=3)
        w.pedal = True
        await h.run_for(ticks=2)
        w.pedal = False
        await h.run_for(ticks=2)
    assert rt.state == "idle", rt.events_log[-5:]
    np.testing.assert_allclose(rt.cfg.tool.tip_6_mm, (0.0, 0.0, 90.0), atol=0.05)
    np.testing.assert_allclose(rt.kin.fk_tool(w.arm.q)[:3, 3], point, atol=0.05)
    assert sum(e[1] == "tcp_point" for e in rt.events_log) == 4


async def test_alignment_left_running_stops_at_the_depth_limit():
    """An open-ended self-alignment pushes the file in at 6.25 mm/s per N; past the working
    length + 1.0 mm (depth estimate) the supervisor stops everything (latched fault). The
    canal's bottom is 0.5 mm past the working length, so the WL here is set 1 mm short of
    the canal's to let the push reach the limit."""
    h, rows = harness(seed=13, canal=CanalParams(working_length_mm=8.0),
                      plan=TreatmentPlan(working_length_mm=6.0, orifice_gap_mm=2.0))
    rt = h.runtime
    await h.command("align")
    await h.run_for(until=lambda r: r.state == "fault", ticks=20_000)
    assert rt.state == "fault" and "depth_limit" in rt.treatment.fault_causes[0]
    assert max(r["depth_mm"] for r in rows) <= 7.0 + 0.05


async def test_a_file_bound_while_retracting_is_withdrawn_without_turning():
    """Over the hard torque limit on the way out there is no reversal state to go to: the file
    stops turning and is withdrawn straight, instead of being left stopped in the canal."""
    h, rows = harness(seed=6)
    rt = h.runtime
    await h.command("drill")
    await h.run_for(until=lambda r: r.last_row and r.last_row["true_depth_mm"] > 6.0,
                 ticks=20_000)
    assert await h.command("retract") is None
    await h.run_for(ticks=50)
    assert rt.state == "treating.retracting" and h.world.handpiece.omega_rpm > 50.0
    k0 = rt.ticks
    limit = rt.cfg.thresholds.torque_limit_mnm
    h.world.canal.debris_mm3 += 2.0          # +60 mNm (torque_mnm_per_mm3): bound
    await h.run_for(until=lambda r: r.state != "treating.retracting", ticks=10_000)
    after = rows[k0:]
    first = next(i for i, r in enumerate(after) if "file_stopped" in r["events"])
    assert after[first - 1]["file_torque_mnm"] <= limit < after[first]["file_torque_mnm"]
    assert first <= 10
    assert abs(h.world.handpiece.omega_rpm) < 1.0 and h.world.handpiece.cmd_rpm == 0.0
    assert rt.state != "fault" and not any(r["fractured"] for r in after)
    assert after[-1]["true_depth_mm"] < 0.5           # withdrawn: back at the orifice


async def test_the_runtime_runs_the_tick_chain_of_control_tick(monkeypatch):
    """What the control-tick benchmark times (dentibot.control.tick) is what the runtime runs:
    every admittance tick goes through its functions, and their output is what the arm gets."""
    import dentibot.runtime.actuate as ct
    import dentibot.runtime.estimate as estimate
    from dentibot.control import tick

    calls = {"wrench": 0, "command": []}

    def wrench(*a):
        calls["wrench"] += 1
        return tick.sense(*a)

    def command(*a):
        cmd = tick.admittance_command(*a)
        calls["command"].append(cmd.qdot_deg_s.copy())
        return cmd

    monkeypatch.setattr(estimate, "sense", wrench)
    monkeypatch.setattr(ct, "admittance_command", command)
    h, rows = harness(seed=3)
    rt = h.runtime
    assert await h.command("align") is None
    await h.run_for(ticks=100)
    # every tick, plus once more on entering self-alignment (its reference point B is set
    # in that tick, and the wrench is moved to it again)
    assert calls["wrench"] == 101
    assert len(calls["command"]) == 100
    np.testing.assert_array_equal(rows[-1]["qdot_cmd_deg_s"], calls["command"][-1])


@pytest.mark.parametrize("mm_s", [20.0, 40.0, 60.0, 100.0])
async def test_an_axial_jerk_onto_the_file_does_not_break_it(mm_s):
    """The tooth pushed 3 mm onto the working file along the canal: the torque climbs about
    4,000 mNm/s (8 mNm per tick at 40 mm/s) while the force stays under the 1.5 N patient
    trigger, faster than the drive can turn the file round (about 10 ms) after the torque
    limit asks for the reversal. The drive's current limit, set at start to the file's safe
    torque ((55.8 + 62) / 2 = 58.9 mNm), holds the motor's torque under the 62 mNm strength
    whatever the software does."""
    h, rows = harness(seed=3)
    w = h.world
    await h.command("drill")
    assert await h.run_for(ticks=30_000, until=lambda r: r.last_row is not None
                           and r.last_row["true_depth_mm"] > 8.0)
    k0 = len(rows)
    _, axis = w.canal_axis_0()
    w.motion = MotionJerk(w.motion, w.t, tuple(-x for x in axis), mm=3.0, mm_s=mm_s)
    await h.run_for(ticks=500)
    assert w.fractured is None
    assert max(abs(r["file_torque_mnm"]) for r in rows[k0:]) < FILE_STRENGTH_MNM
    # the drive's limit: (58.9 mNm + the no-load current's share) of motor current
    assert w.handpiece.current_limit_a == pytest.approx(58.9 / (16 * 67 * 0.7) + 0.005,
                                                         rel=1e-3)




async def test_reset_after_a_drive_fault_brings_the_devices_back_to_ready():
    """The drive disables its output while drilling (no EMCY): fault; the operator's reset
    re-enables it, and the next drilling turns the file again."""
    h, rows = harness(seed=6)
    w = h.world
    await h.command("drill")
    await h.run_for(ticks=500)
    w.handpiece.enabled = False
    w.handpiece.stop()
    assert await h.run_for(ticks=50, until=lambda r: r.state == "fault")
    assert "handpiece_disabled" in h.runtime.treatment.fault_causes[0]
    assert await h.command("reset") is None
    assert h.runtime.state == "idle" and w.handpiece.enabled
    await h.run_for(ticks=10)
    assert await h.command("drill") is None
    await h.run_for(ticks=200)
    assert h.runtime.state.startswith("treating.drilling"), h.runtime.treatment.fault_causes
    assert abs(w.handpiece.omega_rpm - 60.0) < 1.0
