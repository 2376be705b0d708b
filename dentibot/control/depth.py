"""Depth along the canal: the tip's distance past a reference point along an axis."""

from __future__ import annotations

from numba import njit


@njit(cache=True)
def depth_along_xyz(tx: float, ty: float, tz: float, ox: float, oy: float, oz: float,
                    ax: float, ay: float, az: float) -> float:
    """The tip (tx, ty, tz)'s depth (mm) past the point (ox, oy, oz) along the unit axis
    (ax, ay, az): (tip - o) . a. (Compiled: the simulator's compiled drilling ticks call it.)"""
    return (tx - ox) * ax + (ty - oy) * ay + (tz - oz) * az


def depth_along(tip, depth_ref) -> float:
    """The tip's depth (mm) along ``depth_ref`` = (orifice point, unit canal axis), {0}."""
    o, a = depth_ref
    return depth_along_xyz(float(tip[0]), float(tip[1]), float(tip[2]), float(o[0]),
                           float(o[1]), float(o[2]), float(a[0]), float(a[1]), float(a[2]))


depth_along_xyz(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)   # compiled at import
