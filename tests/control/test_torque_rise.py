"""The file torque projected along its slope (the reversal starts before the limit)."""

from __future__ import annotations

import pytest

from dentibot.control.torque_rise import TorqueRise, TorqueRiseParams
from dentibot.errors import ConfigError

TS = 0.002


def test_a_steady_ramp_is_projected_by_its_slope_times_the_horizon():
    """A ramp of 2,000 mNm/s (15 -> 68 mNm in 26 ms): once the 4 ms filter has settled the
    slope is the ramp's, and the projection 12 ms ahead is tau + 24 mNm."""
    r = TorqueRise(TorqueRiseParams(horizon_s=0.012, filter_s=0.004), TS)
    tau = 15.0
    for _ in range(20):                       # 40 ms = 10 filter time constants
        ahead = r.step(tau)
        tau += 2000.0 * TS
    assert r.slope_mnm_s == pytest.approx(2000.0, rel=1e-3)
    assert ahead == pytest.approx((tau - 2000.0 * TS) + 24.0, rel=1e-3)


def test_a_rise_no_steeper_than_drilling_is_not_projected():
    """500 mNm/s, drilling's own ripple: the projection is the torque itself."""
    r = TorqueRise(ts=TS)
    tau = 45.0
    for _ in range(30):
        ahead = r.step(tau)
        tau += 500.0 * TS
    assert r.slope_mnm_s == pytest.approx(500.0, rel=1e-3)
    assert ahead == pytest.approx(tau - 500.0 * TS)


def test_a_falling_or_flat_torque_is_not_projected():
    r = TorqueRise(ts=TS)
    for k in range(50):
        ahead = r.step(40.0 - 0.5 * k)
    assert r.slope_mnm_s < 0.0 and ahead == pytest.approx(40.0 - 0.5 * 49)
    r.reset()
    assert [r.step(30.0) for _ in range(5)] == [30.0] * 5


def test_bad_parameters_name_the_field():
    with pytest.raises(ConfigError, match="horizon_s"):
        TorqueRiseParams(horizon_s=0.0)
