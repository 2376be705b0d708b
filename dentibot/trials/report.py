"""A trial's answer: per arm, and per arm and Schneider curvature class, the rates a setting is
chosen by, with 95 % intervals; as one JSON-ready dict (:func:`summarize`) and as figures
(:func:`figures`).

Rates (fracture, reaching the working length, over-instrumentation) come with the Wilson score
interval (Wilson 1927, J Am Stat Assoc 22:209; recommended over the Wald interval for small
``n`` and rates near 0 or 1 by Newcombe 1998, Stat Med 17:857 and Brown, Cai & DasGupta 2001,
Stat Sci 16:101): it is never outside 0..1 and not empty at 0 of ``n``. Distributions
(completeness, time to the working length) as median and interquartile range. The file life
(:mod:`dentibot.trials.fatigue`): canals per file, per arm.

Summary keys: ``trial``, ``seed``, ``spec_hash``, ``procedures``, and ``arms[]``, each with
``name``, its settings, ``n``, ``fractures``, ``fracture_rate``, ``fracture_rate_ci``,
``fracture_causes``, ``reached_wl_rate`` (and ``_ci``), ``t_wl_s`` (median, q25, q75, n of the
procedures that reached it), ``completeness_median``, ``completeness_iqr``,
``over_instrumentation_rate`` (and ``_ci``), ``peak_torque_mnm`` (median, max), stalls and
faults, ``not_completed`` (runs that ended in a fault or were aborted), ``file_life``, and
``by_curvature`` (the same figures per class).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa

from dentibot.jsonsafe import finite as clean
from dentibot.trials import fatigue
from dentibot.trials.population import SCHNEIDER_CLASSES
from dentibot.trials.spec import TrialSpec

#: The standard normal quantile of a two-sided 95 % interval.
Z95 = 1.959963984540054


def wilson(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of ``k`` successes in ``n`` trials:
    ``(p + z^2/2n -+ z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)``; (0, 1) for ``n = 0``."""
    if n <= 0:
        return (0.0, 1.0)
    p = k / n
    z2 = z * z
    centre = p + z2 / (2 * n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    den = 1 + z2 / n
    lo = 0.0 if k == 0 else max(0.0, (centre - half) / den)
    hi = 1.0 if k == n else min(1.0, (centre + half) / den)
    return (lo, hi)


def _rate(flags: Sequence[bool]) -> tuple[float | None, list[float]]:
    n = len(flags)
    k = int(sum(bool(f) for f in flags))
    return (k / n if n else None), list(wilson(k, n))


def _quartiles(values: Sequence[float | None]) -> dict:
    vals = np.asarray([v for v in values if v is not None and math.isfinite(v)], float)
    if vals.size == 0:
        return {"median": None, "q25": None, "q75": None, "n": 0}
    q25, med, q75 = (float(x) for x in np.percentile(vals, [25, 50, 75]))
    return {"median": med, "q25": q25, "q75": q75, "n": int(vals.size)}


def _figures_of(rows: list[dict]) -> dict:
    n = len(rows)
    frac = [r["fracture"] for r in rows]
    rate, ci = _rate(frac)
    reached, reached_ci = _rate([r["reached_wl"] for r in rows])
    over, over_ci = _rate([r["over_instrumented"] for r in rows])
    comp = _quartiles([r["completeness"] for r in rows])
    causes: dict[str, int] = {}
    for r in rows:
        if r["fracture"]:
            causes[r["fracture_cause"]] = causes.get(r["fracture_cause"], 0) + 1
    torque = [r["peak_torque_mnm"] for r in rows]
    return {
        "n": n, "fractures": int(sum(frac)), "fracture_rate": rate, "fracture_rate_ci": ci,
        "fracture_causes": causes,
        "reached_wl": int(sum(r["reached_wl"] for r in rows)), "reached_wl_rate": reached,
        "reached_wl_rate_ci": reached_ci,
        "t_wl_s": _quartiles([r["t_wl_s"] for r in rows]),
        "completeness_median": comp["median"],
        "completeness_iqr": [comp["q25"], comp["q75"]],
        "over_instrumented": int(sum(r["over_instrumented"] for r in rows)),
        "over_instrumentation_rate": over, "over_instrumentation_rate_ci": over_ci,
        "overshoot_mm_max": max((r["overshoot_mm"] for r in rows), default=None),
        "peak_torque_mnm": {"median": _quartiles(torque)["median"],
                            "max": max(torque, default=None)},
        "motor_stall_s": _quartiles([r["motor_stall_s"] for r in rows]),
        "feed_stall_s": _quartiles([r["feed_stall_s"] for r in rows]),
        "faults": int(sum(r["faults"] for r in rows)),
        "not_completed": int(sum(r["status"] not in ("ok", "fracture") for r in rows)),
    }


def summarize(table: pa.Table, spec: TrialSpec) -> dict:
    """The trial's summary (see the module's docstring for the keys)."""
    rows = table.to_pylist()
    lives = file_life_samples(table, spec)
    arms = []
    for a, arm in enumerate(spec.arms):
        mine = [r for r in rows if r["arm_index"] == a]
        entry = {"name": arm.name, **arm.model_dump(exclude={"name"}), **_figures_of(mine)}
        entry["file_life"] = fatigue.life_summary(lives[arm.name], spec.file_life.max_canals)
        entry["file_life"]["fatigue_damage_per_canal"] = _quartiles(
            [r["fatigue_damage"] for r in mine])
        entry["by_curvature"] = {
            c: _figures_of([r for r in mine if r["curvature"] == c])
            for c in SCHNEIDER_CLASSES if any(r["curvature"] == c for r in mine)}
        arms.append(entry)
    return clean({"trial": spec.name, "seed": spec.seed, "spec_hash": spec.spec_hash(),
                  "procedures": len(rows), "rounds_s": list(spec.rounds_s), "arms": arms})


def file_life_samples(table: pa.Table, spec: TrialSpec) -> dict[str, np.ndarray]:
    """Canals per file of each arm (the samples behind ``file_life``), from a stream of the
    trial's seed and the arm's index."""
    rows = table.to_pylist()
    out = {}
    for a, arm in enumerate(spec.arms):
        mine = [r for r in rows if r["arm_index"] == a]
        rng = np.random.default_rng([spec.seed, a, 0xF11E])
        out[arm.name] = fatigue.canals_until_failure(
            [r["fatigue_damage"] for r in mine], [r["fracture"] for r in mine], rng,
            spec.file_life.files, spec.file_life.max_canals)
    return out


def _save(fig, path: Path) -> Path:
    """Lay ``fig`` out, write it to ``path`` (PNG, 120 dpi) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def figures(table: pa.Table, spec: TrialSpec, summary: dict, out: str | Path) -> list[Path]:
    """PNG figures in ``out``: fracture rate per arm and curvature class with Wilson 95 %
    intervals; completeness per arm; canals per file per arm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    arms = summary["arms"]
    names = [a["name"] for a in arms]
    x = np.arange(len(arms))

    fig, ax = plt.subplots(figsize=(7, 4))
    groups = [("all", None), *((c, c) for c in SCHNEIDER_CLASSES
                               if any(c in a["by_curvature"] for a in arms))]
    width = 0.8 / len(groups)
    for g, (label, cls) in enumerate(groups):
        rates, lo, hi = [], [], []
        for a in arms:
            e = a if cls is None else a["by_curvature"].get(cls)
            if e is None or not e["n"]:
                rates.append(np.nan)
                lo.append(0.0)
                hi.append(0.0)
                continue
            rates.append(e["fracture_rate"])
            lo.append(max(0.0, e["fracture_rate"] - e["fracture_rate_ci"][0]))
            hi.append(max(0.0, e["fracture_rate_ci"][1] - e["fracture_rate"]))
        ax.bar(x + (g - (len(groups) - 1) / 2) * width, rates, width, yerr=[lo, hi],
               capsize=3, label=label)
    ax.set_xticks(x, names)
    ax.set_ylim(0, 1)
    ax.set_ylabel("fracture rate (Wilson 95 % CI)")
    ax.set_title(f"{spec.name}: file fractures per arm and Schneider class")
    ax.legend(fontsize=8)
    paths.append(_save(fig, out / "fracture_rate.png"))

    rows = table.to_pylist()
    fig, ax = plt.subplots(figsize=(7, 4))
    data = [[r["completeness"] for r in rows if r["arm_index"] == a] for a in range(len(arms))]
    ax.boxplot(data, tick_labels=names)
    ax.set_ylabel("completeness (eq 6.1)")
    ax.set_ylim(0, 1.02)
    ax.set_title(f"{spec.name}: completeness per arm")
    paths.append(_save(fig, out / "completeness.png"))

    samples = file_life_samples(table, spec)
    fig, ax = plt.subplots(figsize=(7, 4))
    cap = spec.file_life.max_canals
    for name, canals in samples.items():
        if canals.size == 0:
            continue
        k = np.arange(1, cap + 1)
        surv = [(canals > i).mean() for i in k]
        ax.step(k, surv, where="post", label=name)
    ax.set_xscale("log")
    ax.set_xlabel("canals prepared")
    ax.set_ylabel("files still whole")
    ax.set_ylim(0, 1.02)
    ax.set_title(f"{spec.name}: file life (Miner's rule over canals drawn from each arm)")
    ax.legend(fontsize=8)
    paths.append(_save(fig, out / "file_life.png"))
    return paths
