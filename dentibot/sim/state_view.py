"""Attributes of the simulator's components as views on their kernels' state arrays.

The compiled kernels (``dentibot/sim/*_kernels.py``) keep a component's state in a float
array, one field per index; the component's class names those fields as attributes with
these property factories, so that the rest of the product reads ``canal.debris_mm3`` and
not ``canal.st[4]``.
"""

from __future__ import annotations

from operator import attrgetter


def scalar(array: str, i: int, kind: type = float, doc: str | None = None,
           settable: bool = True) -> property:
    """Field ``i`` of the instance's array attribute ``array``, read as ``kind`` (float, int,
    bool); written as it is given (a bool stores 1.0 or 0.0)."""
    arr = attrgetter(array)

    def get(self):
        return kind(arr(self)[i])

    def put(self, x) -> None:
        arr(self)[i] = x

    return property(get, put if settable else None, doc=doc)


def vector(array: str, i: int, n: int, doc: str | None = None,
           settable: bool = True) -> property:
    """Fields ``i .. i + n - 1`` of the instance's array attribute ``array`` as a tuple of
    floats; written from any sequence of ``n`` numbers."""
    arr = attrgetter(array)

    def get(self) -> tuple:
        return tuple(arr(self)[i:i + n].tolist())

    def put(self, v) -> None:
        arr(self)[i:i + n] = v

    return property(get, put if settable else None, doc=doc)


def listed(array: str, row: int | None = None, doc: str | None = None) -> property:
    """The instance's array attribute ``array`` (or its row ``row``) as a list of floats,
    read-only (the kernels write it)."""
    arr = attrgetter(array)
    if row is None:
        return property(lambda self: arr(self).tolist(), doc=doc)
    return property(lambda self: arr(self)[row].tolist(), doc=doc)
