"""A fault cause found by the supervisor or an observer."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Finding:
    """A fault cause: ``kind`` (short key), ``detail`` (cause, value, limit)."""

    kind: str
    detail: str

    def __str__(self) -> str:
        return f"{self.kind}: {self.detail}"
