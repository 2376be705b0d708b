"""Shaping the canal: the red area (eq 6.1) is removed by repeated passes to working length."""

from __future__ import annotations

import itertools

import numpy as np
from world_drive import depth

from dentibot.sim import World, WorldConfig


def _peck_to_working_length(world: World, seconds: float, tau_max: float = 35.0,
                            dwell_s: float = 3.0) -> None:
    """A simple gentle protocol: 60 rpm, feed 0.5 mm/s while the torque is under ``tau_max``;
    over it: turn back 90 deg and withdraw 1 mm; at working length: turn for ``dwell_s``, then
    withdraw to 1 mm depth."""
    hp = world.handpiece
    hp.set_velocity(60.0)
    wl = world.canal.p.working_length_mm
    state, mark, k, d = "feed", 0.0, 0, 0.0
    end = world.t + seconds
    while world.t < end:
        d = depth(world) if k % 5 == 0 else d
        if state == "feed":
            if abs(hp.torque_mnm) > tau_max:
                hp.move_relative(-90.0)
                state = "reverse"
            elif d >= wl:
                state, mark = "dwell", world.t + dwell_s
            v = 0.5
        elif state == "dwell":       # keep turning at working length to finish the shape
            v = 0.0
            if world.t >= mark:
                state, mark = "out", 1.0
        elif state == "reverse":
            v = 0.0
            if hp.move_done:
                hp.set_velocity(60.0)
                state, mark = "back", d - 1.0
        else:  # back / out: withdraw to mark
            v = -2.0
            if d <= mark:
                state = "feed"
        if k % 5 == 0:
            world.arm.command_velocity(world.tool_rates((0.0, 0.0, v)), world.t)
        world.step()
        k += 1
        assert world.fractured is None


def test_completeness_starts_at_zero_and_exceeds_99_percent():
    world = World(WorldConfig(seed=7, orifice_gap_mm=0.5))
    assert world.completeness() == 0.0
    red0 = world.canal.red_area_mm2().copy()
    # independent check of the initial red area: the stained canal (20 um into the wall) as
    # photographed, width 2 (R0 + 0.02) per slice of 0.25 mm
    s = (np.arange(64) + 0.5) * 0.25
    r0 = (0.15 + 0.02 * (16.0 - s)) / 2
    np.testing.assert_allclose(red0, 2 * (r0 + 0.02) * 0.25)
    history = []
    for _ in range(10):
        _peck_to_working_length(world, 25.0)
        history.append(world.completeness())
    assert all(b >= a for a, b in itertools.pairwise(history))
    assert history[-1] > 0.99, history
    assert world.canal.shaping() > 0.9
    assert (world.canal.red_area_mm2() <= red0 + 1e-12).all()


def test_a_canal_already_at_the_target_shape_is_shaped_but_still_red():
    from dentibot.sim.canal import Canal, CanalParams

    c = Canal(CanalParams(initial_apical_mm=0.25, initial_taper=0.06))
    assert c.shaping() == 1.0 and c.completeness() == 0.0


def test_world_completeness_is_the_canals_and_follows_every_cut():
    """The world keeps the canal's completeness between cuts (the telemetry asks every tick);
    every cut that removes material is seen at once."""
    world = World(WorldConfig(seed=3, orifice_gap_mm=0.5))
    canal = world.canal
    assert world.completeness() == canal.completeness() == 0.0
    v0 = canal.version
    _peck_to_working_length(world, 15.0)
    assert canal.version > v0                      # the file cut the lumen
    assert world.completeness() == canal.completeness() > 0.0
    before, v1 = world.completeness(), canal.version
    assert canal.cut(0.0) == 0.0 and canal.version == v1      # nothing removed: no change
    assert world.completeness() == before
    _peck_to_working_length(world, 15.0)
    assert canal.version > v1
    assert world.completeness() == canal.completeness() > before
