"""A protocol's ``world`` and ``simulator`` section: the world fitted to the thesis bench
unless it names the thesis's world (the ideal arm, a drag-free canal, Table 4.3's admittance)
or asks for other physics, which then reach the world the run steps; the controller's
defaults go with the world."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dentibot.app.runner import runtime_config, world_config
from dentibot.protocol.loader import ProtocolFileError, parse_protocol
from dentibot.sim.arm import ArmParams
from dentibot.sim.bench_physics import BENCH
from dentibot.sim.world import World

BASE = """\
name: t
seed: 1
phantom: {working_length_mm: 14.5, tilt_deg: 3.0}
steps:
  - drill: {strategy: automated, tau_d_mnm: 40, rounds: [{duration_s: 10}]}
"""


@pytest.mark.parametrize("extra", ["", "world: bench\n"])
def test_by_default_the_bench_world_the_fitted_arm_and_drag_and_the_controller_for_them(extra):
    p = parse_protocol(BASE + extra)
    assert p.world == "bench"
    cfg = world_config(p)
    assert (cfg.arm.vel_dead_time_s, cfg.arm.vel_gain, cfg.arm.servo_tau_s) == \
        (0.016, 0.804, 0.0063)
    assert (cfg.canal.drag_n_s_per_mm, cfg.canal.drag_depth_mm) == (0.21, 16.5)
    plan = runtime_config(p).plan
    assert (plan.lateral_free_ref_mm, plan.axial_lag_s) == (18.0, 0.060)


def test_the_thesis_world_is_the_ideal_arm_no_drag_and_table_4_3_alone():
    p = parse_protocol(BASE + "world: thesis\n")
    assert p.world == "thesis"
    cfg = world_config(p)
    assert cfg.arm == ArmParams()
    assert cfg.arm.vel_dead_time_s == 0.0 and cfg.arm.vel_gain == 1.0
    assert cfg.canal.drag_n_s_per_mm == 0.0 and cfg.canal.drag_coulomb_n == 0.0
    plan = runtime_config(p).plan
    assert (plan.lateral_free_ref_mm, plan.axial_lag_s) == (0.0, None)


def test_keys_a_protocol_gives_win_over_its_world():
    p = parse_protocol(BASE + "world: thesis\nsimulator: {arm: bench}\n"
                              "control: {axial_lag_ms: 60}\n")
    cfg = world_config(p)
    assert cfg.arm.vel_gain == 0.804 and cfg.canal.drag_n_s_per_mm == 0.0
    plan = runtime_config(p).plan
    assert (plan.lateral_free_ref_mm, plan.axial_lag_s) == (0.0, 0.060)


@pytest.mark.parametrize("world", ["mars", "[bench, thesis]", "{bench: 1}"])
def test_an_unknown_world_is_refused_naming_the_field(world):
    with pytest.raises(ProtocolFileError) as e:
        parse_protocol(BASE + f"world: {world}\n")
    assert "world" in str(e.value) and "bench" in str(e.value) and "thesis" in str(e.value)


def test_the_bench_arm_and_drag_reach_the_world_and_the_phantom_stays():
    p = parse_protocol(BASE + "simulator: {arm: bench, canal_drag: bench}\n")
    cfg = world_config(p)
    assert (cfg.arm.vel_dead_time_s, cfg.arm.vel_gain, cfg.arm.servo_tau_s) == \
        (0.016, 0.804, 0.0063)
    c = cfg.canal
    assert (c.drag_n_s_per_mm, c.drag_coulomb_n, c.drag_static_factor,
            c.drag_still_coulomb_n, c.drag_lat_n_s_per_mm, c.drag_depth_mm) == \
        (0.21, 0.02, 1.0, 1.2, 0.10, 16.5)
    # the protocol's phantom, not the bench's: its working length, tilt, bottom and support
    assert (c.working_length_mm, c.tilt_deg) == (14.5, 3.0)
    assert c.bottom_n_mm != BENCH.bottom_n_mm and c.support_mm_per_n == 0.0


def test_the_bench_arm_in_the_world_realises_0_8_of_a_command_after_16_ms():
    """A constant joint-velocity command on the world built from the protocol: nothing moves
    before the dead time (16 ms = 8 periods), then the rate settles at 0.804 of the command
    (first order, 6.3 ms lag)."""
    w = World(world_config(parse_protocol(BASE + "simulator: {arm: bench}\n")))
    q0 = np.array(w.arm.q, dtype=float)
    cmd = np.array([2.0, 0.0, 0.0, 0.0, 0.0, 0.0])     # deg/s on J1
    rates = []
    for _ in range(100):
        w.arm.command_velocity(cmd, w.t)
        w.step()
        rates.append(w.arm.qdot[0])
    assert max(abs(r) for r in rates[:7]) < 1e-9
    assert rates[-1] == pytest.approx(2.0 * 0.804, rel=1e-3)
    assert np.array(w.arm.q)[0] - q0[0] > 0.0
    assert math.isfinite(rates[-1])


def test_an_unknown_physics_is_refused_naming_the_field():
    with pytest.raises(ProtocolFileError) as e:
        parse_protocol(BASE + "simulator: {arm: real}\n")
    msg = str(e.value)
    assert "simulator.arm" in msg and "real" in msg
