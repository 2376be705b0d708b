"""Thesis experiment 1 (6.2): force-guided alignment while the patient moves.

The tooth phantom rides the Stewart-platform square of the thesis (15 x 15 mm in the x-z
plane; 3, 4, 5, 6 mm/s; 10 s pauses; 87 s) while the file is held in the canal by
self-alignment with Table 6.4's parameters (config A: no file rotation, fz = 1 N, b6 = 80;
B: rotation, fz = 1 N, b6 = inf; C: rotation + feedrate control, fz in -0.2..0.5 N).

The run (one protocol with one ``align`` step, Table 6.4 through ``config``, on a pre-shaped
canal as in the thesis):

1. ``insertion_s`` (default 10 s): the phantom rests while the file goes in to the canal
   bottom (the thesis starts its figures with the file inserted: "original offset");
2. the square, 87 s;
3. ``tail_s`` (default 10 s) at rest, so that a detachment at the end of the last square can
   be seen to recover.

Measures (all from simulator truth: the file tip and the orifice in base-frame axes):

- relative distance handpiece-root: ``(tip - orifice) - (tip - orifice)(t_square_start)``
  per base axis x, y, z (the thesis removes the initial offset the same way); max of the
  absolute value and RMS over the square and the tail, overall and per speed (window of a
  speed: from the start of its square to the start of the next one, the pause included; the
  last one runs to the end of the tail);
- detachment along the insertion axis: ``out = -(relative distance . a)`` with ``a`` the file
  axis (pointing into the tooth) at the square's start: how far the tip is out of its seated
  position along the canal. A detachment starts when ``out`` exceeds
  :data:`DETACH_START_MM` and ends (recovered) when it is back below
  :data:`DETACH_END_MM`; its recovery time is from the peak to the end.

What the admittance law predicts, from the thesis's numbers alone (:func:`expected_ripple_mm`):
a file held by a constant insertion force fz follows a receding canal at most at
``v_c = k fz / b3`` (eq 4.35: 6.25 mm/s per N). When the phantom moves away along the
insertion axis at ``v > v_c`` over ``L = 15 mm``, the tip falls behind by
``L (1 - v_c / v)``, then catches up at ``v_c``. Config C (fz <= 0.5 N): v_c = 3.125 mm/s,
ripples of 0, 3.3, 5.6 and 7.2 mm at 3, 4, 5, 6 mm/s, each recovered in under 2.5 s;
A and B (fz = 1 N): v_c = 6.25 mm/s, no ripple at these speeds.

``tracking``: ``force`` (default) is the thesis's experiment, the file held by the admittance
law alone; ``hybrid`` runs the same patient motion with the patient tracker and hybrid
position/force control (:meth:`dentibot.runtime.tooth.ToothFrame.feedforward_h`): the tooth's
tracked motion is fed forward to the arm and the force law corrects the rest, so the chase
speed of eq 4.35 no longer bounds how fast the file follows. Its targets
(:data:`HYBRID_TARGETS`, :func:`hybrid_checks`): the tip within 0.5 mm of its seated position
across the canal axis (``max_lateral_mm``) and along it (``max_rel_mm`` z, the Z ripple), no
detachment, at every speed.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from dentibot.control.admittance import EXPERIMENT_1
from dentibot.app.batch import run_protocol
from dentibot.experiments.common import Check, distribution
from dentibot.protocol.schema import Protocol
from dentibot.app.simulated import SQUARE_MM, StewartSquare

CONFIGS = ("A", "B", "C")
#: How the file follows the patient: the admittance law alone (the thesis), or hybrid control
#: with the patient tracker (the tracked tooth's motion fed forward).
TRACKING = ("force", "hybrid")
#: Hybrid control's targets on experiment 1's path (mm), at every speed: the tip's largest
#: distance from its seated position across the canal axis, and along it (either way).
HYBRID_TARGETS = {"lateral_mm": 0.5, "z_ripple_mm": 0.5}
#: Thesis 6.2: square speeds (mm/s) and the pause between squares (s).
SPEEDS_MM_S = (3.0, 4.0, 5.0, 6.0)
PAUSE_S = 10.0
#: Side of the square (mm).
SIDE_MM = 15.0
#: A detachment starts when the tip is this far out of its seated position (mm) ...
DETACH_START_MM = 1.0
#: ... and has recovered when it is back within this (mm).
DETACH_END_MM = 0.5
#: Decimation of the series kept for the figures (every n-th control tick).
FIGURE_EVERY = 10
#: Thesis 6.2 results, to print beside the simulator's.
THESIS = {
    "max_rel_xy_mm": 3.0,          # "the maximum relative distance are all around 3 mm"
    "ripple_c_6mm_s_mm": 5.0,      # config C, 6 mm/s: "around 5 mm"
    "recovery_c_s": 5.0,           # "after around 5 seconds, it could go back"
}


@dataclass(frozen=True)
class PatientVariation:
    """A randomised patient/phantom for populations (all assumptions, see :func:`variation`).

    ``yaw_deg``: the platform's square turned about the base z axis (a platform not set up
    square to the robot); ``x_distortion_mm``: the thesis's platform distortion ("around 3 mm
    on the X-axis when the platform was moving along the Z-axis"), a half-sine bulge in x
    over each vertical side; ``working_length_mm``, ``tilt_deg``: the phantom's canal.
    """

    yaw_deg: float = 0.0
    x_distortion_mm: float = 0.0
    working_length_mm: float = 16.0
    tilt_deg: float = 0.0


def variation(seed: int) -> PatientVariation:
    """The seeded random patient of population member ``seed``.

    assumption: yaw uniform in +-20 deg, x distortion uniform 0..3 mm (the thesis saw about
    3 mm), working length uniform 14..18 mm, canal tilt uniform +-8 deg.
    """
    rng = np.random.default_rng([seed, 6_2])
    return PatientVariation(yaw_deg=float(rng.uniform(-20.0, 20.0)),
                            x_distortion_mm=float(rng.uniform(0.0, 3.0)),
                            working_length_mm=float(rng.uniform(14.0, 18.0)),
                            tilt_deg=float(rng.uniform(-8.0, 8.0)))


class PlatformSquare:
    """The thesis's square (:class:`~dentibot.sim.patient.StewartSquare`) turned by ``yaw_deg``
    about base z, with an x bulge of ``x_distortion_mm`` (half sine over the z travel)."""

    def __init__(self, square: StewartSquare, yaw_deg: float = 0.0,
                 x_distortion_mm: float = 0.0) -> None:
        self.square = square
        self._c, self._s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        self.distortion = x_distortion_mm

    def offset_mm(self, t: float) -> tuple[float, float, float]:
        x, y, z = self.square.offset_mm(t)
        if self.distortion:
            x += self.distortion * math.sin(math.pi * min(max(z / SIDE_MM, 0.0), 1.0))
        return (self._c * x - self._s * y, self._s * x + self._c * y, z)


@dataclass(frozen=True)
class AlignmentSpec:
    """One run of experiment 1."""

    config: str = "A"
    seed: int = 1
    insertion_s: float = 10.0
    tail_s: float = 10.0
    speeds_mm_s: tuple[float, ...] = SPEEDS_MM_S
    pause_s: float = PAUSE_S
    patient: PatientVariation | None = None
    keep_series: bool = True
    tracking: str = "force"

    def __post_init__(self) -> None:
        if self.config not in CONFIGS:
            raise ValueError(f"config {self.config!r}: one of {', '.join(CONFIGS)}")
        if self.tracking not in TRACKING:
            raise ValueError(f"tracking {self.tracking!r}: one of {', '.join(TRACKING)}")

    def square(self) -> StewartSquare:
        return StewartSquare(self.speeds_mm_s, self.pause_s, start_s=self.insertion_s)

    @property
    def duration_s(self) -> float:
        return self.insertion_s + self.square().duration_s + self.tail_s


@dataclass
class Detachment:
    """One detachment along the insertion axis (s, mm); ``t_end``/``recovery_s`` None when
    the tip had not come back by the end of the run."""

    t_start: float
    t_peak: float
    peak_mm: float
    t_end: float | None

    @property
    def recovery_s(self) -> float | None:
        return None if self.t_end is None else self.t_end - self.t_peak

    def to_dict(self) -> dict:
        return {"t_start_s": self.t_start, "t_peak_s": self.t_peak, "peak_mm": self.peak_mm,
                "t_end_s": self.t_end, "recovery_s": self.recovery_s}


@dataclass
class SpeedStats:
    """The window of one square speed (its square and the pause or tail after it)."""

    speed_mm_s: float
    t0: float
    t1: float
    max_rel_mm: dict[str, float]
    rms_rel_mm: dict[str, float]
    max_out_mm: float
    detachments: list[Detachment]
    expected_ripple_mm: float
    max_lateral_mm: float = float("nan")

    def to_dict(self) -> dict:
        return {"speed_mm_s": self.speed_mm_s, "t0_s": self.t0, "t1_s": self.t1,
                "max_rel_mm": self.max_rel_mm, "rms_rel_mm": self.rms_rel_mm,
                "max_out_mm": self.max_out_mm, "max_lateral_mm": self.max_lateral_mm,
                "expected_ripple_mm": self.expected_ripple_mm,
                "detachments": [d.to_dict() for d in self.detachments]}


@dataclass
class AlignmentRun:
    """The result of one run (``series``: decimated arrays for the figures, or None)."""

    spec: AlignmentSpec
    status: str
    reason: str
    max_rel_mm: dict[str, float]
    rms_rel_mm: dict[str, float]
    max_out_mm: float
    speeds: list[SpeedStats]
    detachments: list[Detachment]
    peak_force_n: float
    seated_depth_mm: float
    wall_s: float
    series: dict[str, np.ndarray] | None = field(default=None, repr=False)
    max_lateral_mm: float = float("nan")

    def to_dict(self) -> dict:
        return {"config": self.spec.config, "seed": self.spec.seed, "status": self.status,
                "tracking": self.spec.tracking,
                "reason": self.reason, "max_rel_mm": self.max_rel_mm,
                "rms_rel_mm": self.rms_rel_mm, "max_out_mm": self.max_out_mm,
                "max_lateral_mm": self.max_lateral_mm,
                "peak_force_n": self.peak_force_n, "seated_depth_mm": self.seated_depth_mm,
                "patient": None if self.spec.patient is None
                else dataclasses.asdict(self.spec.patient),
                "speeds": [s.to_dict() for s in self.speeds],
                "detachments": [d.to_dict() for d in self.detachments],
                "wall_s": self.wall_s}


# ---------------------------------------------------------------------------- model answers
def chase_speed_mm_s(config: str) -> float:
    """Fastest the file follows a receding canal under its largest insertion force:
    ``k fz_max / b3`` (mm/s; eq 4.35, Table 6.4)."""
    c = EXPERIMENT_1[config]
    fz_max = c.fz_n if c.fz_n is not None else c.fz_bounds_n[1]
    return c.params.k * fz_max / c.params.b[2]


def expected_ripple_mm(config: str, speed_mm_s: float, side_mm: float = SIDE_MM) -> float:
    """Lag (mm) of the tip behind a canal receding at ``speed_mm_s`` over ``side_mm`` when
    the file can follow at most at :func:`chase_speed_mm_s`: ``L (1 - v_c / v)``, >= 0."""
    vc = chase_speed_mm_s(config)
    return max(0.0, side_mm * (1.0 - vc / speed_mm_s))


# ---------------------------------------------------------------------------- measures
def relative_distance(tip: np.ndarray, root: np.ndarray, i0: int) -> np.ndarray:
    """(tip - root) minus its value at sample ``i0`` (n x 3, mm)."""
    d = np.asarray(tip, float) - np.asarray(root, float)
    return d - d[i0]


def detachments(t: np.ndarray, out_mm: np.ndarray, start_mm: float = DETACH_START_MM,
                end_mm: float = DETACH_END_MM) -> list[Detachment]:
    """Episodes where ``out_mm`` rises above ``start_mm``, each until it is back below
    ``end_mm`` (hysteresis), with the peak inside."""
    events: list[Detachment] = []
    t = np.asarray(t, float)
    out = np.asarray(out_mm, float)
    i, n = 0, len(out)
    while i < n:
        above = np.flatnonzero(out[i:] > start_mm)
        if not len(above):
            break
        s = i + int(above[0])
        back = np.flatnonzero(out[s:] < end_mm)
        e = s + int(back[0]) if len(back) else None
        seg = out[s:e] if e is not None else out[s:]
        k = s + int(np.argmax(seg))
        events.append(Detachment(float(t[s]), float(t[k]), float(out[k]),
                                 None if e is None else float(t[e])))
        if e is None:
            break
        i = e
    return events


def _axes(v: np.ndarray) -> dict[str, float]:
    return {a: float(v[j]) for j, a in enumerate("xyz")}


_NAN3 = np.full(3, np.nan)


def _window(t, rel, out, lo, hi):
    """(max |rel|, RMS rel, max out) over lo <= t < hi; NaN when the run has no sample there
    (it ended early: a fault)."""
    m = (t >= lo) & (t < hi)
    if not m.any():
        return _axes(_NAN3), _axes(_NAN3), float("nan")
    r = rel[m]
    return (_axes(np.abs(r).max(axis=0)), _axes(np.sqrt((r ** 2).mean(axis=0))),
            float(out[m].max()))


def _max_in(t, x, lo, hi) -> float:
    m = (t >= lo) & (t < hi)
    return float(x[m].max()) if m.any() else float("nan")


def lateral_distance(rel: np.ndarray, axis_in) -> np.ndarray:
    """The part of the relative distance ``rel`` (n x 3, mm) across the unit ``axis_in``:
    ``|rel - (rel . a) a|`` (mm)."""
    a = np.asarray(axis_in, float)
    return np.linalg.norm(rel - np.outer(rel @ a, a), axis=1)


def square_starts(square: StewartSquare) -> list[float]:
    """Start time (s, world time) of each square of the profile."""
    per = len(SQUARE_MM) - 1
    return [square.start_s + square.segments[k][0] for k in range(0, len(square.segments), per)]


def analyse(spec: AlignmentSpec, t, tip, root, axis_in, status="ok", reason="",
            peak_force_n=float("nan"), seated_depth_mm=float("nan"), wall_s=0.0,
            series=None) -> AlignmentRun:
    """The measures of one run from its full-rate arrays (t, tip, root: world time s and
    base-frame positions mm; ``axis_in``: unit file axis into the tooth at the square's
    start)."""
    t = np.asarray(t, float)
    sq = spec.square()
    starts = square_starts(sq)
    i0 = int(np.searchsorted(t, starts[0]))
    if i0 >= len(t):                        # ended (fault) before the square started
        return AlignmentRun(spec, status, reason or "ended before the square", _axes(_NAN3),
                            _axes(_NAN3), float("nan"), [], [], peak_force_n,
                            seated_depth_mm, wall_s, series)
    rel = relative_distance(tip, root, i0)
    out = -(rel @ np.asarray(axis_in, float))
    lat = lateral_distance(rel, axis_in)
    end = float(t[-1]) + 1e-9
    mx, rms, mo = _window(t, rel, out, starts[0], end)
    speeds = []
    bounds = [*starts[1:], end]
    for k, v in enumerate(spec.speeds_mm_s):
        lo, hi = starts[k], bounds[k]
        w_mx, w_rms, w_mo = _window(t, rel, out, lo, hi)
        m = (t >= lo) & (t < hi)
        speeds.append(SpeedStats(v, lo, hi, w_mx, w_rms, w_mo, detachments(t[m], out[m]),
                                 expected_ripple_mm(spec.config, v),
                                 _max_in(t, lat, lo, hi)))
    m = t >= starts[0]
    return AlignmentRun(spec, status, reason, mx, rms, mo, speeds, detachments(t[m], out[m]),
                        peak_force_n, seated_depth_mm, wall_s, series,
                        _max_in(t, lat, starts[0], end))


# ---------------------------------------------------------------------------- the run
def alignment_protocol(spec: AlignmentSpec) -> Protocol:
    """The protocol of one run: protocols/experiment1-config-<X>.yaml (the thesis's world)
    with the run's seed, phantom and duration (the square itself is set on the world, see
    :func:`run_alignment`); with hybrid ``tracking``, the patient tracker on and hybrid
    control."""
    pv = spec.patient or PatientVariation()
    patient = {"motion": "square"}
    if spec.tracking == "hybrid":
        patient |= {"tracker": True, "tracking": "hybrid"}
    return Protocol.model_validate({
        "name": f"experiment1-{spec.config}", "seed": spec.seed, "world": "thesis",
        "phantom": {"working_length_mm": pv.working_length_mm, "tilt_deg": pv.tilt_deg,
                    "orifice_gap_mm": 2.0, "preshaped": True},
        "patient": patient,
        "recording": {"enabled": False},
        "steps": [{"align": {"duration_s": spec.duration_s, "config": spec.config}}],
    })


def run_alignment(spec: AlignmentSpec) -> AlignmentRun:
    """Run one configuration (blocking; lock-step time)."""
    protocol = alignment_protocol(spec)
    square = spec.square()
    pv = spec.patient
    motion = square if pv is None else PlatformSquare(square, pv.yaw_deg, pv.x_distortion_mm)
    t_square = square.start_s
    cols: dict[str, list] = {k: [] for k in ("t", "tip", "root", "euler", "f_h", "depth")}
    axis_at_start: list = []
    peak = [0.0]

    def prepare(runner) -> None:
        runner.world.motion = motion          # the square starts after the insertion

    def tap(row: dict, runner) -> None:
        t = runner.world.t                    # the world time the row's truth is from
        pose = row["tool_pose"]
        cols["t"].append(t)
        cols["tip"].append(pose[:3])
        cols["root"].append(row["phantom_pose"][:3])
        cols["euler"].append(pose[3:])
        f = row["wrench_h"]
        cols["f_h"].append(f[:3])
        cols["depth"].append(row["true_depth_mm"])
        fn = math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
        if t >= t_square and fn > peak[0]:
            peak[0] = fn
        if not axis_at_start and t >= t_square:
            axis_at_start.append(runner.world.axis_0)

    wall = time.perf_counter()
    result, runner = run_protocol(protocol, tap=tap, prepare=prepare)
    wall = time.perf_counter() - wall
    t = np.asarray(cols["t"])
    tip, root = np.asarray(cols["tip"]), np.asarray(cols["root"])
    depth = np.asarray(cols["depth"])
    i0 = int(np.searchsorted(t, t_square))
    series = None
    if spec.keep_series:
        sl = slice(None, None, FIGURE_EVERY)
        R = Rotation.from_euler("XYZ", np.asarray(cols["euler"])[sl], degrees=True).as_matrix()
        series = {"t": t[sl], "tip": tip[sl], "root": root[sl], "depth": depth[sl],
                  "force_0": np.einsum("nij,nj->ni", R, np.asarray(cols["f_h"])[sl])}
    axis = axis_at_start[0] if axis_at_start else runner.world.axis_0
    s = result.summary
    return analyse(spec, t, tip, root, axis, status=s.status, reason=s.reason,
                   peak_force_n=peak[0], seated_depth_mm=float(depth[min(i0, len(depth) - 1)]),
                   wall_s=wall, series=series)


def population_summary(runs: list[AlignmentRun]) -> dict:
    """Median and worst case (largest) over the runs of one configuration (the runs that
    ended before the square count in ``not_ok`` only)."""
    out: dict = {"n": len(runs), "not_ok": sum(r.status != "ok" for r in runs)}
    runs = [r for r in runs if r.speeds]
    if not runs:
        return out
    out["max_rel_mm"] = {a: distribution(r.max_rel_mm[a] for r in runs) for a in "xyz"}
    out["rms_rel_mm"] = {a: distribution(r.rms_rel_mm[a] for r in runs) for a in "xyz"}
    out["max_out_mm"] = distribution(r.max_out_mm for r in runs)
    out["speeds"] = []
    for k, v in enumerate(runs[0].spec.speeds_mm_s):
        rec = [d.recovery_s for r in runs for d in r.speeds[k].detachments]
        out["speeds"].append({
            "speed_mm_s": v,
            "max_out_mm": distribution(r.speeds[k].max_out_mm for r in runs),
            "detachments": distribution(len(r.speeds[k].detachments) for r in runs),
            "recovery_s": distribution(rec),
            "not_recovered": sum(d.t_end is None for r in runs for d in r.speeds[k].detachments),
        })
    return out


def checks(runs: dict[str, list[AlignmentRun]]) -> list[Check]:
    """The thesis's claims for experiment 1 on these runs (worst case over a population; a run
    that did not end ok shows no claim)."""
    out = []
    bad = [f"{r.spec.config}/{r.spec.seed}: {r.status} {r.reason}".strip()
           for rs in runs.values() for r in rs if r.status != "ok" or not r.speeds]
    note = f"; not ok: {'; '.join(bad)}" if bad else ""
    if runs:
        def worst(rs, a):
            vals = [r.max_rel_mm[a] for r in rs if math.isfinite(r.max_rel_mm[a])]
            return max(vals, default=float("nan"))

        lim = THESIS["max_rel_xy_mm"]
        ok = not bad and all(worst(rs, a) <= lim for rs in runs.values() for a in "xy")
        per = ", ".join(f"{c} {worst(rs, 'x'):.2f}/{worst(rs, 'y'):.2f}"
                        for c, rs in sorted(runs.items()))
        out.append(Check(f"X and Y max relative distance within {lim:g} mm "
                         f"({', '.join(sorted(runs))})", ok,
                         f"max |x|/|y| (mm): {per}{note}"))
    rs = [r for r in runs.get("C", []) if r.speeds]
    if "C" in runs:
        grows = bool(rs) and all(
            all(b.max_out_mm >= a.max_out_mm for a, b in zip(r.speeds, r.speeds[1:]))
            and r.speeds[-1].max_out_mm > DETACH_START_MM for r in rs)
        speeds = [s.speed_mm_s for s in rs[0].speeds] if rs else []
        med = [float(np.median([r.speeds[k].max_out_mm for r in rs]))
               for k in range(len(speeds))]
        out.append(Check("config C's insertion-axis ripple grows with platform speed",
                         grows and not bad, "peak out of the canal (mm) at "
                         + ", ".join(f"{v:g}: {m:.2f}" for v, m in zip(speeds, med))
                         + f" mm/s (thesis: about {THESIS['ripple_c_6mm_s_mm']:g} mm at 6 mm/s;"
                         " admittance law: " + ", ".join(
                             f"{expected_ripple_mm('C', v):.2f}" for v in speeds) + ")"))
        events = [d for r in rs for d in r.detachments]
        rec = [d.recovery_s for d in events if d.recovery_s is not None]
        ok = bool(events) and all(d.t_end is not None for d in events) and not bad
        out.append(Check("config C recovers from every detachment", ok,
                         f"{len(events)} detachments, {len(events) - len(rec)} not recovered; "
                         f"recovery {min(rec, default=float('nan')):.2f}.."
                         f"{max(rec, default=float('nan')):.2f} s after the peak "
                         f"(thesis: about {THESIS['recovery_c_s']:g} s)"))
    return out


def hybrid_checks(runs: dict[str, list[AlignmentRun]]) -> list[Check]:
    """Hybrid control's targets on experiment 1's path (:data:`HYBRID_TARGETS`), at every
    speed of every run: the tip within 0.5 mm of its seated position across the canal axis
    and along it, and no detachment (a run that did not end ok shows no target)."""
    rs = [r for v in runs.values() for r in v]
    bad = [f"{r.spec.config}/{r.spec.seed}: {r.status} {r.reason}".strip()
           for r in rs if r.status != "ok" or not r.speeds]
    note = f"; not ok: {'; '.join(bad)}" if bad else ""
    lat_lim, z_lim = HYBRID_TARGETS["lateral_mm"], HYBRID_TARGETS["z_ripple_mm"]

    def worst(get) -> float:
        vals = [get(s) for r in rs for s in r.speeds if math.isfinite(get(s))]
        return max(vals, default=float("nan"))

    lat = worst(lambda s: s.max_lateral_mm)
    z = worst(lambda s: s.max_rel_mm["z"])
    n_det = sum(len(s.detachments) for r in rs for s in r.speeds)
    speeds = ", ".join(f"{v:g}" for v in (rs[0].spec.speeds_mm_s if rs else ()))
    return [
        Check(f"hybrid control: the tip within {lat_lim:g} mm of its seated position across "
              f"the canal at every speed ({speeds} mm/s)", not bad and lat <= lat_lim,
              f"worst {lat:.3f} mm{note}"),
        Check(f"hybrid control: Z ripple within {z_lim:g} mm and no detachment at every "
              "speed", not bad and z <= z_lim and n_det == 0,
              f"worst |z| {z:.3f} mm, {n_det} detachments{note}"),
    ]


# ---------------------------------------------------------------------------- the bench
#: Experiment 1 as the thesis's bench ran it (the thesis lab's recordings): A, B, C with
#: k = 500 and C_K250 (k = 250, fz 0..1 N: the same chase speed k fz_max / b).
BENCH_CONFIGS = ("A", "B", "C", "C_K250")
#: The bench's figures the bench-fitted world is compared on (the names of the recordings'
#: per-trial table; see :func:`bench_figures` for the definitions). Per square N = 1..4:
BENCH_SQUARE_FIGURES = ("z_out_max_mm", "tip_out_max_mm", "n_detach", "recovery_s",
                        "Fhz_zup_mean_N", "Fhz_zdown_mean_N", "v_eff_mm_s")
BENCH_FIGURES = (
    "rel_x_maxabs_mm", "rel_x_rms_mm", "rel_y_maxabs_mm", "rel_y_rms_mm", "rel_z_maxabs_mm",
    "rel_z_rms_mm", "tiprel_x_maxabs_mm", "tiprel_x_rms_mm", "tiprel_y_maxabs_mm",
    "tiprel_y_rms_mm", "tiprel_z_maxabs_mm", "tiprel_z_rms_mm",
    *(f"sq{k}_{n}" for k in (1, 2, 3, 4) for n in BENCH_SQUARE_FIGURES),
    "Fh_z_mean_N", "Fh_z_std_N", "Fh_z_min_N", "Fh_z_max_N", "Fh_lat_median_N",
    "Fh_lat_p99_N", "Fz_chatter_rms_N", "Fz_des_min_N", "Fz_des_max_N", "Fz_des_frac_at_max",
    "torque_median_mNm", "torque_p99_mNm", "torque_max_mNm", "vcmd_per_F_mm_s_per_N",
    "realised_gain_vmeas_over_vcmd", "realised_mm_s_per_N", "fit_delay_ms_z", "fit_tau_ms_z")
#: The bench's admittance (Table 6.4 as run): k, b1..b6 (m = b / 1000), file rotation.
BENCH_SETUP = {"A": (500.0, 80.0, False), "B": (500.0, math.inf, True),
               "C": (500.0, math.inf, True), "C_K250": (250.0, math.inf, True)}
#: Chatter band (Hz) of ``Fz_chatter_rms_N``.
CHATTER_BAND_HZ = (1.5, 6.0)


@dataclass(frozen=True)
class BenchSpec:
    """One run of experiment 1 on the bench-fitted world (:mod:`dentibot.sim.bench_physics`):
    ``settle_s`` seated at rest before the first square, ``tail_s`` after the last."""

    config: str = "A"
    seed: int = 1
    settle_s: float = 4.0
    tail_s: float = 6.0

    def __post_init__(self) -> None:
        if self.config not in BENCH_CONFIGS:
            raise ValueError(f"config {self.config!r}: one of {', '.join(BENCH_CONFIGS)}")


def run_bench(spec: BenchSpec, physics=None) -> dict:
    """Run one configuration on the bench-fitted world in lock-step (the bench's own loop,
    :func:`dentibot.app.bench_run.bench_record`) and return its figures
    (:func:`bench_figures`); ``physics``: another
    :class:`~dentibot.sim.bench_physics.BenchPhysics` than the fitted one (a fit weighing a
    value)."""
    from dentibot.app.bench_run import bench_record

    k, b6, rotate = BENCH_SETUP[spec.config]
    # b4 = b5 = 80 about the tip, as the bench ran: the canal's lateral loads act along the
    # file (a couple about the tip), which bounds the tilt (0.6-9 deg from the vertical over
    # a run; the bench: 4-8 deg).
    more = {} if physics is None else {"physics": physics}
    r = bench_record(spec.config, k, b6, rotate, seed=spec.seed, settle_s=spec.settle_s,
                     tail_s=spec.tail_s, **more)
    return bench_figures(r.rec, r.starts, r.ends, r.stewart, r.led_behind_tip_mm,
                         k / 80.0, r.dt)


def _fopdt_fit(t, vcmd, vmeas, dt):
    """Gain, dead time (ms) and lag (ms) of ``vmeas`` against ``vcmd`` (first order plus
    dead time, least squares on a grid at 1 ms)."""
    tt = np.arange(t[0], t[-1], 0.001)
    u = np.interp(tt, t, vcmd)
    best = (math.inf, 1.0, 0.0, 0.0)
    for tau in (1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 10.0, 12.0, 15.0):
        a = 1.0 - math.exp(-1.0 / tau)
        y = np.empty_like(u)
        acc = 0.0
        for i, x in enumerate(u):
            acc += (x - acc) * a
            y[i] = acc
        for d in range(0, 41):
            yd = np.interp(t - d / 1000.0, tt, y)
            g = float(np.dot(yd, vmeas) / max(np.dot(yd, yd), 1e-12))
            r = float(np.sum((vmeas - g * yd) ** 2))
            if r < best[0]:
                best = (r, g, float(d), tau)
    return best[1], best[2], best[3]


def bench_figures(rec: dict, starts, ends, stewart, led_mm: float, vcmd_per_f: float,
                  dt: float) -> dict[str, float | None]:
    """The bench's per-trial figures from a run's 100 Hz record (definitions of the thesis
    lab's recordings, experiment 1): positions in the Stewart frame (rows of ``stewart``:
    its x, y, z in base axes); ``rel_*`` the handpiece LED (``led_mm`` behind the tip)
    minus the platform centre, ``tiprel_*`` the file tip instead, both referenced to their
    mean over the 2 s before the first square; statistics from the first square's start to
    1 s after the last square's end. Per square (to the next square's start; the last to
    the end of the record): Z out (``z`` of rel, + away from the root), detachments (start
    above 1.0 mm, end below 0.5 mm, recovery from the peak), mean contact Fz in {H} while
    the platform rises / descends faster than 1 mm/s, the measured speed (path / time).
    ``Fz_chatter_rms_N``: RMS of Fz in {H} in the 1.5-6 Hz band. Command -> motion:
    least squares of the tip's z velocity on the commanded z velocity."""
    t = rec["t"]
    S = np.asarray(stewart)
    tip = rec["tip"] @ S.T
    root = rec["root"] @ S.T
    led = (rec["tip"] - led_mm * rec["axis"]) @ S.T
    out: dict[str, float | None] = {}
    ref = (t >= starts[0] - 2.0) & (t < starts[0])
    win = (t >= starts[0]) & (t <= ends[-1] + 1.0)
    rel = led - root
    rel = rel - rel[ref].mean(0)
    trel = tip - root
    trel = trel - trel[ref].mean(0)
    for name, r in (("rel", rel), ("tiprel", trel)):
        for j, a in enumerate("xyz"):
            x = r[win, j]
            out[f"{name}_{a}_maxabs_mm"] = float(np.abs(x).max())
            out[f"{name}_{a}_rms_mm"] = float(np.sqrt(np.mean(x ** 2)))
    fh = rec["fh"]
    vz_root = np.gradient(root[:, 2], t)
    bounds = [*starts[1:], t[-1] + 1e-9]
    for k in range(4):
        m = (t >= starts[k]) & (t < bounds[k])
        zo = rel[m, 2]
        ev = detachments(t[m], zo)
        out[f"sq{k + 1}_z_out_max_mm"] = float(zo.max())
        out[f"sq{k + 1}_tip_out_max_mm"] = float(trel[m, 2].max())
        out[f"sq{k + 1}_n_detach"] = float(len(ev))
        rec_s = [d.recovery_s for d in ev if d.recovery_s is not None]
        out[f"sq{k + 1}_recovery_s"] = float(np.mean(rec_s)) if rec_s else None
        sq = (t >= starts[k]) & (t < ends[k])
        up, down = sq & (vz_root > 1.0), sq & (vz_root < -1.0)
        out[f"sq{k + 1}_Fhz_zup_mean_N"] = float(fh[up, 2].mean()) if up.any() else None
        out[f"sq{k + 1}_Fhz_zdown_mean_N"] = float(fh[down, 2].mean()) if down.any() else None
        path = float(np.sum(np.linalg.norm(np.diff(root[sq], axis=0), axis=1)))
        out[f"sq{k + 1}_v_eff_mm_s"] = path / (ends[k] - starts[k])
    fz = fh[win, 2]
    lat = np.hypot(fh[win, 0], fh[win, 1])
    out.update({"Fh_z_mean_N": float(fz.mean()), "Fh_z_std_N": float(fz.std()),
                "Fh_z_min_N": float(fz.min()), "Fh_z_max_N": float(fz.max()),
                "Fh_lat_median_N": float(np.median(lat)),
                "Fh_lat_p99_N": float(np.percentile(lat, 99))})
    spec = np.fft.rfft(fz - fz.mean())
    freq = np.fft.rfftfreq(len(fz), dt)
    band = (freq >= CHATTER_BAND_HZ[0]) & (freq <= CHATTER_BAND_HZ[1])
    out["Fz_chatter_rms_N"] = float(np.sqrt(2.0 * np.sum(np.abs(spec[band]) ** 2))
                                    / len(fz))
    fd = rec["fz_des"][win]
    out.update({"Fz_des_min_N": float(fd.min()), "Fz_des_max_N": float(fd.max()),
                "Fz_des_frac_at_max": float(np.mean(fd >= fd.max() - 1e-9))})
    tq = rec["torque"][win]
    out.update({"torque_median_mNm": float(np.median(tq)),
                "torque_p99_mNm": float(np.percentile(tq, 99)),
                "torque_max_mNm": float(tq.max())})
    vc = (rec["vcmd"] @ S.T)[:, 2]
    vm = np.gradient(tip[:, 2], t)
    g, d, tau = _fopdt_fit(t[win], vc[win], vm[win], dt)
    out.update({"vcmd_per_F_mm_s_per_N": vcmd_per_f, "realised_gain_vmeas_over_vcmd": g,
                "realised_mm_s_per_N": g * vcmd_per_f, "fit_delay_ms_z": d,
                "fit_tau_ms_z": tau})
    return out


#: The recordings' group of each bench configuration.
BENCH_GROUPS = {"A": "A_K500_fz1.0", "B": "B_K500_fz1.0", "C": "C_K500_fz0.5",
                "C_K250": "C_K250_fz1.0"}
#: Widening of the real range: 20 % of the median, at least this much by unit suffix.
WIDEN_MIN = {"_mm": 0.3, "_N": 0.2, "_ms_z": 3.0, "_mNm": 2.0}


def widen_min(name: str) -> float:
    return next((v for k, v in WIDEN_MIN.items() if name.endswith(k)), 0.0)


def compare_bench(sim: dict, real_rows: list[dict]) -> list[dict]:
    """Figure by figure: the real range (min..max over ``real_rows``, the recordings' rows
    of the configuration's group), widened by 20 % of the median (at least 0.3 mm, 0.2 N,
    3 ms, 2 mNm), the simulated value and whether it is inside. A figure applies when the
    real trials give it (a recovery time only where the real squares detached) and the
    simulation gives it."""
    out = []
    for name in BENCH_FIGURES:
        vals = [float(r[name]) for r in real_rows
                if r.get(name) not in (None, "") and math.isfinite(float(r[name]))]
        if not vals:
            continue
        lo, hi, med = min(vals), max(vals), float(np.median(vals))
        pad = max(0.2 * abs(med), widen_min(name))
        v = sim.get(name)
        inside = v is not None and lo - pad <= v <= hi + pad
        out.append({"figure": name, "real_min": lo, "real_max": hi, "widened": pad,
                    "sim": v, "inside": bool(inside)})
    return out
