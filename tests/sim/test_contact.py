"""File-canal contact, torque, reversal, withdrawal and fracture."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from world_drive import depth, drive

from dentibot.sim import CanalParams, World, WorldConfig
from dentibot.sim.nitifile import NiTiFile


def _mean_torque(world: World, seconds: float) -> float:
    n = round(seconds / world.ts)
    acc = 0.0
    for _ in range(n):
        world.step()
        acc += world.handpiece.torque_mnm
    return acc / n


def _sensor_force_0(world: World, n: int = 50) -> np.ndarray:
    """Mean sensor force turned into {0} (N)."""
    th = np.radians(world.config.sensor.mount_angle_deg)
    rz = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    acc = np.zeros(3)
    for _ in range(n):
        world.step()
        acc += world.flange_rotation @ rz @ np.array(world.sensor.last[:3])
    return acc / n


def test_free_space_gives_no_contact_force(world):
    before = _sensor_force_0(world)
    drive(world, (1.0, -0.5, 0.5), 1.0)   # moves about, tip stays above the orifice
    world.run(0.1)
    assert depth(world) < 0.0
    assert world.contact_force_0 == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(_sensor_force_0(world), before, atol=0.01)


def test_sideways_press_pushes_towards_the_canal_axis(world):
    drive(world, (0.0, 0.0, 1.0), 7.0)            # 2 mm gap, then 5 mm into the canal
    assert depth(world) == pytest.approx(5.0, abs=0.05)
    before = _sensor_force_0(world)
    drive(world, (0.5, 0.2, 0.0), 0.6)            # 0.32 mm sideways
    world.run(0.1)
    after = _sensor_force_0(world)
    o, t0 = world.canal_axis_0()
    r = np.subtract(world.tip_0, o)
    to_axis = -(r - np.dot(r, t0) * np.asarray(t0))
    assert np.linalg.norm(to_axis) == pytest.approx(np.hypot(0.3, 0.12), abs=0.02)
    to_axis /= np.linalg.norm(to_axis)
    df = after - before                            # what the sensor sees, gravity cancels
    lateral = df - np.dot(df, t0) * np.asarray(t0)
    assert np.linalg.norm(lateral) > 0.1            # well above the 0.01 N resolution
    assert np.dot(lateral, to_axis) / np.linalg.norm(lateral) > 0.98
    # a file is a soft cantilever: at 0.32 mm the force stays below its tip stiffness bound
    k_max = NiTiFile().lateral_stiffness_n_mm(16.0)
    assert np.linalg.norm(lateral) < k_max * 0.33


def test_torque_rises_with_insertion_into_a_narrower_lumen(world):
    hp = world.handpiece
    hp.set_velocity(60.0)
    drive(world, (0.0, 0.0, 1.0), 2.0)             # across the 2 mm gap to the orifice
    torques = {}
    for target in range(1, 13):
        drive(world, (0.0, 0.0, 0.5), 2.0)         # 1 mm per bin at 0.5 mm/s
        assert depth(world) == pytest.approx(target, abs=0.05)
        torques[target] = _mean_torque(world, 0.02)
    # engagement starts when the file's orifice diameter exceeds the lumen's:
    # 0.25 + 0.06 s = 0.15 + 0.02 * 16  ->  s = 3.67 mm (s = depth of the tip)
    assert abs(torques[2]) < 1.0 and abs(torques[3]) < 1.0
    assert torques[4] > 0.0
    deep = [torques[k] for k in range(4, 13)]
    assert all(b > a for a, b in itertools.pairwise(deep)), deep
    # the current-based estimate (documented efficiency and friction) tracks the torque
    est = hp.p.file_torque_estimate_mnm(hp.current_a, hp.omega_rpm)
    assert est == pytest.approx(hp.torque_mnm, abs=4.0)


def _inserted_cutting_world(seed=2) -> World:
    w = World(WorldConfig(seed=seed))
    w.handpiece.set_velocity(60.0)
    drive(w, (0.0, 0.0, 0.6), 20.0)   # tip at about 10 mm, cutting, debris accumulated
    return w


def test_reversal_and_withdrawal_lower_the_torque():
    a, b = _inserted_cutting_world(), _inserted_cutting_world()
    t_before = _mean_torque(a, 0.05)
    _mean_torque(b, 0.05)
    assert t_before > 15.0
    # b turns back 90 deg, then resumes; a keeps turning forward
    b.handpiece.move_relative(-90.0)
    reverse = []
    while not b.handpiece.move_done:
        b.step()
        a.step()
        reverse.append(b.handpiece.torque_mnm)
    assert min(reverse) < 0.0 and max(abs(x) for x in reverse) < t_before
    b.handpiece.set_velocity(60.0)
    ta, tb = _mean_torque(a, 0.2), _mean_torque(b, 0.2)
    assert tb < ta - 1.0                     # debris cleared by the reversal
    drive(b, (0.0, 0.0, -1.0), 2.0)          # withdraw 2 mm
    tw = _mean_torque(b, 0.2)
    assert tw < tb - 5.0


def test_exceeding_the_strength_fractures_the_file(world):
    world.handpiece.set_velocity(60.0)
    drive(world, (0.0, 0.0, 2.0), 10.0, until=lambda w: w.fractured is not None)
    f = world.fractured
    assert f is not None and f.cause == "torsion"
    assert f.torque_mnm > world.file.torsional_strength_mnm
    assert 3.67 < f.depth_mm < 16.0
    world.run(0.2)
    assert world.contact_force_0 == (0.0, 0.0, 0.0)
    assert world.handpiece.torque_mnm == 0.0
    assert abs(world.handpiece.omega_rpm - 60.0) < 1.0     # spins free: nothing transmitted


def test_rotation_in_a_curve_fatigues_the_file_by_miners_rule():
    canal = CanalParams(curve_start_mm=8.0, curve_radius_mm=5.0, curve_angle_deg=40.0,
                        initial_apical_mm=0.25, initial_taper=0.06)   # already shaped
    w = World(WorldConfig(seed=4, canal=canal))
    drive(w, (0.0, 0.0, 1.0), 14.0)
    s_tip = depth(w)
    assert s_tip == pytest.approx(12.0, abs=0.05)
    w.handpiece.set_velocity(200.0)
    t0 = w.t
    while w.fractured is None and w.t < t0 + 300.0:
        w.step()
    assert w.fractured is not None and w.fractured.cause == "fatigue"
    # thickest point inside the arc: first slice centre past 8 mm (8.125); strain d / (2 rho)
    d = 0.25 + 0.06 * (s_tip - 8.125)
    n_f = (1.0 / (d / (2 * 5.0))) ** 2          # eps = C N^-b, C = 1, b = 0.5
    cycles = (w.fractured.t - t0) * 200.0 / 60.0
    assert cycles == pytest.approx(n_f, rel=0.02)


def _interact(tilt_deg: float, offset_mm: float, depth_mm: float = 3.0, **canal):
    """A straight #25/.06 file 3 mm deep in a straight canal, turned by ``tilt_deg`` about
    {P}'s y axis with its tip ``offset_mm`` off the centreline along x."""
    from dentibot.sim.canal import Canal

    canal = Canal(CanalParams(**canal))
    a = np.radians(tilt_deg)
    canal._entered, canal._last_depth = True, depth_mm
    return canal.interact((offset_mm, 0.0, depth_mm), (np.sin(a), 0.0, np.cos(a)),
                          NiTiFile(), 0.002)


def _push(direction_deg: float, offset_mm: float = 0.3, **canal):
    """The file's tip ``offset_mm`` off the centreline towards ``direction_deg`` from {P}'s x
    axis, the file parallel to the canal, 3 mm deep: the lateral force's magnitude (N)."""
    from dentibot.sim.canal import Canal

    c = Canal(CanalParams(**canal))
    c._entered, c._last_depth = True, 3.0
    a = np.radians(direction_deg)
    it = c.interact((offset_mm * np.cos(a), offset_mm * np.sin(a), 3.0), (0.0, 0.0, 1.0),
                    NiTiFile(), 0.002)
    return float(np.linalg.norm(it.f_lat))


def test_an_anisotropic_support_is_its_axis_compliance_along_each_axis():
    """A holder softer along {P}'s y (0.5 mm/N along x, 2.0 along y): pushed along x the file
    loads it as an isotropic 0.5 mm/N support, along y as a 2.0 one. At 45 deg the compliance
    along the push is 0.5 cos^2 + 2.0 sin^2 = 1.25 mm/N; the tooth also moves across the push
    (more along y), so the second contact meets the wall a little off it: within 3 % of an
    isotropic 1.25 mm/N support."""
    aniso = {"support_mm_per_n": 0.5, "support_y_mm_per_n": 2.0}
    assert _push(0.0, **aniso) == pytest.approx(_push(0.0, support_mm_per_n=0.5), rel=1e-9)
    assert _push(90.0, **aniso) == pytest.approx(_push(90.0, support_mm_per_n=2.0), rel=1e-9)
    assert _push(45.0, **aniso) == pytest.approx(_push(45.0, support_mm_per_n=1.25), rel=0.03)
    assert _push(90.0, **aniso) < 0.5 * _push(0.0, **aniso)


def test_a_negative_support_compliance_is_refused():
    from dentibot.errors import ConfigError

    with pytest.raises(ConfigError, match="support_y_mm_per_n"):
        CanalParams(support_y_mm_per_n=-1.0)


def test_a_file_tilted_in_the_canal_is_turned_by_a_couple_towards_its_axis():
    """Tip on the centreline, file turned 10 deg: its line leaves the lumen near the orifice
    (0.53 mm off at 3 mm up) and the bent file presses the far wall at the tip. The walls push
    the orifice end one way and the tip the other: the moment about the tip, -axis x m_lat,
    turns the file's axis back towards the canal's (about -y), and its arm is longer than the
    resultant alone would give (a couple)."""
    it = _interact(10.0, 0.0)
    f, g = np.asarray(it.f_lat), np.asarray(it.m_lat)
    a = np.radians(10.0)
    axis = np.array([np.sin(a), 0.0, np.cos(a)])
    moment = -np.cross(axis, g)                  # N*mm about the tip
    assert moment[1] < -1.0                       # more than 1 N*mm, turning z towards the axis
    assert np.linalg.norm(g) > 3.0 * np.linalg.norm(f)   # the arm exceeds the 3 mm depth
    # straight and centred: the file is free in its lumen (#15/.02 around a #25/.06 tip)
    free = _interact(0.0, 0.0)
    assert free.f_lat == (0.0, 0.0, 0.0) and free.m_lat == (0.0, 0.0, 0.0)


def test_a_file_pushed_sideways_bends_as_a_cantilever_of_its_own_stiffness():
    """Straight file, 0.3 mm off the centreline along its whole part in the canal: both ends
    press the same wall, so the load is one-sided, and no more than the sum of the file's own
    stiffnesses at the two ends times their rigid penetrations (the loads' coupling through
    the beam and the wall in series only soften it)."""
    it = _interact(0.0, 0.3)
    f = np.asarray(it.f_lat)
    assert f[0] < 0.0 and abs(f[1]) < 1e-12       # back towards the axis
    lumen = lambda s: (0.15 + 0.02 * (16.0 - s)) / 2.0          # noqa: E731 (#15/.02, WL 16)
    pen_tip = 0.3 + 0.125 - lumen(2.875)                        # tip slice centre 2.875 mm
    pen_orifice = 0.3 + (0.25 + 0.06 * 2.875) / 2.0 - lumen(0.125)
    file = NiTiFile()
    bound = file.lateral_stiffness_n_mm(0.0) * pen_tip + \
        file.lateral_stiffness_n_mm(2.75) * pen_orifice
    assert 0.5 * bound < -f[0] <= bound


def test_a_compliant_tooth_support_softens_a_push_and_leaves_a_couple_alone():
    """The support moves the tooth as a body: it adds the same compliance to every pair of
    contacts. A file pushed sideways (both ends one way) then loads it less; a tilted file
    (a couple: opposite loads) bends the same, since a rigid translation cancels in it."""
    push0, push1 = (np.asarray(_interact(0.0, 0.3, **kw).f_lat)
                    for kw in ({}, {"support_mm_per_n": 1.0}))
    assert abs(push1[0]) < 0.6 * abs(push0[0])
    c0, c1 = _interact(10.0, 0.0), _interact(10.0, 0.0, support_mm_per_n=1.0)
    f0, f1 = np.asarray(c0.f_lat), np.asarray(c1.f_lat)
    g0, g1 = np.asarray(c0.m_lat), np.asarray(c1.m_lat)
    # the couple part (moment arms beyond the resultant's) is kept within 25 %
    assert np.linalg.norm(g1 - 3.0 * f1) == pytest.approx(np.linalg.norm(g0 - 3.0 * f0), rel=0.25)
