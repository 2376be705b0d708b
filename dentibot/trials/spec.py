"""The trial file (YAML), validated with pydantic and read as strictly as a protocol
(:mod:`dentibot.yamlfile`): unknown keys, values out of range and impossible combinations are
errors naming the line, the field, the value and the limit, before anything runs.

A trial::

    name: tau-d-curved
    seed: 7
    n: 12                     # procedures per arm (the same 12 patients in every arm)
    batch_size: 4             # procedures per batch file (the unit of resumption)
    rounds_s: [60]            # the drilling rounds of every procedure (s)
    population:               # overrides of dentibot.trials.population.TABLE
      anatomy:
        curvature_class: {dist: choice, values: [moderate, severe], weights: [1, 1]}
    arms:
      - {name: tau30, tau_d_mnm: 30}
      - {name: tau50, tau_d_mnm: 50, fz_max_n: 0.3}

An arm changes the drilling step's settings (:class:`dentibot.protocol.schema.DrillStep`:
``strategy``, ``tau_d_mnm``, ``fz_min_n``, ``fz_max_n``, ``rpm``), the hard torque limit as a
share of each file's strength (``torque_limit_share``; the protocol's 90 % unless told; up to 1
on the simulator, as the pre-clinical ablations run) and how the arm follows the patient
(``tracking``: force, or hybrid with the patient tracker; ``tracker``).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field

from dentibot.protocol.schema import (
    FILE_CLEARANCE_MM,
    LIMIT_SHARE_OF_STRENGTH,
    MilliNm,
)
from dentibot.trials import population as pop
from dentibot.yamlfile import StrictModel, YamlFileError, load, loads

#: Most procedures a trial may ask for (all arms), and the longest drilling (s, all rounds).
MAX_PROCEDURES = 1_000_000
MAX_DRILL_S = 3600.0
#: Bump when the rows a procedure gives change: a rerun then refuses the old batches.
ROWS_VERSION = 1

Name = Annotated[str, Field(min_length=1, max_length=40, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")]
Round = Annotated[float, Field(gt=0.0, le=MAX_DRILL_S)]


class TrialFileError(YamlFileError):
    """A trial file is malformed or invalid; ``problems`` lists every (line, field, text)."""

    kind = "trial"


class ArmSpec(StrictModel):
    """One arm: the settings its procedures run with (the rest as the protocol defaults)."""

    name: Name
    strategy: Literal["automated", "feedrate", "reversal", "none"] = "automated"
    tau_d_mnm: MilliNm = Field(40.0, gt=0.0, le=200.0, description="desired file torque (mNm)")
    fz_min_n: float = Field(-0.5, ge=-2.0, le=0.0, description="feed force lower bound (N)")
    fz_max_n: float = Field(0.5, gt=0.0, le=2.0, description="feed force upper bound (N)")
    rpm: float = Field(60.0, gt=0.0, le=200.0, description="file speed (rpm)")
    torque_limit_share: float = Field(
        LIMIT_SHARE_OF_STRENGTH, gt=0.0, le=1.0,
        description="the runtime's hard torque limit as a share of each file's strength")
    tracker: bool = Field(False, description="depth from the patient tracker")
    tracking: Literal["force", "hybrid"] = Field("force", description="force or hybrid")

    def drill(self, rounds_s: list[float]) -> dict:
        """The protocol's drill step of this arm."""
        return {"strategy": self.strategy, "tau_d_mnm": self.tau_d_mnm,
                "fz_min_n": self.fz_min_n, "fz_max_n": self.fz_max_n, "rpm": self.rpm,
                "rounds": [{"duration_s": d} for d in rounds_s]}


Overrides = dict[str, pop.Distribution]


class PopulationSpec(StrictModel):
    """Overrides of :data:`dentibot.trials.population.TABLE`, per group."""

    anatomy: Overrides = {}
    file: Overrides = {}
    patient: Overrides = {}

    def overrides(self) -> dict[str, Overrides]:
        return {g: dict(getattr(self, g)) for g in pop.GROUPS if getattr(self, g)}


class FileLifeSpec(StrictModel):
    """How a file's life over several canals is estimated (:mod:`dentibot.trials.fatigue`)."""

    files: int = Field(2000, ge=10, le=1_000_000,
                       description="simulated files per arm (each through a run of canals)")
    max_canals: int = Field(200, ge=1, le=100_000, description="canals at most per file")


class TrialSpec(StrictModel):
    name: Name
    description: str = Field("", max_length=4000)
    seed: int = Field(0, ge=0, le=2**32 - 1)
    n: int = Field(ge=1, le=100_000, description="procedures per arm")
    batch_size: int = Field(8, ge=1, le=10_000, description="procedures per batch")
    rounds_s: list[Round] = Field([60.0], min_length=1, max_length=20,
                                  description="drilling rounds (s)")
    population: PopulationSpec = PopulationSpec()
    file_life: FileLifeSpec = FileLifeSpec()
    arms: list[ArmSpec] = Field(min_length=1, max_length=100)

    def table(self) -> dict[str, pop.Distribution]:
        return pop.table_with(self.population.overrides())

    def cross_checks(self) -> list[tuple[tuple, str]]:
        out = list(pop.problems(self.population.overrides()))
        if out:
            return out
        table = self.table()
        if sum(self.rounds_s) > MAX_DRILL_S:
            out.append((("rounds_s",), f"{sum(self.rounds_s):g} s in all: at most "
                                       f"{MAX_DRILL_S:g} s"))
        if self.n * len(self.arms) > MAX_PROCEDURES:
            out.append((("n",), f"{self.n} x {len(self.arms)} arms: at most "
                                f"{MAX_PROCEDURES} procedures"))
        seen: dict[str, int] = {}
        weakest = _lowest(table["file.rated_strength_mnm"])
        for i, arm in enumerate(self.arms):
            if arm.name in seen:
                out.append((("arms", i, "name"), f"{arm.name!r} names arm {seen[arm.name]} "
                                                 "too: arm names are unique"))
            seen.setdefault(arm.name, i)
            limit = arm.torque_limit_share * weakest
            if arm.tau_d_mnm >= limit:
                out.append((("arms", i, "tau_d_mnm"),
                            f"{arm.tau_d_mnm:g} mNm is not below the hard torque limit: "
                            f"torque_limit_share {arm.torque_limit_share:g} x the files' rated "
                            f"strength {weakest:g} mNm (population.file.rated_strength_mnm) = "
                            f"{limit:.1f} mNm (torque_limit_share goes up to 1 on the "
                            "simulator)"))
            if arm.tracking == "hybrid" and not arm.tracker:
                out.append((("arms", i, "tracking"), "hybrid needs the patient tracker "
                                                     "(set tracker: true)"))
        wl_hi = _highest(table["anatomy.working_length_mm"])
        length = _lowest(table["file.length_mm"])
        if wl_hi + FILE_CLEARANCE_MM > length:
            out.append((("population", "anatomy", "working_length_mm"),
                        f"up to {wl_hi:g} mm does not fit the {length:g} mm file: at most "
                        f"{length - FILE_CLEARANCE_MM:g} mm"))
        return out

    def spec_hash(self) -> str:
        """What the procedures' rows depend on (everything but the description), hashed: a
        rerun into the same directory keeps its batches only under the same hash."""
        data = self.model_dump(mode="json", exclude={"description", "file_life"})
        data["rows_version"] = ROWS_VERSION
        text = json.dumps(data, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def _lowest(d: pop.Distribution) -> float:
    got = d.possible()
    return float(got[0] if isinstance(got, tuple) else min(float(v) for v in got))


def _highest(d: pop.Distribution) -> float:
    got = d.possible()
    return float(got[1] if isinstance(got, tuple) else max(float(v) for v in got))


def load_trial(path: str | Path) -> TrialSpec:
    """Read and validate the trial file ``path``; raises :class:`TrialFileError`."""
    return load(path, TrialSpec, TrialFileError)


def parse_trial(text: str, path: str = "<trial>") -> TrialSpec:
    """Validate trial ``text``; raises :class:`TrialFileError`."""
    return loads(text, TrialSpec, path, TrialFileError)
