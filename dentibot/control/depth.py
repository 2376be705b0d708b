"""Depth along the canal: the tip's distance past a reference point along an axis."""

from __future__ import annotations


def depth_along(tip, depth_ref) -> float:
    """The tip's depth (mm) along ``depth_ref`` = (orifice point, unit canal axis), {0}."""
    o, a = depth_ref
    return (tip[0] - o[0]) * a[0] + (tip[1] - o[1]) * a[1] + (tip[2] - o[2]) * a[2]
