"""Patient / phantom motion profiles."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dentibot.sim import HeadMotion, StewartSquare, World, WorldConfig


def test_stewart_square_timing_matches_the_thesis():
    sq = StewartSquare()
    assert sq.duration_s == pytest.approx(87.0)   # 20 + 15 + 12 + 10 s, three 10 s pauses
    assert sq.offset_mm(2.5) == pytest.approx((7.5, 0.0, 0.0))     # 3 mm/s along x
    assert sq.offset_mm(5.0) == pytest.approx((15.0, 0.0, 0.0))
    assert sq.offset_mm(10.0) == pytest.approx((15.0, 0.0, 15.0))
    assert sq.offset_mm(25.0) == pytest.approx((0.0, 0.0, 0.0))    # pausing
    assert sq.offset_mm(30.0 + 15.0 / 4.0 / 2) == pytest.approx((7.5, 0.0, 0.0))  # 4 mm/s
    assert sq.offset_mm(77.0 + 2.5) == pytest.approx((15.0, 0.0, 0.0))           # 6 mm/s
    assert sq.offset_mm(100.0) == (0.0, 0.0, 0.0)


def test_phantom_follows_the_profile_in_the_world():
    w = World(WorldConfig(motion="square"))
    o0 = np.array(w.phantom_origin_0())
    w.run(2.5)
    np.testing.assert_allclose(np.array(w.phantom_origin_0()) - o0, (7.5, 0.0, 0.0), atol=1e-9)


def test_head_motion_is_smooth_small_and_seeded():
    a = HeadMotion(np.random.default_rng(1))
    b = HeadMotion(np.random.default_rng(1))
    c = HeadMotion(np.random.default_rng(2))
    t = np.arange(0.0, 120.0, 0.002)
    xa = np.array([a.offset_mm(x) for x in t[::50]])
    assert a.offset_mm(0.0) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert a.offset_mm(12.3) == b.offset_mm(12.3) != c.offset_mm(12.3)
    assert 0.3 < np.std(xa, axis=0).min() and np.abs(xa).max() < 8.0
    # smooth: max speed bounded by sum of amplitude * omega (<= 4 * 0.71 * 2 pi 0.5 mm/s)
    v = np.diff(xa, axis=0) / 0.1
    assert np.abs(v).max() < 4 * math.sqrt(0.5) * 2 * math.pi * 0.5


def test_a_turning_jerk_turns_the_phantom_about_its_centre():
    """5 deg about base x through a hinge 80 mm below the orifice: the canal's axis turns by
    5 deg about x and the orifice swings on an 80 mm radius (Rodrigues, checked against
    scipy's rotation)."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from dentibot.sim import World, WorldConfig
    from dentibot.sim.faults import Jerk

    w = World(WorldConfig(seed=1))
    o0, a0 = (np.array(v) for v in w.canal_axis_0())
    centre = o0 - np.array([0.0, 0.0, 80.0])
    w.motion = Jerk(w.motion, w.t, mm=0.0, deg=5.0, axis=(1.0, 0.0, 0.0), centre_mm=centre,
                    deg_s=50.0)
    for _ in range(100):                                     # 0.2 s: the turn is over
        w.step()
    R = Rotation.from_euler("x", 5.0, degrees=True).as_matrix()
    o, a = (np.array(v) for v in w.canal_axis_0())
    np.testing.assert_allclose(a, R @ a0, atol=1e-12)
    np.testing.assert_allclose(o, centre + R @ (o0 - centre), atol=1e-9)
    np.testing.assert_allclose(w.phantom_rotation, R @ w.phantom_pose[:3, :3], atol=1e-12)


def test_tremor_lies_in_its_band_with_its_rms():
    """A sum of three sinusoids of amplitude a sqrt(2/3) per axis: rms a over a long window;
    its spectrum's peak between 8 and 12 Hz."""
    from dentibot.sim.patient import Tremor

    tr = Tremor(np.random.default_rng(4), amplitude_mm=0.05, deg=0.02)
    t = np.arange(0.0, 60.0, 0.002)
    x = np.array([tr.offset_mm(ti) for ti in t])
    x -= x.mean(axis=0)
    np.testing.assert_allclose(np.sqrt((x**2).mean(axis=0)), 0.05, rtol=0.1)
    spec = np.abs(np.fft.rfft(x[:, 0]))
    f = np.fft.rfftfreq(len(t), 0.002)
    assert 8.0 <= f[np.argmax(spec)] <= 12.0
    ang = np.array([tr.angle_rad(ti) for ti in t])
    assert np.degrees(np.std(ang)) == pytest.approx(0.02, rel=0.1)


def test_swallows_come_about_once_a_minute_and_go_back():
    """Intervals drawn in 30..90 s; each swallow a raised-cosine bump: the full 3 mm and 3 deg
    half-way through its second, nothing before or after."""
    from dentibot.sim.patient import Swallowing

    sw = Swallowing(np.random.default_rng(7), horizon_s=600.0)
    gaps = np.diff((0.0, *sw.starts_s))
    assert len(sw.starts_s) >= 600.0 / 90.0 - 1 and ((gaps >= 30.0) & (gaps <= 90.0)).all()
    t0 = sw.starts_s[0]
    assert sw.level(t0 - 0.01) == 0.0 and sw.level(t0 + 1.01) == 0.0
    assert sw.level(t0 + 0.5) == pytest.approx(1.0)
    assert np.linalg.norm(sw.offset_mm(t0 + 0.5)) == pytest.approx(3.0)
    assert np.degrees(sw.angle_rad(t0 + 0.5)) == pytest.approx(3.0)


def test_a_swallowing_patient_turns_the_tooth_about_the_jaw_hinge():
    """A world with a swallowing patient: at the first swallow's peak the orifice has moved
    3 mm towards the robot along the canal, and the 3 deg turn about the hinge 60 mm beyond it
    has taken it 60 sin 3 deg = 3.1 mm across and 60 (1 - cos 3 deg) = 0.08 mm back along
    the canal; the world's phantom orientation has turned by 3 deg."""
    from dentibot.sim import World, WorldConfig

    w = World(WorldConfig(seed=2, motion="swallowing"))
    o0, a0 = (np.asarray(x) for x in w.canal_axis_0())
    t_peak = w.motion.parts[0].starts_s[0] + 0.5
    w.t = t_peak                          # the patient's motion is a function of time
    w._rotate_patient(w.t)
    o1 = np.asarray(w.phantom_origin_0())
    R = w.phantom_rotation @ np.asarray(w._RP0).T
    assert np.degrees(np.arccos((np.trace(R) - 1.0) / 2.0)) == pytest.approx(3.0, abs=1e-6)
    d = o1 - o0
    assert np.dot(d, -a0) == pytest.approx(3.0 - 60.0 * (1 - np.cos(np.radians(3.0))), abs=1e-6)
    assert np.linalg.norm(d - np.dot(d, a0) * a0) == pytest.approx(
        60.0 * np.sin(np.radians(3.0)), abs=1e-6)
