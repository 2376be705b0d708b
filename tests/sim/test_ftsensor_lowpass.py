"""The F/T reading's first-order low-pass filter (``FTSensorParams.lowpass_s``)."""

import math

import numpy as np
import pytest

from dentibot.sim.ftsensor import FTSensorModel, FTSensorParams

#: The flange pointing down (rotation's columns, then the origin), as the kernels take it.
FLANGE = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 300.0]])


def _quiet(**kw):
    """A sensor without noise or offsets, its resolution fine enough not to matter."""
    return FTSensorParams(noise_n=(0.0, 0.0, 0.0), noise_nm=0.0, offset_sigma_n=0.0,
                          offset_sigma_nm=0.0, res_n=(1e-6,) * 3, res_nm=1e-9, **kw)


def _readings(params, period_s, steps, f_after=(0.0, 0.0, -2.0)):
    s = FTSensorModel(params, np.random.default_rng(1), period_s=period_s)
    s.sample_frame(FLANGE, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    s.bias()
    out = []
    for _ in range(steps):
        s.sample_frame(FLANGE, f_after, (0.0, 0.0, 0.0))
        out.append(s.last[2])
    return np.array(out)


def test_a_step_reaches_its_first_order_share_after_each_sample():
    """After n samples of period T a step of size A reads A (1 - exp(-n T / tau)): a first
    order filter's step response, sampled (tau 0.1 s, T 2 ms)."""
    r = _readings(_quiet(lowpass_s=0.1), 0.002, 200)
    # the flange points down: {0} -z is {S} +z (no mount turn changes z)
    n = np.arange(1, 201)
    assert r == pytest.approx(2.0 * (1.0 - np.exp(-n * 0.002 / 0.1)), abs=1e-5)
    # one time constant in: 63.2 % of the step
    assert r[49] / 2.0 == pytest.approx(1.0 - math.exp(-1.0), abs=1e-4)


def test_without_a_filter_the_step_reads_at_once():
    r = _readings(_quiet(), 0.002, 3)
    assert r == pytest.approx([2.0, 2.0, 2.0], abs=1e-5)


def test_the_first_reading_starts_the_filter_without_a_transient():
    """A sensor switched on under load reads the load at once, filtered or not (the gauges'
    offsets must not ring in)."""
    s = FTSensorModel(_quiet(lowpass_s=0.1), np.random.default_rng(1))
    s.sample_frame(FLANGE, (0.0, 0.0, -3.0), (0.0, 0.0, 0.0))
    first = s.raw[2]
    s.sample_frame(FLANGE, (0.0, 0.0, -3.0), (0.0, 0.0, 0.0))
    assert s.raw[2] == pytest.approx(first, abs=1e-6)


@pytest.mark.parametrize("bad", [-0.01, math.nan, math.inf])
def test_a_bad_time_constant_is_refused_with_its_value(bad):
    with pytest.raises(ValueError, match="lowpass_s"):
        FTSensorParams(lowpass_s=bad)
