"""A protocol's freshness bounds against the drivers' own, from the device file.

Two bounds guard the F/T stream: the F/T driver's ``ft.stale_after_ms`` (the device file) and
the protocol's ``limits.stale_periods.ft`` (control periods). The tighter one acts first, so a
protocol that loosens its bound beyond the driver's (a loaded machine talking to simulators
over loopback, say) does not get what it asked for; :func:`stale_bound_conflict` says so in
words that a run logs before it starts and a session adds to its connect reply."""

from __future__ import annotations

from dentibot.io.devices import DevicesConfig
from dentibot.protocol.schema import Protocol


def stale_bound_conflict(protocol: Protocol, devices: DevicesConfig) -> str | None:
    """Why the protocol's F/T freshness bound cannot take effect on ``devices``, or None."""
    periods = protocol.limits.stale_periods.ft
    ms = periods * 1000.0 / protocol.control.rate_hz
    if devices.ft.stale_after_ms >= ms:
        return None
    return (f"limits.stale_periods.ft is {periods} periods ({ms:g} ms), looser than the F/T "
            f"driver's own bound ft.stale_after_ms {devices.ft.stale_after_ms:g} ms in the "
            "device file, which acts first: raise that too for the protocol's bound to take "
            "effect")
