"""Patient / phantom motion profiles: offset (mm, base-frame axes) of the phantom vs time,
and for a patient's 6-DoF motion also a turn about the jaw's hinge (``rotation_at``).

Platform axes are taken parallel to the robot base axes (assumption: the Stewart platform is
set up square to the robot).
"""

from __future__ import annotations

import bisect
import itertools
import math
from typing import Protocol

import numpy as np
from numba import njit


class MotionProfile(Protocol):
    def offset_mm(self, t: float) -> tuple[float, float, float]:
        """Phantom translation (mm) at time ``t`` (s)."""
        ...


def offsets_mm(motion, times: np.ndarray) -> np.ndarray:
    """The motion's offsets (mm, n x 3) at the ``times`` (s): its own ``offsets_mm`` where it
    has one (the same numbers, many at once), else ``offset_mm`` time by time."""
    many = getattr(motion, "offsets_mm", None)
    if many is not None:
        return many(times)
    return np.array([motion.offset_mm(t) for t in times.tolist()], dtype=float).reshape(-1, 3)


class StaticPose:
    """No motion (or a fixed offset, e.g. set through the platform interface)."""

    def __init__(self, offset_mm=(0.0, 0.0, 0.0)) -> None:
        self.offset = tuple(float(x) for x in offset_mm)

    def offset_mm(self, t: float) -> tuple[float, float, float]:
        return self.offset

    def offsets_mm(self, times: np.ndarray) -> np.ndarray:
        return np.tile(np.array(self.offset), (len(times), 1))


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
        self._base = np.array([[math.sin(p) for p in row] for row in self.phase.tolist()])
        self._one = np.zeros((1, 3))

    def offset_mm(self, t: float) -> tuple[float, float, float]:
        out = self._one
        _sway(self.freq, self.phase, self._base, self.amp, np.array([float(t)]), out)
        return tuple(out[0].tolist())

    def offsets_mm(self, times: np.ndarray) -> np.ndarray:
        out = np.empty((len(times), 3))
        _sway(self.freq, self.phase, self._base, self.amp, np.asarray(times, dtype=float), out)
        return out


@njit(cache=True)
def _sway(freq: np.ndarray, phase: np.ndarray, base: np.ndarray, amp: float,
          times: np.ndarray, out: np.ndarray) -> None:
    """:class:`HeadMotion` at the ``times``: per axis ``amp * sum(sin(w t + p) - sin(p))``
    (zero at t = 0), into ``out`` (n x 3)."""
    for j in range(times.shape[0]):
        t = times[j]
        for axis in range(3):
            s = 0.0
            for c in range(freq.shape[1]):
                s += math.sin(freq[axis, c] * t + phase[axis, c]) - base[axis, c]
            out[j, axis] = amp * s


_sway(np.zeros((3, 1)), np.zeros((3, 1)), np.zeros((3, 1)), 0.0, np.zeros(1),
      np.zeros((1, 3)))       # compiled (or loaded from numba's cache) at import


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

    No two squares of a real platform are the same: ``wander_mm`` (rms per Stewart axis) adds
    to each square its own smooth deviation from the loop, piecewise linear through
    ``wander_points`` random offsets around the loop (zero at its start and end, so every
    square still starts and ends at rest), drawn from ``rng``.

    Nor does a real platform only translate: ``tilt_rad_per_mm`` (roll about x_S per mm of
    x_S travel, pitch about y_S per mm of z_S travel) turns it as it moves, about the centre
    its position is measured at (``centre_mm``, {0} at rest, set by whoever places the
    phantom), so that a point below that centre (the canal) moves across the measured path:
    :meth:`rotation_at`, as a patient's turn, for the world.
    """

    def __init__(self, knots_mm, durations_s, pauses_s, frame_yaw_deg: float = 0.0,
                 start_s: float = 0.0, wander_mm=(0.0, 0.0, 0.0), wander_points: int = 12,
                 rng: np.random.Generator | None = None, tilt_rad_per_mm=(0.0, 0.0),
                 centre_mm=(0.0, 0.0, 0.0)) -> None:
        k = np.asarray(knots_mm, float)
        if k.ndim != 2 or k.shape[1] != 3 or len(k) < 4:
            raise ValueError("knots_mm: n x 3 (x, y, z), n >= 4")
        self.knots = np.vstack([k, k[:1]])            # closed
        self.n = len(k)
        self.durations_s = tuple(float(d) for d in durations_s)
        self._wander = self._draw_wander(wander_mm, wander_points, rng)
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
        tilt = tuple(float(x) for x in tilt_rad_per_mm)
        if len(tilt) != 2 or not all(math.isfinite(x) for x in tilt):
            raise ValueError(f"tilt_rad_per_mm: (roll per mm of x, pitch per mm of z), "
                             f"finite, got {tilt_rad_per_mm!r}")
        self.tilt_rad_per_mm = tilt
        self.centre_mm = tuple(float(x) for x in centre_mm)

    def _draw_wander(self, rms_mm, points: int, rng) -> list | None:
        """Per square, the wander's offsets (mm) at ``points + 1`` phases around the loop
        (first and last zero); None without wander. Linear interpolation between independent
        offsets has 2/3 of their variance on average: they are drawn with rms / sqrt(2/3)."""
        rms = np.asarray(rms_mm, float)
        if rms.shape != (3,) or np.any(rms < 0.0):
            raise ValueError(f"wander_mm: three rms values >= 0 (mm), got {rms_mm!r}")
        if not rms.any():
            return None
        if points < 2:
            raise ValueError(f"wander_points: at least 2, got {points}")
        rng = rng if rng is not None else np.random.default_rng(0)
        out = []
        for _ in self.durations_s:
            w = np.zeros((points + 1, 3))
            w[1:-1] = rng.standard_normal((points - 1, 3)) * rms / math.sqrt(2.0 / 3.0)
            out.append(w.tolist())
        return out

    def stewart_mm(self, t: float) -> tuple[float, float, float]:
        """Platform position (mm, Stewart frame) at world time ``t``."""
        t -= self.start_s
        if t <= 0.0 or t >= self.duration_s:
            return (0.0, 0.0, 0.0)
        for j, (t0, d) in enumerate(zip(self.square_starts_s, self.durations_s)):
            if t0 <= t < t0 + d:
                phase = (t - t0) / d
                x, y, z = _along(self._k, phase)
                if self._wander is not None:
                    wx, wy, wz = _along(self._wander[j], phase)
                    return (x + wx, y + wy, z + wz)
                return (x, y, z)
        return tuple(self._k[0])

    def offset_mm(self, t: float) -> tuple[float, float, float]:
        x, y, z = self.stewart_mm(t)
        ex, ey = self.ex, self.ey
        return (x * ex[0] + y * ey[0], x * ex[1] + y * ey[1], z)

    def rotation_at(self, t: float):
        """(0R, centre): the platform's turn at ``t`` (small angles: the rotation vector
        roll x_S + pitch y_S) about its measured centre at rest ({0}, mm)."""
        kr, kp = self.tilt_rad_per_mm
        if not (kr or kp):
            return _IDENTITY, self.centre_mm
        x, _, z = self.stewart_mm(t)
        a, b = kr * x, kp * z
        ex, ey = self.ex, self.ey
        v = (a * ex[0] + b * ey[0], a * ex[1] + b * ey[1], 0.0)
        ang = math.hypot(v[0], v[1])
        if ang == 0.0:
            return _IDENTITY, self.centre_mm
        return axis_angle_matrix((v[0] / ang, v[1] / ang, 0.0), ang), self.centre_mm

    def centre_at(self, t: float) -> tuple[float, float, float]:
        """Where the platform's position is measured ({0}, mm) at ``t``."""
        o, c = self.offset_mm(t), self.centre_mm
        return (c[0] + o[0], c[1] + o[1], c[2] + o[2])


_IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def _along(points, phase: float) -> tuple[float, float, float]:
    """The point at ``phase`` in [0, 1) of the piecewise-linear curve through ``points``
    (n + 1 of them, equally spaced in phase, the last one the curve's end)."""
    u = phase * (len(points) - 1)
    i = int(u)
    f = u - i
    a, b = points[i], points[i + 1]
    return (a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f, a[2] + (b[2] - a[2]) * f)


# ---------------------------------------------------------------------------- the jaw
#: The jaw's hinge: this far (mm) beyond a canal's orifice along the canal. assumption: the
#: mandible's condyles and the head's nodding axis are 60 to 100 mm from a molar; the nearer
#: end makes a turn felt most at the file.
JAW_HINGE_MM = 60.0


def jaw_hinge(orifice, axis) -> tuple[tuple, tuple]:
    """The jaw's hinge for a tooth whose canal starts at ``orifice`` along the unit ``axis``
    (both {0}): its centre, :data:`JAW_HINGE_MM` beyond the orifice along the canal, and its
    unit axis across the canal (``axis`` x base x, or x base y when the canal lies along x)."""
    a = [float(x) for x in axis]
    e = (1.0, 0.0, 0.0) if abs(a[0]) < 0.9 else (0.0, 1.0, 0.0)
    n = (a[1] * e[2] - a[2] * e[1], a[2] * e[0] - a[0] * e[2], a[0] * e[1] - a[1] * e[0])
    k = math.sqrt(sum(x * x for x in n))
    return (tuple(float(orifice[i]) + JAW_HINGE_MM * a[i] for i in range(3)),
            tuple(x / k for x in n))


def axis_angle_matrix(axis, rad: float) -> tuple:
    """The rotation by ``rad`` about the unit ``axis`` (Rodrigues' formula), as nested tuples
    (a tick's worth of scalar maths, no array allocation)."""
    c, s, (x, y, z) = math.cos(rad), math.sin(rad), axis
    k = 1.0 - c
    return ((c + x * x * k, x * y * k - z * s, x * z * k + y * s),
            (y * x * k + z * s, c + y * y * k, y * z * k - x * s),
            (z * x * k - y * s, z * y * k + x * s, c + z * z * k))


class Tremor:
    """Physiological tremor of the head and jaw: per axis a sum of sinusoids at seeded
    frequencies in ``band_hz`` and phases, ``amplitude_mm`` rms per axis, and a turn about the
    jaw's hinge of ``deg`` rms.

    Physiological tremor lies at 8-12 Hz (Elble & Koller, Tremor, 1990), of the order of
    10-50 um at an outstretched hand; the head, far heavier, moves less: assumption 0.01 mm and
    0.005 deg rms (5 um at a molar 60 mm from the hinge). A file held 10 mm deep in a canal
    is laterally stiff (several N/mm near the shank), so even this reaches the force sensor.
    """

    def __init__(self, rng: np.random.Generator, amplitude_mm: float = 0.01,
                 deg: float = 0.005, band_hz=(8.0, 12.0), n_components: int = 3) -> None:
        lo, hi = band_hz
        w = rng.uniform(lo, hi, (4, n_components)) * 2.0 * math.pi
        ph = rng.uniform(0.0, 2.0 * math.pi, (4, n_components))
        self._w, self._ph = w.tolist(), ph.tolist()
        self._base = [[math.sin(p) for p in row] for row in self._ph]
        k = math.sqrt(2.0 / n_components)
        self.amp_mm, self.amp_rad = amplitude_mm * k, math.radians(deg) * k

    def _wave(self, i: int, t: float) -> float:
        return sum(math.sin(w * t + p) - b
                   for w, p, b in zip(self._w[i], self._ph[i], self._base[i]))

    def offset_mm(self, t: float) -> tuple[float, float, float]:
        a = self.amp_mm
        return (a * self._wave(0, t), a * self._wave(1, t), a * self._wave(2, t))

    def angle_rad(self, t: float) -> float:
        return self.amp_rad * self._wave(3, t)


class Swallowing:
    """Swallows at seeded times: each moves the tooth ``mm`` along ``direction`` and turns it
    ``deg`` about the jaw's hinge, there and back in a raised-cosine bump of ``duration_s``.

    An awake adult swallows about once a minute (Lear et al. 1965, Arch Oral Biol 10:83:
    about 580 swallows a day awake), the pharyngeal phase lasting about a second (Logemann,
    Evaluation and Treatment of Swallowing Disorders, 1998); the intervals are drawn
    uniformly in ``every_s``. How far the tooth moves is an assumption: 3 mm and 3 deg, the
    jaw closing towards the robot (the direction that takes a file past the working length).
    """

    def __init__(self, rng: np.random.Generator, every_s=(30.0, 90.0), mm: float = 3.0,
                 deg: float = 3.0, duration_s: float = 1.0, horizon_s: float = 3600.0) -> None:
        lo, hi = every_s
        starts, t = [], 0.0
        while True:
            t += float(rng.uniform(lo, hi))
            if t > horizon_s:
                break
            starts.append(t)
        self.starts_s = tuple(starts)
        self.mm, self.rad, self.duration_s = mm, math.radians(deg), duration_s
        self.direction = (0.0, 0.0, 1.0)

    def level(self, t: float) -> float:
        """0 .. 1 .. 0 over each swallow (raised cosine), 0 between them."""
        i = bisect.bisect_right(self.starts_s, t) - 1
        if i < 0:
            return 0.0
        x = (t - self.starts_s[i]) / self.duration_s
        return 0.5 - 0.5 * math.cos(2.0 * math.pi * x) if 0.0 <= x <= 1.0 else 0.0

    def offset_mm(self, t: float) -> tuple[float, float, float]:
        s = self.mm * self.level(t)
        d = self.direction
        return (s * d[0], s * d[1], s * d[2])

    def angle_rad(self, t: float) -> float:
        return self.rad * self.level(t)


class PatientMotion:
    """A patient's 6-DoF motion: the translations of ``parts`` (head sway, tremor, swallows)
    summed, their turns summed about the jaw's hinge (``centre`` and unit ``axis``, {0}; the
    angles are small, so summing them is turning by their sum). ``rotation_at(t)`` gives the
    world (R, centre)."""

    def __init__(self, parts, centre, axis) -> None:
        self.parts = tuple(parts)
        self._turning = tuple(p for p in self.parts if hasattr(p, "angle_rad"))
        self.centre = tuple(float(x) for x in centre)
        self.axis = tuple(float(x) for x in axis)

    def offset_mm(self, t: float) -> tuple[float, float, float]:
        x = y = z = 0.0
        for p in self.parts:
            a, b, c = p.offset_mm(t)
            x, y, z = x + a, y + b, z + c
        return (x, y, z)

    def rotation_at(self, t: float):
        return axis_angle_matrix(self.axis, sum(p.angle_rad(t) for p in self._turning)), \
            self.centre


#: The patient motions a world builds by name about its tooth (``WorldConfig.motion``).
PATIENT_MOTIONS = ("tremor", "swallowing", "patient")


def patient_motion(kind: str, rng: np.random.Generator, orifice, canal_axis) -> PatientMotion:
    """``tremor``, ``swallowing``, or ``patient`` (head sway, tremor and swallows together)
    for a tooth whose canal starts at ``orifice`` along ``canal_axis`` ({0}); seeded by
    ``rng``. Swallows move the tooth towards the robot along the canal."""
    centre, axis = jaw_hinge(orifice, canal_axis)
    r_head, r_tremor, r_swallow = (np.random.default_rng(s) for s in
                                   np.random.SeedSequence(int(rng.integers(2**63))).spawn(3))
    parts = []
    if kind == "patient":
        parts.append(HeadMotion(r_head))
    if kind in ("tremor", "patient"):
        parts.append(Tremor(r_tremor))
    if kind in ("swallowing", "patient"):
        sw = Swallowing(r_swallow)
        sw.direction = tuple(-float(x) for x in canal_axis)
        parts.append(sw)
    if not parts:
        raise ValueError(f"patient motion {kind!r}: one of {', '.join(PATIENT_MOTIONS)}")
    return PatientMotion(parts, centre, axis)
