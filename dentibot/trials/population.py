"""Who is treated: the distributions of canal anatomy, files and patients, as data.

:data:`TABLE` names every drawn field (``group.name``) with its distribution, its unit, the
values the simulator can express (:class:`Field`), and a ``source`` for the numbers. A trial
file overrides any of them (:mod:`dentibot.trials.spec`); nothing else is drawn.

Seeding: procedure ``i`` of a trial with seed ``s`` draws field ``f`` from
``numpy.random.default_rng([s, i, crc32(f)])``, one independent stream per procedure and field.
So procedure ``i`` is the same canal, file and patient whatever the batch split, the number of
workers or the arm (every arm treats the same ``n`` patients: a paired design, the arms differ
by their settings only), and overriding one field leaves the draws of the others unchanged.
The simulator's own seed (sensor and motor noise, patient sway) is
``SeedSequence([s, i]).generate_state(1)[0]``, as :mod:`dentibot.experiments.preclinical`
seeds its phantoms.

Curvature follows Schneider's classes (Schneider 1971, Oral Surg Oral Med Oral Pathol 32:271:
straight <= 5 deg, moderate 10-20 deg, severe 25-70 deg): a class is drawn, then the angle
within it. :func:`schneider_class` classifies an angle, putting Schneider's gaps (5-10 and
20-25 deg) into the next class up. Radius and angle are separate parameters of a curve (Pruett,
Clement & Carnes 1997, J Endod 23:77); the radius is drawn on its own.

What the simulator cannot express is not drawn: the canal is one planar arc after a straight
part (:class:`dentibot.sim.canal.CanalParams`), the file one of :class:`NiTiFile`'s shapes, the
patient static or swaying (``HeadMotion``: slow sway, not a tremor).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field as PField
from pydantic import model_validator

from dentibot.yamlfile import StrictModel, echo

Value = float | str

#: Schneider (1971) classes and their upper angle (deg); see :func:`schneider_class`.
SCHNEIDER_CLASSES = ("straight", "moderate", "severe")
SCHNEIDER_UPPER_DEG = {"straight": 5.0, "moderate": 20.0, "severe": math.inf}


def schneider_class(angle_deg: float) -> str:
    """Schneider's class of a canal curving by ``angle_deg``: straight (<= 5 deg), moderate
    (<= 20 deg) or severe; Schneider (1971) left 5-10 and 20-25 deg out, counted here with the
    class above."""
    for name in SCHNEIDER_CLASSES:
        if angle_deg <= SCHNEIDER_UPPER_DEG[name]:
            return name
    return "severe"


class Distribution(StrictModel):
    """One field's distribution.

    - ``fixed``: ``value``;
    - ``uniform``: ``low`` .. ``high``;
    - ``truncnormal``: ``mean``, ``sd``, cut to ``low`` .. ``high`` (redrawn outside);
    - ``choice``: one of ``values`` with ``weights`` (default equal; normalised).

    ``source`` says where the numbers come from (a paper, a standard, or "assumption: ...").
    """

    dist: Literal["fixed", "uniform", "truncnormal", "choice"]
    value: Value | None = None
    low: float | None = None
    high: float | None = None
    mean: float | None = None
    sd: float | None = PField(None, gt=0.0)
    values: list[Value] | None = PField(None, min_length=1, max_length=100)
    weights: list[float] | None = PField(None, min_length=1, max_length=100)
    source: str = PField("", max_length=2000)

    @model_validator(mode="after")
    def _complete(self):
        need = {"fixed": ("value",), "uniform": ("low", "high"),
                "truncnormal": ("mean", "sd", "low", "high"), "choice": ("values",)}[self.dist]
        missing = [k for k in need if getattr(self, k) is None]
        if missing:
            raise ValueError(f"dist {self.dist} needs {', '.join(need)}: "
                             f"{', '.join(missing)} missing")
        if self.low is not None and self.high is not None and not self.low <= self.high:
            raise ValueError(f"low = {self.low!r} must not be above high = {self.high!r}")
        if self.dist == "truncnormal" and not self.low <= self.mean <= self.high:
            raise ValueError(f"mean = {self.mean!r} must lie within low .. high")
        if self.weights is not None:
            if self.dist != "choice":
                raise ValueError("weights belong to dist choice")
            if len(self.weights) != len(self.values):
                raise ValueError(f"{len(self.weights)} weights for {len(self.values)} values")
            if any(w < 0.0 for w in self.weights) or sum(self.weights) <= 0.0:
                raise ValueError(f"weights {echo(self.weights)}: >= 0, not all 0")
        return self

    def sample(self, rng: np.random.Generator) -> Value:
        if self.dist == "fixed":
            return self.value
        if self.dist == "uniform":
            return float(rng.uniform(self.low, self.high))
        if self.dist == "truncnormal":
            if self.low == self.high:
                return float(self.low)
            for _ in range(1000):
                x = float(rng.normal(self.mean, self.sd))
                if self.low <= x <= self.high:
                    return x
            return float(min(max(self.mean, self.low), self.high))
        w = np.asarray(self.weights if self.weights is not None
                       else [1.0] * len(self.values), float)
        return self.values[int(rng.choice(len(self.values), p=w / w.sum()))]

    def possible(self) -> list[Value] | tuple[float, float]:
        """What it can give: a list of values (fixed, choice) or a closed range."""
        if self.dist == "fixed":
            return [self.value]
        if self.dist == "choice":
            return [v for v, w in zip(self.values, self.weights or [1.0] * len(self.values))
                    if w > 0.0]
        return (self.low, self.high)


@dataclass(frozen=True)
class Field:
    """A drawn field: its unit, what the simulator can express (``lo``..``hi`` for a
    number, or ``choices``), whether it is an integer, and its default distribution."""

    unit: str
    default: Distribution
    lo: float | None = None
    hi: float | None = None
    choices: tuple[Value, ...] | None = None
    integer: bool = False

    def limit(self) -> str:
        if self.choices is not None:
            return "one of " + ", ".join(str(c) for c in self.choices)
        kind = "an integer" if self.integer else "a number"
        return f"{kind} in {self.lo:g} .. {self.hi:g}{' ' + self.unit if self.unit else ''}"

    def check(self, dist: Distribution) -> str | None:
        """Why ``dist`` can give a value this field cannot take, or None."""
        got = dist.possible()
        if isinstance(got, tuple):
            if self.choices is not None:
                return f"dist {dist.dist} gives numbers: must be {self.limit()} (use choice)"
            if self.integer:
                return f"dist {dist.dist} gives fractions: must be {self.limit()}"
            values: list = list(got)
        else:
            values = got
        for v in values:
            if self.choices is not None:
                if v not in self.choices and not (isinstance(v, float) and
                                                  float(v) in self.choices):
                    return f"value {echo(v)} is not {self.limit()}"
                continue
            if isinstance(v, str):
                return f"value {echo(v)} is not {self.limit()}"
            if not self.lo <= v <= self.hi or (self.integer and v != int(v)):
                return f"value {echo(v)} is out of range: must be {self.limit()}"
        return None


def _d(**kw) -> Distribution:
    return Distribution(**kw)


_SCHNEIDER = "Schneider 1971, Oral Surg Oral Med Oral Pathol 32:271"
#: Every drawn field, ``group.name`` -> :class:`Field`.
TABLE: dict[str, Field] = {
    # ---------------------------------------------------------------- anatomy
    "anatomy.working_length_mm": Field("mm", _d(
        dist="truncnormal", mean=14.0, sd=1.0, low=12.0, high=16.0,
        source="canal length from the orifice (the canal orifices lie at the pulp chamber "
               "floor, about the cervical line): molar roots are about 12-14 mm long "
               "(Nelson & Ash, Wheeler's Dental Anatomy, Physiology and Occlusion, 9th ed. "
               "2010, tables of tooth dimensions); assumption: sd 1 mm, cut to 12-16 mm (a "
               "25 mm file's 16 mm working part reaches the orifice)"),
        lo=2.0, hi=23.0),
    "anatomy.curvature_class": Field("", _d(
        dist="choice", values=["straight", "moderate", "severe"], weights=[0.3, 0.45, 0.25],
        source=f"classes: {_SCHNEIDER}; weights an assumption: most roots of posterior teeth "
               "curve mildly to moderately, the mesial roots of mandibular molars severely "
               "(Cunningham & Senia 1992, J Endod 18:294: all of 100 mesial roots curved)"),
        choices=SCHNEIDER_CLASSES),
    "anatomy.angle_straight_deg": Field("deg", _d(
        dist="uniform", low=0.0, high=5.0, source=f"{_SCHNEIDER}: straight, <= 5 deg"),
        lo=0.0, hi=60.0),
    "anatomy.angle_moderate_deg": Field("deg", _d(
        dist="uniform", low=10.0, high=20.0, source=f"{_SCHNEIDER}: moderate, 10-20 deg"),
        lo=0.0, hi=60.0),
    "anatomy.angle_severe_deg": Field("deg", _d(
        dist="uniform", low=25.0, high=40.0,
        source=f"{_SCHNEIDER}: severe, 25-70 deg; assumption: up to 40 deg (the simulator's "
               "canal takes up to 60 deg)"), lo=0.0, hi=60.0),
    "anatomy.curve_radius_mm": Field("mm", _d(
        dist="uniform", low=4.0, high=12.0,
        source="radius and angle are separate parameters of a curve, and the file's life "
               "falls with the radius (Pruett, Clement & Carnes 1997, J Endod 23:77: 2 and "
               "5 mm test canals); assumption: clinical radii 4-12 mm"), lo=1.5, hi=100.0),
    "anatomy.curve_start_frac": Field("", _d(
        dist="uniform", low=0.6, high=0.75,
        source="depth where the curve starts, as a fraction of the working length: the "
               "apical third to half of the root curves (Cunningham & Senia 1992, J Endod "
               "18:294); assumption: 60-75 % (the pre-clinical phantoms: 60-70 %)"),
        lo=0.0, hi=0.95),
    "anatomy.tilt_deg": Field("deg", _d(
        dist="truncnormal", mean=0.0, sd=3.0, low=-8.0, high=8.0,
        source="assumption: the canal's straight part within a few degrees of the access "
               "direction (the pre-clinical tilted phantoms: 6-12 deg)"), lo=-30.0, hi=30.0),
    "anatomy.apical_diameter_mm": Field("mm", _d(
        dist="choice", values=[0.10, 0.15], weights=[0.3, 0.7],
        source="the canal's initial apical diameter after the glide path: the tip of an ISO "
               "10 or 15 hand file (ISO 3630-1: size = tip diameter in 1/100 mm); assumption: "
               "70 % enlarged to 15 (the simulator's default)"), lo=0.06, hi=0.24),
    "anatomy.canal_taper": Field("", _d(
        dist="fixed", value=0.02,
        source="ISO 3630-1: hand files taper 0.02 mm/mm, the glide path's shape"),
        lo=0.005, hi=0.06),
    "anatomy.material": Field("", _d(
        dist="choice", values=["resin"],
        source="the simulator's materials (dentibot.sim.canal.MATERIALS): resin, a training "
               "block; acrylic, the thesis's experiment 2 phantoms; no dentin model"),
        choices=("resin", "acrylic")),
    # ---------------------------------------------------------------- file
    "file.size": Field("", _d(
        dist="fixed", value=25, source="ISO 3630-1 size (tip diameter in 1/100 mm); the "
                                       "thesis's #25/.06 file"), lo=6, hi=140, integer=True),
    "file.taper": Field("", _d(dist="fixed", value=0.06, source="the thesis's #25/.06 file"),
                        lo=0.01, hi=0.12),
    "file.length_mm": Field("mm", _d(dist="fixed", value=25, source="the thesis's 25 mm file"),
                            choices=(21.0, 25.0, 28.0, 31.0)),
    "file.rated_strength_mnm": Field("mNm", _d(
        dist="fixed", value=62.0,
        source="the strength the protocol states and the runtime's hard torque limit is a "
               "share of: thesis eq 5.5 (its ref [37]), 6.20 Ncm for the #25/.06 file"),
        lo=5.0, hi=200.0),
    "file.torsional_strength_mnm": Field("mNm", _d(
        dist="truncnormal", mean=62.0, sd=3.0, low=53.0, high=71.0,
        source="the file's actual strength (at which the simulated file breaks): the rated "
               "6.20 Ncm (thesis eq 5.5) with an assumed sd of 3 mNm (5 %) between files of "
               "a batch, cut at 3 sd; torsional tests after ISO 3630-1 (tip held 3 mm, 2 rpm) "
               "scatter by about that"), lo=5.0, hi=200.0),
    "file.fatigue_c": Field("", _d(
        dist="fixed", value=1.0,
        source="strain-life law eps_a = C N_f^-b (Coffin-Manson form) of "
               "dentibot.sim.nitifile: about 330 cycles at 5.5 % strain, the order Pruett et "
               "al. 1997 (J Endod 23:77) report for a 5 mm radius"), lo=0.01, hi=100.0),
    "file.fatigue_b": Field("", _d(
        dist="fixed", value=0.5, source="as file.fatigue_c (dentibot.sim.nitifile)"),
        lo=0.05, hi=2.0),
    # ---------------------------------------------------------------- patient
    "patient.motion": Field("", _d(
        dist="choice", values=["static"],
        source="static: a held head (the thesis's phantoms); head: slow sway of a patient "
               "holding still (dentibot.sim.patient.HeadMotion)"), choices=("static", "head")),
    "patient.sway_mm": Field("mm", _d(
        dist="fixed", value=1.0,
        source="rms per axis of the head sway, 0.05-0.5 Hz (assumption of "
               "dentibot.sim.patient.HeadMotion: 1 mm)"), lo=0.0, hi=5.0),
}
GROUPS = ("anatomy", "file", "patient")


def field_names(group: str) -> list[str]:
    return [k.split(".", 1)[1] for k in TABLE if k.startswith(group + ".")]


def problems(overrides: Mapping[str, Mapping[str, Distribution]]) -> list[tuple[tuple, str]]:
    """``[(location, text)]`` for overrides naming no field or giving values the field
    cannot take (location as pydantic's: ``("population", group, name, ...)``)."""
    out: list[tuple[tuple, str]] = []
    for group, fields in overrides.items():
        for name, dist in fields.items():
            key = f"{group}.{name}"
            if key not in TABLE:
                out.append((("population", group, name),
                            f"unknown field; {group} has {', '.join(field_names(group))}"))
                continue
            why = TABLE[key].check(dist)
            if why:
                out.append((("population", group, name), why))
    return out


def table_with(overrides: Mapping[str, Mapping[str, Distribution]] | None = None
               ) -> dict[str, Distribution]:
    """The default distributions with ``overrides`` (group -> field -> Distribution) on top;
    raises ValueError on a problem of :func:`problems`."""
    overrides = overrides or {}
    bad = problems(overrides)
    if bad:
        loc, text = bad[0]
        raise ValueError(f"{'.'.join(map(str, loc))}: {text}")
    out = {k: f.default for k, f in TABLE.items()}
    for group, fields in overrides.items():
        for name, dist in fields.items():
            out[f"{group}.{name}"] = dist
    return out


def field_rng(seed: int, index: int, key: str) -> np.random.Generator:
    """The stream of field ``key`` for procedure ``index`` of a trial seeded ``seed``."""
    return np.random.default_rng([seed, index, zlib.crc32(key.encode())])


def sim_seed(seed: int, index: int) -> int:
    """The simulator's seed for procedure ``index``."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


@dataclass(frozen=True)
class Subject:
    """One procedure's patient, canal and file (what :func:`draw` gives)."""

    index: int
    sim_seed: int
    working_length_mm: float
    curve_angle_deg: float
    curve_radius_mm: float
    curve_start_mm: float
    tilt_deg: float
    apical_diameter_mm: float
    canal_taper: float
    material: str
    file_size: int
    file_taper: float
    file_length_mm: float
    rated_strength_mnm: float
    torsional_strength_mnm: float
    fatigue_c: float
    fatigue_b: float
    motion: str
    sway_mm: float

    @property
    def curvature(self) -> str:
        return schneider_class(self.curve_angle_deg)


def draw(table: Mapping[str, Distribution], seed: int, index: int) -> Subject:
    """Procedure ``index``'s subject (see the module's seeding)."""
    v = {k: d.sample(field_rng(seed, index, k)) for k, d in table.items()}
    klass = v["anatomy.curvature_class"]
    wl = float(v["anatomy.working_length_mm"])
    return Subject(
        index=index, sim_seed=sim_seed(seed, index), working_length_mm=wl,
        curve_angle_deg=float(v[f"anatomy.angle_{klass}_deg"]),
        curve_radius_mm=float(v["anatomy.curve_radius_mm"]),
        curve_start_mm=float(v["anatomy.curve_start_frac"]) * wl,
        tilt_deg=float(v["anatomy.tilt_deg"]),
        apical_diameter_mm=float(v["anatomy.apical_diameter_mm"]),
        canal_taper=float(v["anatomy.canal_taper"]), material=str(v["anatomy.material"]),
        file_size=int(v["file.size"]), file_taper=float(v["file.taper"]),
        file_length_mm=float(v["file.length_mm"]),
        rated_strength_mnm=float(v["file.rated_strength_mnm"]),
        torsional_strength_mnm=float(v["file.torsional_strength_mnm"]),
        fatigue_c=float(v["file.fatigue_c"]), fatigue_b=float(v["file.fatigue_b"]),
        motion=str(v["patient.motion"]), sway_mm=float(v["patient.sway_mm"]))
