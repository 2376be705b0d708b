"""The simulated patient tracker: string lengths from a World, and a lock-step device.

:class:`StringModel` computes what the six draw-wire encoders read: the pose of the tooth
clamp {T} in the handpiece mount {M} from the World (the flange pose ``0T_6 = kin.fk(q)``
and the phantom's pose: rotation ``world.phantom_rotation``, origin
``world.phantom_origin_0()``, which includes patient motion and the platform), composed with
the tracker's own frames (``mount_in_flange`` = 6T_M, ``tooth_in_phantom`` = PT_T)::

    MT_T = (0T_6 6T_M)^-1 0T_P PT_T,     l_i = || p + R b_i - a_i ||

then turns them into encoder counts: ``counts = round((l + noise - zero_length) /
resolution)``, clipped to ``0 .. range / resolution - 1`` (a wire cannot go in further than
its zero, nor out beyond its drum). A string can be made to break (it winds in fully:
counts 0) or be held at a given length (caught on something).

:class:`SimPatientTracker` implements :class:`dentibot.io.interfaces.PatientTracker` over a
World for lock-step runs (``seq = world.steps``, ``t = world.t``), with the driver's status
rules. :mod:`dentibot.sim.tracker_nodes` puts the same model on the CAN bus.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dentibot.control.strings import StringGeometry, lengths, ring_geometry
from dentibot.errors import ConfigError
from dentibot.io.interfaces import (
    STRING_FAULT,
    STRING_OK,
    STRING_OVER_RANGE,
    STRING_SLACK,
    StringSample,
)
from dentibot.sim.world import World

#: Default anchors: a ring of radius 40 mm at z = 30 mm in the mount frame (a collar on the
#: handpiece, {M} = the flange frame), and a ring of radius 15 mm at z = -5 mm in the tooth
#: frame ({T} = the phantom frame: 5 mm above the orifice, around the crown). Assumptions of
#: a plausible mechanism, not a drawing: strings about 65 mm long.
_DEFAULT = ring_geometry(40.0, 15.0, 30.0, -5.0)


@dataclass
class TrackerSimParams:
    """The simulated tracker (mm). Encoder defaults: the 0.01 mm resolution class of
    draw-wire encoders with CANopen; ``noise_mm`` 0.003 mm rms on top of the quantisation
    (assumption: the electronics' jitter, well under one step); a 100 mm drum and a 300 mm
    range (assumptions)."""

    mount_mm: np.ndarray = field(default_factory=lambda: _DEFAULT.mount_mm.copy())
    tooth_mm: np.ndarray = field(default_factory=lambda: _DEFAULT.tooth_mm.copy())
    mount_in_flange: np.ndarray = field(default_factory=lambda: np.eye(4))
    tooth_in_phantom: np.ndarray = field(default_factory=lambda: np.eye(4))
    resolution_mm: float = 0.01
    drum_mm_per_rev: float = 100.0
    range_mm: float = 300.0
    zero_length_mm: float = 20.0
    noise_mm: float = 0.003
    min_length_mm: float = 30.0
    max_length_mm: float = 300.0
    seed: int = 0

    @property
    def geometry(self) -> StringGeometry:
        return StringGeometry(self.mount_mm, self.tooth_mm)

    @property
    def range_units(self) -> int:
        return round(self.range_mm / self.resolution_mm)


class StringModel:
    """Encoder readings of the strings over a World (see the module docstring)."""

    def __init__(self, world: World, params: TrackerSimParams | None = None) -> None:
        self.world = world
        self.p = p = params or TrackerSimParams()
        if not (p.resolution_mm > 0 and p.range_mm > 0 and p.noise_mm >= 0):
            raise ConfigError("tracker_sim", (p.resolution_mm, p.range_mm, p.noise_mm),
                              "resolution and range > 0 mm, noise >= 0 mm")
        self.geometry = p.geometry
        self.n = self.geometry.n
        self._rng = np.random.default_rng(p.seed)
        #: strings whose wire broke (reads 0 counts), and strings held at a length (mm)
        self.broken: set[int] = set()
        self.held_mm: dict[int, float] = {}
        self._key: tuple | None = None
        self._counts: tuple[int, ...] = ()

    def tooth_in_mount(self) -> np.ndarray:
        """``MT_T`` now (4x4, mm)."""
        w = self.world
        t0m = w.kin.fk(w.arm.q) @ self.p.mount_in_flange
        t0p = np.eye(4)
        t0p[:3, :3] = w.phantom_rotation
        t0p[:3, 3] = w.phantom_origin_0()
        return np.linalg.inv(t0m) @ t0p @ self.p.tooth_in_phantom

    def true_lengths_mm(self) -> np.ndarray:
        """The strings' geometric lengths now (mm), before faults, noise and quantisation."""
        return lengths(self.geometry, self.tooth_in_mount())

    def counts(self) -> tuple[int, ...]:
        """The encoders' position values now (one noise draw per World step)."""
        key = (self.world.steps, self.world.t, frozenset(self.broken),
               tuple(sorted(self.held_mm.items())))
        if key != self._key:
            p = self.p
            ell = self.true_lengths_mm()
            for i, v in self.held_mm.items():
                ell[i] = v
            if p.noise_mm:
                ell = ell + self._rng.normal(0.0, p.noise_mm, self.n)
            c = np.clip(np.round((ell - p.zero_length_mm) / p.resolution_mm), 0,
                        p.range_units - 1)
            for i in self.broken:
                c[i] = 0
            self._counts = tuple(int(x) for x in c)
            self._key = key
        return self._counts

    def length_of(self, counts: int) -> float:
        return self.p.zero_length_mm + counts * self.p.resolution_mm


class SimPatientTracker:
    """The tracker over a World, lock-step (implements ``dentibot.io.PatientTracker``).
    ``stopped`` holds strings whose encoder is off (status ``fault``)."""

    def __init__(self, world: World, params: TrackerSimParams | None = None) -> None:
        self.world = world
        self.model = StringModel(world, params)
        self.stopped: set[int] = set()

    async def read(self) -> StringSample:
        m, p, w = self.model, self.model.p, self.world
        counts = m.counts()
        lens = tuple(m.length_of(c) for c in counts)
        status = []
        for i, (c, ell) in enumerate(zip(counts, lens, strict=True)):
            if i in self.stopped:
                status.append(STRING_FAULT)
            elif ell < p.min_length_mm:
                status.append(STRING_SLACK)
            elif ell > p.max_length_mm or c >= p.range_units - 1:
                status.append(STRING_OVER_RANGE)
            else:
                status.append(STRING_OK)
        return StringSample(w.t, w.steps, lens, counts, tuple(status))

    async def recover(self) -> None:
        """The encoders switched back on."""
        self.stopped.clear()


def expected_length_error_mm(params: TrackerSimParams) -> float:
    """Bound on |reading - true length| (mm): half a step of quantisation plus 5 sigma of
    noise."""
    return 0.5 * params.resolution_mm + 5.0 * params.noise_mm + 1e-9


__all__ = ["SimPatientTracker", "StringModel", "TrackerSimParams", "expected_length_error_mm"]
