"""The protocol's freshness bound on the F/T stream against the F/T driver's own (the device
file's): when the driver's is tighter it acts first, and a run says so before it starts."""

from __future__ import annotations

from dentibot.app.device_bounds import stale_bound_conflict
from dentibot.app.runner import ProtocolRunner
from dentibot.io.devices import loopback_config
from dentibot.logs import configure_logging
from dentibot.protocol.loader import parse_protocol

STEPS = "steps:\n  - calibrate_load: {}\n  - drag: {duration_s: 0.1}\n"


def _protocol(ft_periods: int, rate_hz: int = 500):
    return parse_protocol(f"name: t\ncontrol: {{rate_hz: {rate_hz}}}\n"
                          f"limits: {{stale_periods: {{ft: {ft_periods}}}}}\n" + STEPS)


def test_a_bound_looser_than_the_drivers_is_named_with_both_values():
    # 50 periods of 2 ms = 100 ms against the driver's 20 ms hardware default
    text = stale_bound_conflict(_protocol(50), loopback_config())
    assert "limits.stale_periods.ft is 50 periods (100 ms)" in text
    assert "ft.stale_after_ms 20 ms" in text
    # 25 periods at 250 Hz are 100 ms as well
    assert "(100 ms)" in stale_bound_conflict(_protocol(25, 250), loopback_config())


def test_no_conflict_when_the_driver_is_as_loose_or_the_protocol_tighter():
    assert stale_bound_conflict(_protocol(50), loopback_config(ft_stale_after_ms=100)) is None
    assert stale_bound_conflict(_protocol(4), loopback_config()) is None      # 8 ms < 20 ms
    assert stale_bound_conflict(_protocol(10), loopback_config()) is None     # 20 ms: equal


def test_a_run_on_devices_reports_it_before_it_starts(capsys):
    configure_logging("warning")
    ProtocolRunner(_protocol(50), devices=loopback_config(), no_record=True)
    assert "ft.stale_after_ms 20 ms" in capsys.readouterr().err
    ProtocolRunner(_protocol(50), devices=loopback_config(ft_stale_after_ms=100),
                   no_record=True)
    assert "stale_after_ms" not in capsys.readouterr().err
