"""The drilling states' compiled decisions on synthetic inputs with known answers."""

import numpy as np
import pytest

from dentibot.control.feedrate import FeedrateParams
from dentibot.control.torque_rise import TorqueRise
from dentibot.states import feeding_kernels as fk
from dentibot.states.strategies import StrategyParams, make_strategy


@pytest.mark.parametrize("force,depth,fz,code", [
    (1.6, 10.0, 0.0, fk.GUARD_PATIENT_MOVED),      # ||f|| over 1.5 N first
    (1.6, 20.0, -9.0, fk.GUARD_PATIENT_MOVED),
    (1.0, 16.6, -9.0, fk.GUARD_DEPTH_LIMIT),       # 16 + 0.5 mm
    (1.0, 16.4, -5.1, fk.GUARD_FORCE_LIMIT),       # pushing 5.1 N > 5 N
    (1.0, 16.4, -4.9, 0),
])
def test_drilling_guard(force, depth, fz, code):
    assert fk.drilling_guard(force, 1.5, True, depth, 16.0 + 0.5, fz, 5.0) == code


def test_an_unknown_depth_is_no_depth_limit():
    assert fk.drilling_guard(0.0, 1.5, False, 99.0, 16.5, 0.0, 5.0) == 0


def test_regulated_strategy_waits_out_its_blanking_and_yields_to_the_working_length():
    # tau_d 40, kp 0.025: a steady 60 mNm gives fz* = -0.5 N < -0.2 N (reversal); the
    # restart blanking of 0.1 s at 2 ms is 50 ticks without a reversal.
    s = make_strategy(StrategyParams(feedrate=FeedrateParams(kd_n_s_per_mnm=0.0)), 16.0, 0.002)
    s.start_pass(5.0)
    decisions = [s.step(60.0, 5.0) for _ in range(52)]
    assert decisions[0].fz_star_n == pytest.approx(0.025 * (40.0 - 60.0))
    assert decisions[0].fz_n == pytest.approx(-0.5)
    assert [d.events for d in decisions[49:]] == [(), ("reversal_needed",),
                                                   ("reversal_needed",)]
    assert s.step(60.0, 16.0).events == ("working_length_reached",)


def test_constant_feed():
    s = make_strategy(StrategyParams(name="none", constant_fz_n=0.3), 16.0, 0.002)
    d = s.step(80.0, 3.0)
    assert (d.fz_n, d.fz_star_n, d.events) == (0.3, 0.3, ())
    assert s.step(0.0, 16.5).events == ("working_length_reached",)


def test_feeding_checks_limit_then_projected_rise():
    r = TorqueRise(ts=0.002)
    args = (r._a, r.ts, r.p.min_slope_mnm_s, r.p.horizon_s)
    assert fk.feeding_checks(0, 50.5, 300.0, 270.0, 50.0, r.st, *args)[0] == fk.REVERSE_LIMIT
    # the strategy already reverses: nothing more
    assert fk.feeding_checks(fk.REVERSAL_NEEDED, 60.0, 300.0, 270.0, 50.0, r.st, *args)[0] == 0
    # 3,000 mNm/s from 20 mNm: the filtered slope settles at 3,000, so 12 ms ahead is 36 mNm
    # above the torque: past 50 mNm while the torque itself is still under it
    r.reset()
    tau, code, ahead = 20.0, 0, 0.0
    for _ in range(20):
        tau += 3000.0 * 0.002
        code, ahead = fk.feeding_checks(0, tau, 300.0, 270.0, 100.0, r.st, *args)
    assert r.slope_mnm_s == pytest.approx(3000.0, rel=1e-3)
    assert ahead == pytest.approx(tau + 36.0, rel=1e-3)
    code, _ = fk.feeding_checks(0, 45.0, 300.0, 270.0, 50.0, np.array([1.0, 39.0, 3000.0]),
                                *args)
    assert code == fk.REVERSE_RISE
    # spinning up (200 < 270 rpm): the projection is off
    code, ahead = fk.feeding_checks(0, 45.0, 200.0, 270.0, 50.0, np.array([1.0, 39.0, 3000.0]),
                                    *args)
    assert (code, ahead) == (0, 45.0)


def test_a_run_compiles_nothing_after_import():
    """The kernels the drilling states call are called with the types they were compiled
    for at import: a call with an int where a float was compiled (or, from another kernel,
    a literal bool) would compile again, inside a tick (in real time, a missed deadline and
    a lost drive heartbeat). Simulated runs, tick by tick and compiled, add no signature."""
    from dentibot.control import depth, feedrate, torque_rise
    from dentibot.experiments import preclinical as pc

    kernels = (fk.drilling_guard, fk.strategy_decision, fk.feeding_checks, fk.overloaded,
               fk.retracted, fk.reversal_over, feedrate.pd_step, torque_rise.rise_step,
               depth.depth_along_xyz)
    before = [list(k.signatures) for k in kernels]
    phantom = pc.phantoms(1)[0]
    for strategy in ("automated", "none"):
        pc.run_phantom(pc.PreclinicalSpec(phantom, strategy=strategy, rounds_s=(8.0,)))
    assert [list(k.signatures) for k in kernels] == before
