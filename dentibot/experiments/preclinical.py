"""Thesis experiment 2 (6.3): pre-clinical evaluation on six root phantoms A-F.

Each phantom is prepared by a drilling strategy (the automated algorithm of 5.4 unless an
ablation asks otherwise) in two rounds of 300 s and 200 s, with tau_d = 40 mNm for A-C and
50 mNm for D-F. The protocol is protocols/preclinical-phantom-D.yaml with the phantom's canal,
tau_d and seed: load calibration, 0.2 s of self-alignment, then the drilling rounds.

The phantoms are acrylic (:data:`dentibot.sim.canal.MATERIALS`): the torque to turn the file
grows with its depth (its flutes rub every wall they touch) and its flutes screw it in, so the
desired torque decides how deep the file gets within the rounds (the thesis's tau_d 40 vs 50),
and what protects the file from the screw-in is the reversal (5.2), not the feedrate PD alone.

Ablations (``strategy`` other than automated) run with the runtime's hard torque limit at the
file's strength (:func:`default_torque_limit`): the strategy alone protects the file, and
:func:`ablation_checks` compares each with the automated algorithm on the same phantoms.

Phantoms (seeded; the thesis's acrylic phantoms "might be straight, tilted, or even curved"):
A and D straight, B and E tilted, C and F curved. Geometry per phantom from
``numpy.random.default_rng([seed, index])`` (ranges in :func:`phantoms`, all assumptions).

Reported per phantom (Table 6.5's columns plus what explains them):

- red area before / after: the red-stained canal as a photograph across it shows it (mm^2;
  Table 6.5 counts the pixels of such photographs, so only the ratio compares), and
  completeness (eq 6.1, 0..1); see :mod:`dentibot.sim.canal`. Shaping: how much of the volume
  between the initial lumen and the target #25/.06 shape has been cut;
- fracture (torsion or fatigue) and the peak file torque (simulator truth, mNm; the 62 mNm
  strength is the limit);
- reversals (and how many of them the runtime's hard torque limit, 90 % of 62 mNm, forced:
  the last line of defence, under every strategy), passes to working length (the strategy's arrivals), when the file first
  reached it, the time it spent stalled before that (feeding, yet its deepest point gained
  less than :data:`~dentibot.app.batch.STALL_GAIN_MM` in
  :data:`~dentibot.app.batch.STALL_WINDOW_S`), and the fatigue used (Miner
  sum, 1 = failure).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from dentibot.control.feedrate import FILE_STRENGTH_MNM
from dentibot.app import drill_kernels as dk
from dentibot.app.batch import run_protocol, stalled_seconds
from dentibot.app.simulated import true_depth_mm
from dentibot.experiments.common import Check, distribution
from dentibot.protocol.schema import LimitsSpec, Protocol

NAMES = ("A", "B", "C", "D", "E", "F")
KINDS = {"A": "straight", "B": "tilted", "C": "curved",
         "D": "straight", "E": "tilted", "F": "curved"}
#: Thesis 6.3: tau_d 40 mNm for A-C, 50 mNm for D-F.
TAU_D_MNM = {"A": 40.0, "B": 40.0, "C": 40.0, "D": 50.0, "E": 50.0, "F": 50.0}
#: Thesis 6.3: two rounds, 300 s then 200 s.
ROUNDS_S = (300.0, 200.0)
STRATEGIES = ("automated", "feedrate", "reversal", "none")
#: Traces kept for the figures: one sample every this many control ticks (10 Hz).
TRACE_EVERY = 50
#: Table 6.5: preoperative and postoperative red area (pixels), completeness, fracture.
THESIS_TABLE_6_5 = {
    "A": (15652, 795, 0.9492, False), "B": (17316, 2418, 0.8604, False),
    "C": (17403, 2738, 0.8427, False), "D": (16114, 53, 0.9967, False),
    "E": (17047, 185, 0.9891, False), "F": (18482, 180, 0.9903, False),
}
#: The thesis's phantoms were acrylic (6.3); see dentibot.sim.canal.MATERIALS.
MATERIAL = "acrylic"
#: Thesis 6.3: mean completeness per tau_d.
THESIS_MEANS = {40.0: 0.8841, 50.0: 0.992}


@dataclass(frozen=True)
class Phantom:
    """One root phantom: its canal, tau_d and the simulator seed of its run."""

    name: str
    kind: str
    tau_d_mnm: float
    seed: int
    working_length_mm: float
    member: int = 1                     # the population member (``phantoms(seed=...)``)
    tilt_deg: float = 0.0
    curve_start_mm: float | None = None
    curve_radius_mm: float = 10.0
    curve_angle_deg: float = 0.0

    def describe(self) -> str:
        """Short: "straight", "tilt +9.7" (deg), "curve 19/r12@10" (deg / radius mm @ start
        depth mm)."""
        if self.kind == "tilted":
            return f"tilt {self.tilt_deg:+.1f}"
        if self.kind == "curved":
            return (f"curve {self.curve_angle_deg:.0f}/r{self.curve_radius_mm:.0f}"
                    f"@{self.curve_start_mm:.0f}")
        return "straight"


def phantoms(seed: int = 1, names: tuple[str, ...] = NAMES) -> list[Phantom]:
    """The six phantoms of population member ``seed``.

    assumption (acrylic training blocks, within what the simulator and a 25 mm #25/.06 file
    can prepare): working length uniform 14.5..16 mm (the file's 16 mm working part must
    reach the target shape at the orifice); tilted canals 6..12 deg either way (a
    tip more than 0.5 mm past the working length along a tilted canal touches the modelled
    apex, so no more); curved canals bend 15..30 deg with a radius of 10..14 mm, starting at
    60..70 % of the working length (tighter curves exhaust the file's fatigue life within the
    500 s at 60 rpm, and the thesis saw no fracture).
    """
    out = []
    for i, name in enumerate(NAMES):
        rng = np.random.default_rng([seed, i])
        wl = float(rng.uniform(14.5, 16.0))
        kind = KINDS[name]
        extra: dict = {}
        if kind == "tilted":
            extra["tilt_deg"] = float(rng.uniform(6.0, 12.0) * rng.choice([-1.0, 1.0]))
        elif kind == "curved":
            extra["curve_start_mm"] = float(rng.uniform(0.6, 0.7) * wl)
            extra["curve_radius_mm"] = float(rng.uniform(10.0, 14.0))
            extra["curve_angle_deg"] = float(rng.uniform(15.0, 30.0))
        sim_seed = int(np.random.SeedSequence([seed, i]).generate_state(1)[0])
        if name in names:
            out.append(Phantom(name, kind, TAU_D_MNM[name], sim_seed, wl, member=seed,
                               **extra))
    return out


@dataclass(frozen=True)
class PreclinicalSpec:
    """One phantom's run."""

    phantom: Phantom
    strategy: str = "automated"
    rounds_s: tuple[float, ...] = ROUNDS_S
    keep_trace: bool = True
    #: the phantom material: a name, or a mapping as in a protocol's ``phantom.material``
    material: str | dict = MATERIAL
    #: the runtime's hard file-torque limit (mNm); None: the protocol default (90 % of the
    #: strength). Ablations set it to the strength itself, so that the strategy alone decides.
    torque_limit_mnm: float | None = None

    def __post_init__(self) -> None:
        if self.strategy not in STRATEGIES:
            raise ValueError(f"strategy {self.strategy!r}: one of {', '.join(STRATEGIES)}")


@dataclass
class PhantomRun:
    spec: PreclinicalSpec
    status: str
    reason: str
    red_before_mm2: float
    red_after_mm2: float
    completeness: float
    shaping: float
    fracture: bool
    fracture_cause: str | None
    peak_torque_mnm: float
    peak_torque_estimate_mnm: float
    reversals: int
    limit_reversals: int
    passes: int
    depth_max_mm: float
    t_first_wl_s: float | None
    stalled_s: float
    fatigue_damage: float
    wall_s: float
    trace: dict[str, np.ndarray] | None = field(default=None, repr=False)

    @property
    def name(self) -> str:
        return self.spec.phantom.name

    def to_dict(self) -> dict:
        p = self.spec.phantom
        return {"name": p.name, "canal": p.kind, "geometry": asdict(p), "tau_d": p.tau_d_mnm,
                "strategy": self.spec.strategy, "status": self.status, "reason": self.reason,
                "red_before_mm2": self.red_before_mm2, "red_after_mm2": self.red_after_mm2,
                "completeness": self.completeness, "shaping": self.shaping,
                "fracture": self.fracture,
                "fracture_cause": self.fracture_cause,
                "peak_torque_mnm": self.peak_torque_mnm,
                "peak_torque_estimate_mnm": self.peak_torque_estimate_mnm,
                "reversals": self.reversals, "limit_reversals": self.limit_reversals,
                "passes": self.passes,
                "depth_max_mm": self.depth_max_mm, "t_first_wl_s": self.t_first_wl_s,
                "stalled_s": self.stalled_s, "fatigue_damage": self.fatigue_damage,
                "wall_s": self.wall_s}


def preclinical_protocol(spec: PreclinicalSpec) -> Protocol:
    """protocols/preclinical-phantom-D.yaml with this phantom's canal, tau_d, strategy, seed
    (on the thesis's world, whose Table 6.5 it reproduces)."""
    p = spec.phantom
    phantom: dict = {"working_length_mm": p.working_length_mm, "orifice_gap_mm": 2.0,
                     "tilt_deg": p.tilt_deg, "material": spec.material}
    if p.curve_start_mm is not None:
        phantom["curve"] = {"start_mm": p.curve_start_mm, "radius_mm": p.curve_radius_mm,
                            "angle_deg": p.curve_angle_deg}
    return Protocol.model_validate({
        "name": f"preclinical-{p.name}", "seed": p.seed, "world": "thesis",
        "file": {"size": 25, "taper": 0.06, "length_mm": 25},
        "phantom": phantom,
        "recording": {"enabled": False},
        **({} if spec.torque_limit_mnm is None
           else {"limits": {"torque_limit_mnm": spec.torque_limit_mnm}}),
        "steps": [
            {"calibrate_load": {}},
            {"align": {"duration_s": 0.2, "fz_n": 1.0}},
            {"drill": {"strategy": spec.strategy, "tau_d_mnm": p.tau_d_mnm, "rpm": 60,
                       "rounds": [{"duration_s": d} for d in spec.rounds_s]}},
        ],
    })


def run_phantom(spec: PreclinicalSpec) -> PhantomRun:
    """Prepare one phantom (blocking; lock-step time)."""
    peak = [0.0, 0.0]              # true torque, the runtime's estimate
    trace: dict[str, list] = {"t": [], "depth": [], "torque": [], "completeness": [],
                              "feeding": []}
    protocol = preclinical_protocol(spec)

    def sample(runner) -> None:
        """The trace at the tick that just ran, when it is one of every ``TRACE_EVERY``."""
        rt, w = runner.rt, runner.world
        if (rt.ticks - 1) % TRACE_EVERY == 0:
            trace["t"].append(w.t)
            trace["depth"].append(true_depth_mm(w))
            trace["torque"].append(w.handpiece.torque_mnm)
            trace["completeness"].append(w.completeness())
            trace["feeding"].append(rt.state == "treating.drilling.feeding")

    def after_tick(runner) -> None:
        rt, w = runner.rt, runner.world
        if rt.last is None:             # before the first estimate (no row either)
            return
        tq = abs(w.handpiece.torque_mnm)
        peak[0] = max(peak[0], tq)
        peak[1] = max(peak[1], abs(rt.last.file_torque_mnm))
        sample(runner)

    def ticks(runner, out, n, k0, state) -> None:
        """Ticks that ran compiled (:mod:`dentibot.app.drill_loop`); the last is the first
        traced tick among them, if any (``every``)."""
        peak[0] = max(peak[0], float(out[:n, dk.OUT_TORQUE_ABS].max()))
        peak[1] = max(peak[1], float(np.abs(out[:n, dk.OUT_EST_TORQUE]).max()))
        sample(runner)

    after_tick.ticks, after_tick.every = ticks, TRACE_EVERY

    wall = time.perf_counter()
    # an ablation's hard limit may be the file's strength itself (no runtime net: the
    # strategy alone protects the file), which only a simulated study may ask for
    result, runner = run_protocol(
        protocol, None, on_tick=after_tick,
        limit_share=torque_limit_of(spec) / protocol.file.torsional_strength_mnm)
    wall = time.perf_counter() - wall
    w = runner.world
    canal = w.canal
    s = result.summary
    tr = {k: np.asarray(v) for k, v in trace.items()}
    depth = tr["depth"]
    arrivals = [tick * runner.rt.ts for tick, kind, _ in runner.rt.events_log
                if kind == "working_length_reached"]
    t_wl = arrivals[0] if arrivals else None
    # the runtime's hard torque limit asks for a reversal whatever the strategy: its detail
    # names the file torque against the limit (the strategies' name tau and fz*)
    limit = sum(1 for _, kind, detail in runner.rt.events_log
                if kind == "reversal_needed" and detail.startswith("file torque"))
    return PhantomRun(
        spec=spec, status=s.status, reason=s.reason,
        red_before_mm2=canal.red0,
        red_after_mm2=float(canal.red_area_mm2().sum()),
        completeness=w.completeness(), shaping=canal.shaping(),
        fracture=w.fractured is not None,
        fracture_cause=None if w.fractured is None else w.fractured.cause,
        peak_torque_mnm=peak[0],
        peak_torque_estimate_mnm=peak[1],
        reversals=runner.rt.ctx.reversals, limit_reversals=limit, passes=len(arrivals),
        depth_max_mm=float(depth.max()) if len(depth) else float("nan"),
        t_first_wl_s=t_wl,
        stalled_s=stalled_seconds(tr["t"], depth, tr["feeding"], t_wl),
        fatigue_damage=w.fatigue_damage, wall_s=wall,
        trace=tr if spec.keep_trace else None)


def group_means(runs: list[PhantomRun]) -> dict[float, float]:
    """Mean completeness per tau_d."""
    out: dict[float, list[float]] = {}
    for r in runs:
        out.setdefault(r.spec.phantom.tau_d_mnm, []).append(r.completeness)
    return {k: float(np.mean(v)) for k, v in sorted(out.items())}


def population_summary(runs: list[PhantomRun]) -> dict:
    """Distributions over the population, per phantom name and per tau_d group (worst case:
    lowest completeness, highest torque)."""
    by_name: dict[str, list[PhantomRun]] = {}
    by_seed: dict[int, list[PhantomRun]] = {}
    for r in runs:
        by_name.setdefault(r.name, []).append(r)
    per = []
    for name, rs in by_name.items():
        per.append({
            "name": name, "canal": KINDS[name], "tau_d": TAU_D_MNM[name], "n": len(rs),
            "completeness": distribution((r.completeness for r in rs), worst="min"),
            "fractures": sum(r.fracture for r in rs),
            "peak_torque_mnm": distribution(r.peak_torque_mnm for r in rs),
            "reversals": distribution(r.reversals for r in rs),
            "limit_reversals": distribution(r.limit_reversals for r in rs),
            "stalled_s": distribution(r.stalled_s for r in rs),
            "t_first_wl_s": distribution(r.t_first_wl_s for r in rs),
            "never_reached_wl": sum(r.t_first_wl_s is None for r in rs),
            "fatigue_damage": distribution(r.fatigue_damage for r in rs),
        })
    for r in runs:
        by_seed.setdefault(r.spec.phantom.member, []).append(r)
    diffs = []
    for rs in by_seed.values():
        m = group_means(rs)
        if 40.0 in m and 50.0 in m:
            diffs.append(m[50.0] - m[40.0])
    groups = {}
    for tau in sorted({r.spec.phantom.tau_d_mnm for r in runs}):
        groups[tau] = distribution((r.completeness for r in runs
                                    if r.spec.phantom.tau_d_mnm == tau), worst="min")
    return {"phantoms": per, "tau_d_groups": groups, "fractures": sum(r.fracture for r in runs),
            "runs": len(runs), "members": len(by_seed),
            "mean_50_minus_40": distribution(diffs, worst="min"),
            "members_50_above_40": sum(d > 0.0 for d in diffs)}


def default_torque_limit(strategy: str) -> float | None:
    """The runtime's hard torque limit for a strategy's runs: the protocol default (90 % of
    the file's strength) for the automated algorithm; the strength itself for an ablation, so
    that what protects the file (or fails to) is the strategy, not the runtime's net."""
    return None if strategy == "automated" else FILE_STRENGTH_MNM


def torque_limit_of(spec: PreclinicalSpec) -> float:
    """The hard torque limit (mNm) a run of ``spec`` has in force."""
    if spec.torque_limit_mnm is None:
        return LimitsSpec().torque_limit_mnm
    return spec.torque_limit_mnm


#: An ablation "stalls" when its mean completeness is this much below the automated one's.
STALL_MARGIN = 0.01


def ablation_checks(by_strategy: dict[str, list[PhantomRun]]) -> list[Check]:
    """What each protection buys: every ablation run beside the automated algorithm on the
    same phantoms fractures files the automated algorithm does not, or stalls: on the
    phantoms where its file survived, its mean completeness is more than
    :data:`STALL_MARGIN` below the automated algorithm's on the same phantoms."""
    base = {(r.spec.phantom.member, r.name): r for r in by_strategy.get("automated", [])}
    if not base:
        return []
    removed = {"feedrate": "without reversal", "reversal": "without feedrate control",
               "none": "without either protection"}
    n0 = sum(r.fracture for r in base.values())
    out = []
    for name, runs in by_strategy.items():
        if name == "automated" or not runs:
            continue
        n = sum(r.fracture for r in runs)
        pairs = [(r, base[r.spec.phantom.member, r.name]) for r in runs
                 if not r.fracture and (r.spec.phantom.member, r.name) in base]
        what = []
        if n > n0:
            what.append(f"{n} of {len(runs)} files fractured (automated: {n0})")
        if pairs:
            c = float(np.mean([r.completeness for r, _ in pairs]))
            c0 = float(np.mean([b.completeness for _, b in pairs]))
            text = (f"mean completeness {100 * c:.1f} % on the {len(pairs)} phantoms whose "
                    f"file survived (automated: {100 * c0:.1f} %)")
            what.append(("stalls: " + text) if c < c0 - STALL_MARGIN else text)
        shown = n > n0 or what[-1].startswith("stalls")
        out.append(Check(f"{name} ({removed[name]}): fractures or stalls", shown,
                         "; ".join(what) + f"; peak {max(r.peak_torque_mnm for r in runs):.1f} "
                         "mNm"))
    return out


def checks(runs: list[PhantomRun]) -> list[Check]:
    """The thesis's claims for experiment 2 (automated algorithm, all six phantoms)."""
    by_member: dict[int, list[PhantomRun]] = {}
    for r in runs:
        by_member.setdefault(r.spec.phantom.member, []).append(r)
    diffs, means = [], []
    for rs in by_member.values():
        m = group_means(rs)
        if 40.0 in m and 50.0 in m:
            diffs.append(m[50.0] - m[40.0])
            means.append(m)
    out = []
    if diffs:
        med = distribution(diffs, worst="min")
        m40 = float(np.median([m[40.0] for m in means]))
        m50 = float(np.median([m[50.0] for m in means]))
        out.append(Check(
            "mean completeness at tau_d 50 above tau_d 40",
            med["median"] > 0.0,
            f"tau_d 40: {100 * m40:.2f} %, tau_d 50: {100 * m50:.2f} % "
            + (f"(median of {len(diffs)} populations; 50 above 40 in "
               f"{sum(d > 0 for d in diffs)})" if len(diffs) > 1 else "")
            + f" (thesis: {100 * THESIS_MEANS[40.0]:.2f} % and {100 * THESIS_MEANS[50.0]:.2f} %)"))
    n = sum(r.fracture for r in runs)
    out.append(Check("no file fracture", n == 0,
                     f"{n} of {len(runs)} runs fractured; peak file torque "
                     f"{max(r.peak_torque_mnm for r in runs):.1f} mNm "
                     f"(strength {FILE_STRENGTH_MNM:g} mNm)"))
    return out
