"""Patient / phantom motion profiles: offset (mm, base-frame axes) of the phantom vs time.

Platform axes are taken parallel to the robot base axes (assumption: the Stewart platform is
set up square to the robot).
"""

from __future__ import annotations

import itertools
import math
from typing import Protocol

import numpy as np


class MotionProfile(Protocol):
    def offset_mm(self, t: float) -> tuple[float, float, float]:
        """Phantom translation (mm) at time ``t`` (s)."""
        ...


class StaticPose:
    """No motion (or a fixed offset, e.g. set through the platform interface)."""

    def __init__(self, offset_mm=(0.0, 0.0, 0.0)) -> None:
        self.offset = tuple(float(x) for x in offset_mm)

    def offset_mm(self, t: float) -> tuple[float, float, float]:
        return self.offset


#: Thesis experiment 1: square corners (mm) in platform coordinates.
SQUARE_MM = ((0.0, 0.0, 0.0), (15.0, 0.0, 0.0), (15.0, 0.0, 15.0), (0.0, 0.0, 15.0),
             (0.0, 0.0, 0.0))


class StewartSquare:
    """Thesis experiment 1: 15 x 15 mm square at 3, 4, 5, 6 mm/s, 10 s pauses between squares.

    Each square is 60 mm: 20, 15, 12, 10 s; with three 10 s pauses, 87 s in all. Before
    ``start_s`` and after the end the phantom rests at the origin.
    """

    def __init__(self, speeds_mm_s=(3.0, 4.0, 5.0, 6.0), pause_s: float = 10.0,
                 start_s: float = 0.0) -> None:
        self.start_s = start_s
        # segments: (t_start, t_end, p_from, p_to)
        segs = []
        t = 0.0
        for k, v in enumerate(speeds_mm_s):
            if k:
                t += pause_s
            for a, b in itertools.pairwise(SQUARE_MM):
                d = math.dist(a, b) / v
                segs.append((t, t + d, a, b))
                t += d
        self.segments = segs
        self.duration_s = t

    def offset_mm(self, t: float) -> tuple[float, float, float]:
        t -= self.start_s
        if t <= 0.0 or t >= self.duration_s:
            return (0.0, 0.0, 0.0)
        for t0, t1, a, b in self.segments:
            if t < t0:
                return a  # pause: at the corner reached (the origin)
            if t <= t1:
                x = (t - t0) / (t1 - t0)
                return (a[0] + (b[0] - a[0]) * x, a[1] + (b[1] - a[1]) * x,
                        a[2] + (b[2] - a[2]) * x)
        return (0.0, 0.0, 0.0)


class HeadMotion:
    """Small smooth random head motion: a sum of sinusoids per axis with seeded phases.

    assumption: amplitude about 1 mm rms per axis, frequencies 0.05-0.5 Hz (slow head drift and
    breathing-like sway of a patient holding still).
    """

    def __init__(self, rng: np.random.Generator, amplitude_mm: float = 1.0,
                 n_components: int = 4, f_min_hz: float = 0.05, f_max_hz: float = 0.5) -> None:
        self.freq = rng.uniform(f_min_hz, f_max_hz, (3, n_components)) * 2.0 * math.pi
        self.phase = rng.uniform(0.0, 2.0 * math.pi, (3, n_components))
        # each component amplitude so that the axis rms is amplitude_mm
        self.amp = amplitude_mm * math.sqrt(2.0 / n_components)
        self._f = self.freq.tolist()
        self._ph = self.phase.tolist()
        self._base = [[math.sin(p) for p in row] for row in self._ph]

    def offset_mm(self, t: float) -> tuple[float, float, float]:
        a = self.amp
        return tuple(
            a * sum(math.sin(f * t + p) - b for f, p, b in zip(fr, ph, bs))
            for fr, ph, bs in zip(self._f, self._ph, self._base)
        )


class BenchSquarePath:
    """The thesis bench's platform as it really moved in experiment 1 (fitted, see
    :mod:`dentibot.sim.bench_physics`): a closed loop in the platform's vertical plane, the
    same shape in every square, run in ``durations_s`` per square with ``pauses_s`` between.

    The shape is a periodic piecewise-linear curve of the square's time phase
    ``phi = (t - t_square) / duration`` in [0, 1): ``knots_mm`` are its (x, y, z) at
    ``phi = i / n`` (Stewart frame: x the square's horizontal travel, y out of the plane, z
    the platform normal, up). Wavy legs, the drift off the plane and the speed changes along
    the loop are all in the knots. The Stewart frame is turned ``frame_yaw_deg`` about base z
    from the robot's base -y axis (x_S = Rz(yaw) (0, -1, 0)); z_S is base z. Before
    ``start_s`` and after the end the phantom rests at the origin.
    """

    def __init__(self, knots_mm, durations_s, pauses_s, frame_yaw_deg: float = 0.0,
                 start_s: float = 0.0) -> None:
        k = np.asarray(knots_mm, float)
        if k.ndim != 2 or k.shape[1] != 3 or len(k) < 4:
            raise ValueError("knots_mm: n x 3 (x, y, z), n >= 4")
        self.knots = np.vstack([k, k[:1]])            # closed
        self.n = len(k)
        self.durations_s = tuple(float(d) for d in durations_s)
        pauses = tuple(float(p) for p in pauses_s)
        if len(pauses) != len(self.durations_s) - 1:
            raise ValueError("one pause between consecutive squares")
        self.start_s = float(start_s)
        starts, t = [], 0.0
        for i, d in enumerate(self.durations_s):
            starts.append(t)
            t += d + (pauses[i] if i < len(pauses) else 0.0)
        self.square_starts_s = tuple(starts)
        self.duration_s = t
        c, s = math.cos(math.radians(frame_yaw_deg)), math.sin(math.radians(frame_yaw_deg))
        self.ex, self.ey = (s, -c, 0.0), (c, s, 0.0)
        self._k = self.knots.tolist()

    def stewart_mm(self, t: float) -> tuple[float, float, float]:
        """Platform position (mm, Stewart frame) at world time ``t``."""
        t -= self.start_s
        if t <= 0.0 or t >= self.duration_s:
            return (0.0, 0.0, 0.0)
        for t0, d in zip(self.square_starts_s, self.durations_s):
            if t0 <= t < t0 + d:
                u = (t - t0) / d * self.n
                i = int(u)
                f = u - i
                a, b = self._k[i], self._k[i + 1]
                return (a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f,
                        a[2] + (b[2] - a[2]) * f)
        return tuple(self._k[0])

    def offset_mm(self, t: float) -> tuple[float, float, float]:
        x, y, z = self.stewart_mm(t)
        ex, ey = self.ex, self.ey
        return (x * ex[0] + y * ey[0], x * ex[1] + y * ey[1], z)
