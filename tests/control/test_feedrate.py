"""File feedrate control and reversal trigger (thesis 5.3-5.4)."""

import pytest

from dentibot.control.feedrate import (
    FeedrateController,
    FeedrateParams,
    current_limit_a,
    file_torque_from_current,
)
from dentibot.errors import ConfigError


def test_current_limit_of_eq_5_6():
    # 62 mNm / (67 * 16 mNm/A) = 0.05784 A
    assert current_limit_a() == pytest.approx(62.0 / (67 * 16))
    assert file_torque_from_current(0.05) == pytest.approx(0.05 * 16 * 67)
    assert file_torque_from_current(0.05, efficiency=0.7) == pytest.approx(0.05 * 16 * 67 * 0.7)


def test_steady_state_is_proportional_and_saturated():
    p = FeedrateParams(tau_d_mnm=40.0, kp_n_per_mnm=0.025)
    ctl = FeedrateController(p)
    for tau, fz in [(40.0, 0.0), (36.0, 0.1), (44.0, -0.1), (0.0, 0.5), (100.0, -0.5)]:
        ctl.reset()
        for _ in range(500):  # constant torque: the derivative term dies out
            out = ctl.step(tau)
        assert out.fz_n == pytest.approx(fz, abs=1e-9)
    assert out.fz_star_n == pytest.approx(0.025 * (40 - 100))


def test_reversal_triggers_above_tau_d_plus_threshold_over_kp():
    p = FeedrateParams(tau_d_mnm=40.0, kp_n_per_mnm=0.025, reversal_threshold_n=-0.2)
    assert p.reversal_torque_mnm == pytest.approx(48.0)
    ctl = FeedrateController(p)
    for tau, rev in [(47.9, False), (48.1, True)]:
        ctl.reset()
        for _ in range(500):
            out = ctl.step(tau)
        assert out.reverse is rev


def test_derivative_reacts_to_a_rising_torque_before_the_level_does():
    # A torque ramp of 100 mNm/s: the filtered derivative settles at 100, so fz* is lower than
    # the proportional part alone by kd * 100 = 0.05 N.
    p = FeedrateParams(kp_n_per_mnm=0.025, kd_n_s_per_mnm=0.0005, kd_filter_s=0.02)
    ctl = FeedrateController(p, ts=0.002)
    tau = 0.0
    for _ in range(200):
        tau += 100.0 * 0.002
        out = ctl.step(tau)
    assert out.fz_star_n == pytest.approx(0.025 * (40.0 - tau) - 0.0005 * 100.0, abs=1e-3)


@pytest.mark.parametrize("field,kw", [
    ("tau_d_mnm", {"tau_d_mnm": 500.0}),
    ("tau_d_mnm", {"tau_d_mnm": 0.0}),
    ("fz_min_n", {"fz_min_n": 0.6}),
    ("reversal_threshold_n", {"reversal_threshold_n": 0.1}),
    ("kp_n_per_mnm", {"kp_n_per_mnm": 0.0}),
])
def test_bad_parameters_name_the_field(field, kw):
    with pytest.raises(ConfigError, match=field):
        FeedrateParams(**kw)
