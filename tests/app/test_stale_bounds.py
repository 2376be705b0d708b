"""The protocol's freshness bound on the F/T stream against the F/T driver's own (the device
file's): when the driver's is tighter it acts first, and the run says so before it starts."""

from __future__ import annotations

from dentibot.app.runner import ProtocolRunner
from dentibot.io.devices import loopback_config
from dentibot.logs import configure_logging
from dentibot.protocol.loader import parse_protocol

#: 50 periods at the default 500 Hz: 100 ms
LOOSE = ("name: t\nlimits: {stale_periods: {ft: 50}}\n"
         "steps:\n  - calibrate_load: {}\n  - drag: {duration_s: 0.1}\n")


def test_a_protocol_bound_looser_than_the_drivers_is_reported(capsys):
    configure_logging("warning")
    ProtocolRunner(parse_protocol(LOOSE), devices=loopback_config(), no_record=True)
    err = capsys.readouterr().err
    assert "limits.stale_periods.ft is 50 periods (100 ms)" in err
    assert "ft.stale_after_ms 20 ms" in err


def test_no_report_when_the_driver_is_as_loose(capsys):
    configure_logging("warning")
    ProtocolRunner(parse_protocol(LOOSE), devices=loopback_config(ft_stale_after_ms=100.0), no_record=True)
    ProtocolRunner(parse_protocol(LOOSE.replace("ft: 50", "ft: 4")), devices=loopback_config(),
                   no_record=True)                       # 8 ms, inside the driver's 20 ms
    assert "stale_after_ms" not in capsys.readouterr().err
