"""Figures of the experiments (PNG, matplotlib's Agg canvas only: no pyplot, no display).

Experiment 1 (per configuration, after thesis fig 6.7-6.9 and 6.11-6.13):

- ``alignment-<X>-position.png``: left column, handpiece (file tip) and root (orifice)
  displacement per base axis (mm, from the square's start); right column, their relative
  distance (red), with the detachment threshold on z;
- ``alignment-<X>-force.png``: measured force (base-frame axes, N) and tip velocity (mm/s)
  per axis;
- ``alignment-ripple.png``: peak excursion out of the canal per platform speed for each
  configuration, the admittance law's prediction and the thesis's config C value.

Experiment 2 (after fig 6.19 / Table 6.5):

- ``preclinical-completeness.png``: completeness per phantom, simulator vs Table 6.5;
- ``preclinical-traces.png``: tip depth and file torque over time per phantom, with the
  working length, tau_d and the 62 mNm strength.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from dentibot.control.feedrate import FILE_STRENGTH_MNM
from dentibot.experiments import alignment as al
from dentibot.experiments import preclinical as pc

_DPI = 100
_AXES = "xyz"


def _save(fig: Figure, path: Path) -> Path:
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=_DPI)
    return path


def _figure(size) -> Figure:
    fig = Figure(figsize=size)
    FigureCanvasAgg(fig)
    return fig


def alignment_figures(run: al.AlignmentRun, out_dir: str | Path) -> list[Path]:
    """Position and force figures of one run (needs ``run.series``)."""
    s = run.series
    if s is None or len(s["t"]) < 3 or not run.speeds:
        return []
    out = Path(out_dir)
    cfg = run.spec.config
    t = s["t"]
    t0 = run.speeds[0].t0 if run.speeds else float(t[0])
    i0 = int(np.searchsorted(t, t0))
    tip, root = s["tip"] - s["tip"][i0], s["root"] - s["root"][i0]
    rel = tip - root
    paths = []
    fig = _figure((11, 8))
    axes = fig.subplots(3, 2, sharex=True)
    for j, a in enumerate(_AXES):
        ax = axes[j][0]
        ax.plot(t, tip[:, j], "b-", label="handpiece (file tip)")
        ax.plot(t, root[:, j], "b:", label="root (orifice)")
        ax.set_ylabel(f"{a} (mm)")
        ax = axes[j][1]
        ax.plot(t, rel[:, j], "r-")
        ax.set_ylabel(f"relative {a} (mm)")
        ax.grid(True, alpha=0.3)
    axes[0][0].legend(loc="best", fontsize=8)
    axes[2][1].axhline(al.DETACH_START_MM, color="k", linestyle="--", linewidth=0.8,
                       label=f"detachment {al.DETACH_START_MM} mm out")
    axes[2][1].legend(loc="best", fontsize=8)
    for ax in axes[2]:
        ax.set_xlabel("t (s)")
    fig.suptitle(f"Config {cfg}: handpiece vs root position and relative distance "
                 f"(from t = {t0:.0f} s, base axes)")
    paths.append(_save(fig, out / f"alignment-{cfg}-position.png"))

    fig = _figure((10, 8))
    axes = fig.subplots(3, 1, sharex=True)
    vel = np.gradient(s["tip"], t, axis=0)
    for j, a in enumerate(_AXES):
        ax = axes[j]
        ax.plot(t, s["force_0"][:, j], "k-", linewidth=0.8, label="force (N)")
        ax.set_ylabel(f"f{a} (N)")
        ax2 = ax.twinx()
        ax2.plot(t, vel[:, j], "g-", linewidth=0.8, alpha=0.7, label="tip velocity (mm/s)")
        ax2.set_ylabel(f"v{a} (mm/s)", color="g")
    axes[-1].set_xlabel("t (s)")
    fig.suptitle(f"Config {cfg}: measured force (base axes) and handpiece velocity")
    paths.append(_save(fig, out / f"alignment-{cfg}-force.png"))
    return paths


def ripple_figure(runs: dict[str, list[al.AlignmentRun]], out_dir: str | Path) -> Path | None:
    """Peak excursion out of the canal per speed (median and worst over the runs)."""
    if not runs:
        return None
    fig = _figure((7, 5))
    ax = fig.subplots()
    for k, (cfg, rs) in enumerate(sorted(runs.items())):
        rs = [r for r in rs if r.speeds]
        if not rs:
            continue
        speeds = [s.speed_mm_s for s in rs[0].speeds]
        vals = np.array([[r.speeds[i].max_out_mm for i in range(len(speeds))] for r in rs])
        ax.plot(speeds, np.median(vals, axis=0), "o-", color=f"C{k}", label=f"config {cfg}")
        if len(rs) > 1:
            ax.plot(speeds, vals.max(axis=0), "v:", color=f"C{k}", label=f"{cfg} worst")
        v = np.linspace(min(speeds), max(speeds), 50)
        ax.plot(v, [al.expected_ripple_mm(cfg, x) for x in v], "--", color=f"C{k}",
                alpha=0.5, label=f"{cfg} admittance law")
    ax.plot([6.0], [al.THESIS["ripple_c_6mm_s_mm"]], "r*", markersize=12,
            label="thesis, config C")
    ax.axhline(al.DETACH_START_MM, color="k", linestyle=":", linewidth=0.8)
    ax.set_xlabel("platform speed (mm/s)")
    ax.set_ylabel("peak excursion out of the canal (mm)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle("Experiment 1: detachment along the insertion axis vs platform speed")
    return _save(fig, Path(out_dir) / "alignment-ripple.png")


def preclinical_figures(runs: list[pc.PhantomRun], out_dir: str | Path) -> list[Path]:
    """Completeness bars (simulator vs Table 6.5) and depth/torque traces."""
    if not runs:
        return []
    out = Path(out_dir)
    paths = []
    fig = _figure((8, 4.5))
    ax = fig.subplots()
    names = [r.name for r in runs]
    x = np.arange(len(runs))
    ax.bar(x - 0.2, [100 * r.completeness for r in runs], 0.4, label="simulator")
    ax.bar(x + 0.2, [100 * pc.THESIS_TABLE_6_5[n][2] for n in names], 0.4,
           label="thesis Table 6.5", alpha=0.7)
    for i, r in enumerate(runs):
        if r.fracture:
            ax.text(i - 0.2, 5, "fracture", rotation=90, ha="center", color="r")
    ax.set_xticks(x, [f"{r.name}\n{r.spec.phantom.kind}\ntau_d {r.spec.phantom.tau_d_mnm:g}"
                      for r in runs])
    lo = min([100 * r.completeness for r in runs] + [80.0])
    ax.set_ylim(max(0.0, lo - 5), 101)
    ax.set_ylabel("completeness (%)")
    ax.legend(loc="lower right")
    ax.set_title(f"Experiment 2: completeness, strategy {runs[0].spec.strategy}")
    paths.append(_save(fig, out / "preclinical-completeness.png"))

    traced = [r for r in runs if r.trace is not None and len(r.trace["t"]) > 1]
    if traced:
        fig = _figure((11, 2.2 * len(traced)))
        axes = np.atleast_2d(fig.subplots(len(traced), 1, sharex=True, squeeze=False))
        for ax, r in zip(axes[:, 0], traced):
            tr = r.trace
            ax.plot(tr["t"], tr["depth"], "b-", linewidth=0.8)
            ax.axhline(r.spec.phantom.working_length_mm, color="b", linestyle=":",
                       linewidth=0.8)
            ax.set_ylabel(f"{r.name} depth (mm)", color="b")
            # from the orifice down (the load calibration before moves the tip far away)
            ax.set_ylim(-3.0, r.spec.phantom.working_length_mm + 2.0)
            ax2 = ax.twinx()
            ax2.plot(tr["t"], tr["torque"], "k-", linewidth=0.5, alpha=0.7)
            ax2.axhline(r.spec.phantom.tau_d_mnm, color="g", linestyle="--", linewidth=0.8)
            ax2.axhline(FILE_STRENGTH_MNM, color="r", linestyle="--", linewidth=0.8)
            ax2.set_ylabel("torque (mNm)")
            ax2.set_ylim(-20, FILE_STRENGTH_MNM + 8)
        axes[-1, 0].set_xlabel("t (s)")
        fig.suptitle("Experiment 2: tip depth (blue; working length dotted) and file torque "
                     "(black; tau_d green, 62 mNm red)")
        paths.append(_save(fig, out / "preclinical-traces.png"))
    return paths
