"""Typed errors shared by every layer.

A leaf module: it imports nothing of DentiBot, so even the pure ``control`` layer may raise
these. Every error carries what the user needs to act on it: which device or field, which
value, which limit.
"""

from __future__ import annotations


class DentibotError(Exception):
    """Base of every error DentiBot raises on purpose."""


class ConfigError(DentibotError, ValueError):
    """A configuration or protocol value is missing, malformed or out of range.

    ``field`` names the offending field (dotted path), ``value`` the value given and
    ``limit`` the allowed range or choices, so the message can be acted on without a debugger.
    """

    def __init__(self, field: str, value: object, limit: str, detail: str = "") -> None:
        self.field = field
        self.value = value
        self.limit = limit
        self.detail = detail
        msg = f"{field} = {value!r} is not allowed: {limit}"
        if detail:
            msg += f" ({detail})"
        super().__init__(msg)

    def __reduce__(self):
        """Pickled with its fields (it crosses process boundaries: batch workers, the
        recorder process)."""
        return type(self), (self.field, self.value, self.limit, self.detail)


class IdentificationError(DentibotError, ValueError):
    """A calibration or identification data set cannot determine the parameters.

    ``condition`` is the condition number found, ``limit`` the largest accepted, and ``advice``
    says which measurements to add.
    """

    def __init__(self, what: str, condition: float, limit: float, advice: str) -> None:
        self.what = what
        self.condition = condition
        self.limit = limit
        self.advice = advice
        super().__init__(
            f"{what}: condition number {condition:.3g} exceeds the limit {limit:.3g}; {advice}"
        )


class KinematicsError(DentibotError, ValueError):
    """A kinematic request is impossible (joint out of range, singular configuration...)."""


class DeviceFault(DentibotError):
    """A device reported or showed a fault. ``device`` names it."""

    def __init__(self, device: str, message: str) -> None:
        self.device = device
        super().__init__(f"{device}: {message}")


class ProtocolError(DentibotError):
    """Bytes on a wire that do not follow the device's protocol. ``device`` names it."""

    def __init__(self, device: str, message: str) -> None:
        self.device = device
        super().__init__(f"{device}: {message}")
