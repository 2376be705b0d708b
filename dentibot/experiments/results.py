"""An experiment end to end: its runs (in parallel local processes), its figures, the thesis's
claims checked on them, and its result as one JSON-ready dict.

``dentibot experiment NAME`` shows these results as tables, or prints :meth:`to_dict` with
``--json``; :func:`dentibot.api.run_experiment` returns :meth:`to_dict`. The parameters of
:func:`alignment_experiment` and :func:`preclinical_experiment` are the command's options
(``_`` for ``-``), with the same defaults; bad values raise
:class:`~dentibot.errors.ConfigError` before anything runs.

``progress(line)`` gets one line per finished run, in the calling thread. ``cancel``: a
:class:`threading.Event` that, once set from another thread, stops the experiment as Ctrl-C
does (see :func:`~dentibot.app.batch.run_all`). Either way the experiment raises
KeyboardInterrupt and returns no result.
"""

from __future__ import annotations

import inspect
import math
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dentibot.app import batch
from dentibot.app.batch import default_workers, run_all
from dentibot.control.feedrate import FILE_STRENGTH_MNM
from dentibot.errors import ConfigError
from dentibot.experiments import alignment as al
from dentibot.experiments import patient_jerk as pj
from dentibot.experiments import preclinical as pc
from dentibot.experiments.common import Check
from dentibot.jsonsafe import finite as clean
from dentibot.protocol.schema import MATERIAL_NAMES

#: Where the figures go unless told (alignment: its ``alignment`` folder; preclinical: one
#: ``preclinical-<strategy>`` folder per strategy).
FIGURES_DIR = Path("runs/experiments")
#: Upper bounds of the options: platform speed (mm/s), a drilling round (s).
MAX_SPEED_MM_S = 20.0
MAX_ROUND_S = 3600.0

Progress = Callable[[str], None]


# ---------------------------------------------------------------------------- helpers
def _worst(values: Iterable[float | None]) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    return max(vals) if vals else None


def in_range(field: str, values: Iterable[float], unit: str, hi: float) -> tuple[float, ...]:
    """``values`` as floats, each in (0, ``hi``]; ConfigError (its ``limit`` says the range)
    otherwise."""
    try:
        vals = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ConfigError(field, values, f"numbers of {unit}") from None
    if not vals or any(not (0.0 < v <= hi) for v in vals):
        raise ConfigError(field, values, f"each 0 < {unit} <= {hi:g}")
    return vals


def speeds_of(values: Iterable[float]) -> tuple[float, ...]:
    """Platform speeds of the squares (mm/s)."""
    return in_range("speeds", values, "mm/s", MAX_SPEED_MM_S)


def rounds_of(values: Iterable[float]) -> tuple[float, ...]:
    """Drilling round durations (s)."""
    return in_range("rounds", values, "seconds", MAX_ROUND_S)


def torque_limit_of(value: float) -> float:
    """The runtime's hard file-torque limit (mNm): up to the file's strength."""
    return in_range("torque_limit", (value,), "mNm", FILE_STRENGTH_MNM)[0]


def _count(field: str, n: Any) -> int:
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ConfigError(field, n, "a whole number >= 1")
    return n


def _choice(field: str, value: Any, choices: Sequence[str]) -> str:
    if value not in choices:
        raise ConfigError(field, value, f"one of {', '.join(choices)}")
    return value


def _seeds(seeds: int, seed: int) -> list[int]:
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError("seed", seed, "a whole number")
    return list(range(seed, seed + _count("seeds", seeds)))


def _workers(workers: int | None) -> int:
    return default_workers() if workers is None else _count("workers", workers)


def _say(progress: Progress | None, text: str) -> None:
    if progress is not None:
        progress(text)


def _checks_dicts(checks: list[Check]) -> list[dict]:
    return [c.to_dict() for c in checks]


# ---------------------------------------------------------------------------- alignment
@dataclass
class AlignmentResult:
    """Experiment 1: the runs (configuration by configuration, seed by seed), the thesis's
    claims checked on them, the figures written and the wall time of the runs (s)."""

    runs: list[al.AlignmentRun]
    seeds: list[int]
    checks: list[Check]
    figures: list[Path]
    wall_s: float
    tracking: str = "force"

    @property
    def by_config(self) -> dict[str, list[al.AlignmentRun]]:
        out: dict[str, list[al.AlignmentRun]] = {}
        for r in self.runs:
            out.setdefault(r.spec.config, []).append(r)
        return out

    @property
    def passed(self) -> bool:
        """Every claim of the thesis shown."""
        return all(c.passed for c in self.checks)

    def to_dict(self) -> dict:
        """What ``dentibot experiment alignment --json`` prints."""
        configs = {}
        for cfg, rs in sorted(self.by_config.items()):
            entry = {"max_rel_mm": {a: _worst(r.max_rel_mm[a] for r in rs) for a in "xyz"},
                     "rms_rel_mm": {a: _worst(r.rms_rel_mm[a] for r in rs) for a in "xyz"}}
            if len(rs) == 1:
                entry.update(rs[0].to_dict())
            else:
                entry["population"] = al.population_summary(rs)
                entry["runs"] = [r.to_dict() for r in rs]
            configs[cfg] = entry
        return clean({
            "experiment": "alignment", "seeds": self.seeds, "configs": configs,
            "definitions": {
                "relative_distance": "(file tip - orifice) minus its value at the square's "
                                     "start, base-frame x, y, z (mm); max of |.| and RMS over "
                                     "the square and the tail; with a population, max_rel_mm "
                                     "is the worst case",
                "detachment": f"the tip more than {al.DETACH_START_MM} mm out of its seated "
                              "position along the file axis (at the square's start), until "
                              f"back within {al.DETACH_END_MM} mm; recovery_s from the peak",
                "expected_ripple_mm": "admittance law: 15 mm x (1 - k fz_max / (b3 v))",
                "max_lateral_mm": "the largest relative distance across the file axis at "
                                  "the square's start (mm)",
            },
            "tracking": self.tracking,
            "hybrid_targets": al.HYBRID_TARGETS if self.tracking == "hybrid" else None,
            "thesis": al.THESIS, "checks": _checks_dicts(self.checks),
            "figures": [str(p) for p in self.figures], "wall_s": self.wall_s,
        })


def alignment_experiment(*, config: str = "all", speeds: Sequence[float] = al.SPEEDS_MM_S,
                         seeds: int = 1, seed: int = 1, workers: int | None = None,
                         out: str | Path | None = None, no_figures: bool = False,
                         tracking: str = "force", progress: Progress | None = None,
                         cancel: threading.Event | None = None) -> AlignmentResult:
    """Experiment 1 (Table 6.4): ``config`` A, B, C or all; platform ``speeds`` (mm/s);
    ``seeds`` seeded random patients from ``seed`` (one: the thesis's set-up); ``workers``
    local processes (None: the CPU count); figures in ``out`` (default
    runs/experiments/alignment, or alignment-hybrid) unless ``no_figures``. ``tracking``:
    ``force``, the thesis's admittance alone, checked against the thesis's claims; ``hybrid``,
    with the patient tracker and its motion fed forward, checked against
    :data:`~dentibot.experiments.alignment.HYBRID_TARGETS`."""
    tracking = _choice("tracking", tracking, al.TRACKING)
    configs = list(al.CONFIGS) if config == "all" else [_choice("config", config,
                                                                (*al.CONFIGS, "all"))]
    speeds_mm_s = speeds_of(speeds)
    seed_list = _seeds(seeds, seed)
    n_workers = _workers(workers)
    specs = [al.AlignmentSpec(config=c, seed=s, speeds_mm_s=speeds_mm_s,
                              patient=None if len(seed_list) == 1 else al.variation(s),
                              keep_series=not no_figures and s == seed_list[0],
                              tracking=tracking)
             for c in configs for s in seed_list]
    started = time.perf_counter()

    def done(spec: al.AlignmentSpec, run: al.AlignmentRun) -> None:
        mode = "" if tracking == "force" else f" ({tracking})"
        _say(progress, f"config {spec.config} seed {spec.seed}{mode}: {run.status}, max |x| "
                       f"{run.max_rel_mm['x']:.2f} mm, max across {run.max_lateral_mm:.2f} "
                       f"mm, peak out {run.max_out_mm:.2f} mm ({run.wall_s:.0f} s)")

    runs = run_all(al.run_alignment, specs, workers=n_workers, done=done, cancel=cancel)
    wall = time.perf_counter() - started
    result = AlignmentResult(runs=runs, seeds=seed_list, checks=[], figures=[], wall_s=wall,
                             tracking=tracking)
    by_config = result.by_config
    if not no_figures:
        from dentibot.experiments.figures import alignment_figures, ripple_figure

        folder = Path(out or FIGURES_DIR / ("alignment" if tracking == "force"
                                            else "alignment-hybrid"))
        for rs in by_config.values():
            result.figures += alignment_figures(rs[0], folder)
        rip = ripple_figure(by_config, folder) if tracking == "force" else None
        if rip is not None:
            result.figures.append(rip)
    result.checks = al.checks(by_config) if tracking == "force" else al.hybrid_checks(by_config)
    return result


# ---------------------------------------------------------------------------- preclinical
def _preclinical_dict(runs: list[pc.PhantomRun], checks: list[Check], figures: list[Path],
                      wall_s: float | None) -> dict:
    members = sorted({r.spec.phantom.member for r in runs})
    spec = runs[0].spec
    out: dict[str, Any] = {"experiment": "preclinical", "strategy": spec.strategy,
                           "rounds_s": list(spec.rounds_s), "seeds": members,
                           "material": spec.material,
                           "torque_limit_mnm": pc.torque_limit_of(spec)}
    if len(members) == 1:
        out["phantoms"] = [r.to_dict() for r in runs]
        out["means"] = {f"{k:g}": v for k, v in pc.group_means(runs).items()}
    else:
        p = pc.population_summary(runs)
        out["phantoms"] = [{"name": e["name"], "tau_d": e["tau_d"],
                            "completeness": e["completeness"]["median"],
                            "completeness_worst": e["completeness"]["worst"],
                            "fracture": e["fractures"] > 0, **e} for e in p["phantoms"]]
        out["population"] = {k: v for k, v in p.items() if k != "phantoms"}
        out["runs"] = [r.to_dict() for r in runs]
    out.update({
        "definitions": {
            "red_mm2": "red-stained canal as a photograph across it shows it, to the working "
                       "length (Table 6.5 counts the pixels of such photographs)",
            "shaping": "removed fraction of the volume between the initial lumen and the "
                       "target #25/.06 shape, 0..1",
            "completeness": "eq 6.1, (red before - red after) / red before, 0..1",
            "peak_torque_mnm": "largest true file torque (simulator), strength 62 mNm",
            "stalled_s": f"feeding before first reaching the working length while the deepest "
                         f"point gained < {batch.STALL_GAIN_MM} mm in {batch.STALL_WINDOW_S:g} s",
        },
        "thesis": {"table_6_5": {k: {"red_before_px": v[0], "red_after_px": v[1],
                                     "completeness": v[2], "fracture": v[3]}
                                 for k, v in pc.THESIS_TABLE_6_5.items()},
                   "means": {f"{k:g}": v for k, v in pc.THESIS_MEANS.items()}},
        "checks": _checks_dicts(checks),
        "figures": [str(p) for p in figures], "wall_s": wall_s})
    return out


@dataclass
class PreclinicalResult:
    """Experiment 2: the runs (strategy by strategy, seed by seed, phantom by phantom), the
    thesis's claims checked on them (an ablation alone claims none), the figures written and
    the wall time of the runs (s)."""

    runs: list[pc.PhantomRun]
    strategies: tuple[str, ...]
    checks: list[Check]
    figures: list[Path]
    wall_s: float

    @property
    def by_strategy(self) -> dict[str, list[pc.PhantomRun]]:
        return {st: [r for r in self.runs if r.spec.strategy == st] for st in self.strategies}

    @property
    def passed(self) -> bool:
        """Every claim of the thesis shown."""
        return all(c.passed for c in self.checks)

    def to_dict(self) -> dict:
        """What ``dentibot experiment preclinical --json`` prints."""
        by = self.by_strategy
        if len(by) == 1:
            return clean(_preclinical_dict(self.runs, self.checks, self.figures, self.wall_s))
        return clean({"experiment": "preclinical", "strategy": "all",
                      "strategies": {st: _preclinical_dict(rs, [], [], None)
                                     for st, rs in by.items()},
                      "checks": _checks_dicts(self.checks),
                      "figures": [str(p) for p in self.figures], "wall_s": self.wall_s})


def preclinical_experiment(*, strategy: str = "automated", material: str | dict = pc.MATERIAL,
                           torque_limit: float | None = None, phantom: str = "all",
                           rounds: Sequence[float] = pc.ROUNDS_S, seeds: int = 1,
                           seed: int = 1, workers: int | None = None,
                           out: str | Path | None = None, no_figures: bool = False,
                           progress: Progress | None = None,
                           cancel: threading.Event | None = None) -> PreclinicalResult:
    """Experiment 2 (Table 6.5): ``strategy`` automated, an ablation (feedrate, reversal,
    none) or all four on the same phantoms; phantom ``material``; the runtime's hard
    ``torque_limit`` (mNm; None: 90 % of the strength for automated, the strength itself for
    the ablations); ``phantom`` letters (e.g. "AD") or all; drilling ``rounds`` (s); ``seeds``
    phantom sets from ``seed``; ``workers`` local processes (None: the CPU count); figures in
    ``out``/preclinical-<strategy> (default runs/experiments) unless ``no_figures``."""
    strategies = pc.STRATEGIES if strategy == "all" else (
        _choice("strategy", strategy, (*pc.STRATEGIES, "all")),)
    if isinstance(material, str):
        _choice("material", material, tuple(MATERIAL_NAMES))
    limit = None if torque_limit is None else torque_limit_of(torque_limit)
    names = pc.NAMES if phantom == "all" else tuple(str(phantom))
    bad = [n for n in names if n not in pc.NAMES]
    if bad or not names:
        raise ConfigError("phantom", "".join(bad), f"letters of {''.join(pc.NAMES)} or 'all'")
    rounds_s = rounds_of(rounds)
    seed_list = _seeds(seeds, seed)
    n_workers = _workers(workers)
    specs = [pc.PreclinicalSpec(p, strategy=st, rounds_s=rounds_s, material=material,
                                torque_limit_mnm=(pc.default_torque_limit(st)
                                                  if limit is None else limit),
                                keep_trace=not no_figures and s == seed_list[0])
             for st in strategies for s in seed_list for p in pc.phantoms(s, names)]
    started = time.perf_counter()

    def done(spec: pc.PreclinicalSpec, run: pc.PhantomRun) -> None:
        p = spec.phantom
        _say(progress, f"{spec.strategy}: phantom {p.name} ({p.describe()}, tau_d "
                       f"{p.tau_d_mnm:g}) seed {p.member}: {100 * run.completeness:.2f} %, "
                       f"{'fracture' if run.fracture else 'no fracture'}, peak "
                       f"{run.peak_torque_mnm:.1f} mNm ({run.wall_s:.0f} s)")

    runs = run_all(pc.run_phantom, specs, workers=n_workers, done=done, cancel=cancel)
    wall = time.perf_counter() - started
    result = PreclinicalResult(runs=runs, strategies=tuple(strategies), checks=[], figures=[],
                               wall_s=wall)
    by = result.by_strategy
    if not no_figures:
        from dentibot.experiments.figures import preclinical_figures

        for st, rs in by.items():
            first = [r for r in rs if r.spec.phantom.member == seed_list[0]]
            result.figures += preclinical_figures(first, Path(out or FIGURES_DIR)
                                                  / f"preclinical-{st}")
    result.checks = ((pc.checks(by["automated"]) if "automated" in by else [])
                     + pc.ablation_checks(by))
    return result


# ---------------------------------------------------------------------------- patient jerk
@dataclass
class PatientJerkResult:
    """Both modes of :mod:`dentibot.experiments.patient_jerk` on the same jerk."""

    runs: dict[str, pj.JerkRun]
    checks: list[Check]
    spec: pj.JerkSpec
    wall_s: float

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.checks)

    def to_dict(self) -> dict:
        return clean({"experiment": "patient-jerk", "mm": self.spec.mm,
                      "mm_s": self.spec.mm_s, "deg": self.spec.deg, "hinge_mm": pj.HINGE_MM,
                      "seed": self.spec.seed,
                      "watch_s": self.spec.watch_s,
                      "modes": {m: r.to_dict() for m, r in self.runs.items()},
                      "checks": _checks_dicts(self.checks), "wall_s": self.wall_s})


def patient_jerk_experiment(*, mm: float = 3.0, mm_s: float = 20.0, deg: float = 0.0,
                            seed: int = 1, workers: int | None = None,
                            progress: Progress | None = None,
                            cancel: threading.Event | None = None) -> PatientJerkResult:
    """The tooth steps ``mm`` towards the robot along the canal at ``mm_s`` (and turns by
    ``deg`` about the jaw's hinge) while the file works at the working length, with depth in
    the base frame (``force``), in the tooth's frame (``tracked``), and with hybrid control
    (``hybrid``)."""
    in_range("mm", [mm], "mm", 10.0)
    in_range("mm_s", [mm_s], "mm/s", 200.0)
    if not (math.isfinite(deg) and abs(deg) <= pj.MAX_DEG):
        raise ConfigError("deg", deg, f"-{pj.MAX_DEG:g} <= deg <= {pj.MAX_DEG:g}")
    specs = [pj.JerkSpec(mode=m, mm=mm, mm_s=mm_s, seed=seed, deg=deg) for m in pj.MODES]
    started = time.perf_counter()

    def done(spec: pj.JerkSpec, run: pj.JerkRun) -> None:
        axis = "--" if run.axis_error_deg is None or math.isnan(run.axis_error_deg) \
            else f"{run.axis_error_deg:.2f}"
        _say(progress, f"{spec.mode}: overshoot {run.overshoot_mm:.2f} mm, "
                       f"{run.past_wl_s:.2f} s past the working length, axis error "
                       f"{axis} deg, {run.final_state}")

    runs = run_all(pj.run_jerk, specs, workers=_workers(workers), done=done, cancel=cancel)
    by = {r.mode: r for r in runs}
    return PatientJerkResult(by, pj.checks(by, deg=deg), specs[0],
                             time.perf_counter() - started)


# ---------------------------------------------------------------------------- by name
EXPERIMENTS: dict[str, Callable[..., AlignmentResult | PreclinicalResult | PatientJerkResult]] = {
    "alignment": alignment_experiment, "preclinical": preclinical_experiment,
    "patient-jerk": patient_jerk_experiment}


def options_of(name: str) -> tuple[str, ...]:
    """The options of experiment ``name`` (its command's long options, ``_`` for ``-``)."""
    run = EXPERIMENTS[_choice("experiment", name, tuple(EXPERIMENTS))]
    return tuple(p for p in inspect.signature(run).parameters
                 if p not in ("progress", "cancel"))


def run_experiment(name: str, *, progress: Progress | None = None,
                   cancel: threading.Event | None = None,
                   **options: Any) -> AlignmentResult | PreclinicalResult:
    """Experiment ``name`` (alignment, preclinical) with ``options``; ConfigError for an
    unknown experiment or option, or a bad value."""
    known = options_of(name)
    for key in options:
        if key not in known:
            raise ConfigError("option", key, f"one of {', '.join(known)}")
    return EXPERIMENTS[name](progress=progress, cancel=cancel, **options)


# ---------------------------------------------------------------------------- the bench
def bench_alignment_experiment(*, config: str = "all", seeds: int = 1, seed: int = 1,
                               workers: int | None = None, progress: Progress | None = None,
                               cancel: threading.Event | None = None) -> dict:
    """Experiment 1 on the bench-fitted world (:mod:`dentibot.sim.bench_physics`), configs
    A, B, C and C_K250 as the thesis's bench ran them: per config ``bench_figures``, the
    median over ``seeds`` runs of each of the recordings' per-trial figures
    (:func:`~dentibot.experiments.alignment.bench_figures`)."""
    configs = list(al.BENCH_CONFIGS) if config == "all" else [
        _choice("config", config, (*al.BENCH_CONFIGS, "all"))]
    seed_list = _seeds(seeds, seed)
    specs = [al.BenchSpec(config=c, seed=s) for c in configs for s in seed_list]
    started = time.perf_counter()

    def done(spec: al.BenchSpec, figs: dict) -> None:
        _say(progress, f"bench config {spec.config} seed {spec.seed}: Z out "
                       + "/".join(f"{figs[f'sq{k}_z_out_max_mm']:.2f}" for k in (1, 2, 3, 4))
                       + " mm")

    runs = run_all(al.run_bench, specs, workers=_workers(workers), done=done, cancel=cancel)
    out: dict[str, Any] = {}
    for c in configs:
        rs = [r for sp, r in zip(specs, runs) if sp.config == c]
        med = {}
        for name in rs[0]:
            vals = [r[name] for r in rs if r[name] is not None]
            med[name] = float(np.median(vals)) if vals else None
        out[c] = {"bench_figures": med, "seeds": seed_list}
    return clean({"experiment": "alignment", "world": "bench", "seeds": seed_list,
                  "configs": out, "wall_s": time.perf_counter() - started})
