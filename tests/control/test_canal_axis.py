"""Self-alignment's orientation loop: the canal's direction from the file's bending."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dentibot.control.canal_axis import AxisServoParams, CanalAxisServo
from dentibot.control.filebeam import NITI_E_MPA, FileBeam
from dentibot.errors import ConfigError

TS = 0.002


def _wrench(p_orifice, p_tip, depth):
    """The wrench at the tip in {H} of lateral loads (x, y; N) at the orifice (``depth`` mm up
    the file, towards -z) and at the tip: force sum, moment (r x F) about the tip (N*m)."""
    po, pt = np.asarray(p_orifice, float), np.asarray(p_tip, float)
    f = po + pt
    r = np.array([0.0, 0.0, -depth * 1e-3])                 # the orifice from the tip (m)
    m = np.cross(r, [po[0], po[1], 0.0])
    return np.array([f[0], f[1], 0.0, *m])


def _settled(servo, depth, wrench, seconds=1.0):
    for _ in range(round(seconds / TS)):
        servo.step(depth, wrench)
    return servo


def test_a_couple_on_a_uniform_file_reads_the_chord_of_the_beam_formulas():
    """A near-uniform 1 mm file, 21 mm long, 4 mm deep: a tip load of 0.3 N one way and an
    orifice load of 0.2 N the other. With c(x1, x2) = x1^2 (3 x2 - x1) / 6EI the chord from
    the orifice to the tip turns by (w_t - w_o) / d, computed here by hand."""
    beam = FileBeam(size=100, taper=1e-9, length_mm=21.0)
    ei = NITI_E_MPA * math.pi / 64
    L, d = 21.0, 4.0
    a = L - d

    def c(x1, x2):
        x1, x2 = sorted((x1, x2))
        return x1**2 * (3 * x2 - x1) / (6 * ei)

    pt, po = 0.3, -0.2
    w_t = c(L, L) * pt + c(L, a) * po
    w_o = c(a, L) * pt + c(a, a) * po
    want = (w_t - w_o) / d
    servo = _settled(CanalAxisServo(beam, ts=TS), d, _wrench((po, 0.0), (pt, 0.0), d))
    assert servo.tilt[0] == pytest.approx(want, rel=5e-3)
    assert servo.tilt[1] == pytest.approx(0.0, abs=1e-12)
    # it turns z towards +x: a rotation about +y, at gain x angle (or the rate bound)
    w = servo.twist()
    assert w[4] > 0.0 and w[3] == pytest.approx(0.0, abs=1e-12) and w[5] == 0.0
    rate = min(10.0 * math.atan(abs(want)), math.radians(20.0))
    assert w[4] == pytest.approx(rate, rel=1e-2)


def test_a_bias_read_out_of_the_canal_is_taken_off_inside_it():
    """The sensor reads a constant 0.05 N / 2 N*mm offset: out of the canal it is the tare,
    so in the canal with no load the loop sees a straight file."""
    beam = FileBeam()
    bias = np.array([0.05, -0.02, 0.0, 0.002, -0.001, 0.0])
    servo = _settled(CanalAxisServo(beam, ts=TS), -1.0, bias, 0.5)
    _settled(servo, 3.0, bias, 0.5)
    assert np.allclose(servo.tilt, 0.0, atol=1e-9)
    assert servo.twist() is None and servo.feed_scale() == 1.0


def test_the_feed_is_held_while_the_file_is_bent_through_a_tilt():
    beam = FileBeam()
    servo = CanalAxisServo(beam, AxisServoParams(hold_deg=1.0, stop_deg=3.0), ts=TS)
    for deg, scale in ((0.5, 1.0), (2.0, 0.5), (4.0, 0.0)):
        servo.tilt = np.array([math.tan(math.radians(deg)), 0.0])
        assert servo.feed_scale() == pytest.approx(scale)
    assert servo.angle_rad == pytest.approx(math.radians(4.0))


def test_shallower_than_the_readable_depth_nothing_turns():
    servo = _settled(CanalAxisServo(FileBeam(), ts=TS), 0.5,
                     _wrench((-0.2, 0.0), (0.3, 0.0), 0.5))
    assert servo.twist() is None


def test_bad_parameters_name_the_field_and_the_limit():
    with pytest.raises(ConfigError, match="stop_deg"):
        AxisServoParams(hold_deg=2.0, stop_deg=1.0)
    with pytest.raises(ConfigError, match="gain_per_s"):
        AxisServoParams(gain_per_s=0.0)


def test_the_loads_build_up_as_a_first_order_filter_from_zero():
    """A constant tip load F from the first period in the canal: after n periods the filtered
    load is F (1 - (1 - a)^n), a = ts / (filter_s + ts), and the chord's tilt (linear in the
    loads; no orifice load: (c(0,0) - c(0,d)) F / d) follows the same curve."""
    beam = FileBeam()
    p = AxisServoParams()
    servo = CanalAxisServo(beam, p, ts=TS)
    d, f = 4.0, 0.2
    tip_only = np.array([f, 0.0, 0.0, 0.0, 0.0, 0.0])
    settled = (beam.compliance_mm_n(0.0, 0.0) - beam.compliance_mm_n(0.0, d)) * f / d
    a = TS / (p.filter_s + TS)
    for n in (1, 5, 40):
        servo.reset()
        _settled(servo, d, tip_only, n * TS)
        assert servo.tilt[0] == pytest.approx(settled * (1.0 - (1.0 - a) ** n), rel=1e-9)
    # leaving the canal drops the loads: back in, they build up from zero again
    _settled(servo, -1.0, np.zeros(6), TS)
    _settled(servo, d, tip_only, TS)
    assert servo.tilt[0] == pytest.approx(settled * a, rel=1e-9)
