"""Handpiece motor model: speed loop, limits, reversal move, current, stall."""

from __future__ import annotations

import math

import numpy as np
import pytest
from world_drive import drive

from dentibot.errors import ConfigError
from dentibot.sim import HandpieceModel, HandpieceParams, World, WorldConfig


def _hp(**kw) -> HandpieceModel:
    return HandpieceModel(HandpieceParams(**kw), np.random.default_rng(0))


def test_first_order_speed_response_and_free_current():
    hp = _hp(current_noise_a=0.0)
    hp.set_velocity(60.0)
    for _ in range(5):                      # 10 ms = one time constant (discrete first order)
        hp.step(0.002, 0.0, 0.0)
    assert hp.omega_rpm == pytest.approx(60.0 * (1 - math.exp(-1)))
    assert hp.current_a == pytest.approx(0.005)          # friction only


def test_speed_above_200_rpm_is_refused():
    hp = _hp()
    with pytest.raises(ConfigError) as e:
        hp.set_velocity(201.0)
    assert e.value.field == "handpiece.rpm"


def test_current_follows_the_load_through_gear_and_efficiency():
    hp = _hp(current_noise_a=0.0)
    hp.set_velocity(60.0)
    for _ in range(100):
        hp.step(0.002, 30.0, 9.0)
    # 30 mNm / (16 mNm/A * 67 * 0.7) + 5 mA
    assert hp.current_a == pytest.approx(30.0 / (16 * 67 * 0.7) + 0.005)
    assert hp.p.file_torque_estimate_mnm(hp.current_a, hp.omega_rpm) == pytest.approx(30.0)


def test_move_relative_turns_back_90_degrees_then_holds():
    hp = _hp()
    hp.set_velocity(60.0)
    for _ in range(100):
        hp.step(0.002, 10.0, 3.0)
    p0 = hp.pos_deg
    hp.move_relative(-90.0)
    n = 0
    while not hp.move_done and n < 1000:
        hp.step(0.002, 10.0, 3.0)
        n += 1
    assert hp.pos_deg - p0 == pytest.approx(-90.0, abs=0.5)
    assert n * 0.002 < 0.5                  # at 100 rpm (600 deg/s) plus ramps
    for _ in range(50):
        hp.step(0.002, 10.0, 3.0)
    assert hp.pos_deg - p0 == pytest.approx(-90.0, abs=0.5)


def test_a_weak_motor_stalls_instead_of_breaking_the_file():
    world = World(WorldConfig(seed=1, handpiece=HandpieceParams(current_limit_a=0.02)))
    world.handpiece.set_velocity(60.0)
    drive(world, (0.0, 0.0, 1.0), 14.0)
    assert world.handpiece.stalled
    assert world.handpiece.omega_rpm == pytest.approx(0.0, abs=0.1)
    assert world.fractured is None
    assert world.handpiece.torque_mnm <= 0.02 * 16 * 67 * 0.7 + 1e-9


def test_float_fk_matches_the_kinematics_module():
    world = World(WorldConfig())
    fk = world.kin.flange_floats
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.uniform(-150, 150, 6)
        R, p = fk(q)
        t = world.kin.fk(q)
        np.testing.assert_allclose(np.array(R), t[:3, :3], atol=1e-12)
        np.testing.assert_allclose(p, t[:3, 3], atol=1e-9)
