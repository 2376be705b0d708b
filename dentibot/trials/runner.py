"""Run a trial: every procedure on the built-in simulator, in batches, each finished batch on
disk at once.

The seam is :func:`run_batch`: ``run_batch(procedures) -> pyarrow.Table``, one row per
procedure (:data:`SCHEMA`), in the order given, and a pure function of its input (procedure
``i`` gives the same row in a batch of one as in a batch of many, in any process). Today it
runs the procedures one after the other through the per-procedure runtime
(:class:`~dentibot.app.runner.ProtocolRunner` in lock-step time, no recording). A batched
(array) engine that steps many worlds at once can replace the loop behind the same signature:
planning, scheduling, storage, resumption and the report do not change.

Scheduling (:func:`run_trial`): the procedures of each arm are cut into batches of
``batch_size`` (:func:`plan`); the batches not on disk yet go to ``workers`` local processes
(the "spawn" start method: a clean interpreter per worker) or, with ``ray_address``, to a Ray
cluster as ``ray.remote`` tasks. As each batch finishes, this process writes it to
``OUT/batches/<arm>-<first index>.parquet`` (a temporary file renamed into place, so a batch
file is whole or absent). ``OUT/trial.json`` holds the trial's spec hash
(:meth:`~dentibot.trials.spec.TrialSpec.spec_hash`): a rerun with the same spec into the same
directory skips the batches already there (after Ctrl-C, a crash or a lost worker), a rerun
with another spec is refused. At the end the batches are concatenated, in plan order, into
``OUT/procedures.parquet``.

Each procedure is the protocol ``protocol_for`` builds: load calibration, 0.2 s of
self-alignment, then the arm's drilling rounds (as the pre-clinical experiment runs its
phantoms, :mod:`dentibot.experiments.preclinical`). The protocol states the file's rated
strength (the runtime's hard torque limit is the arm's share of it); the simulated file breaks
at its own, drawn strength. What the protocol schema cannot state (the canal's initial apical
diameter and taper, the file's actual strength, the sway's amplitude) is set on the world
before the run starts.

Outcomes per procedure (simulator truth unless said): status and reason of the run; reached the
working length (the runtime's first arrival) and when (s from the start of drilling);
completeness (eq 6.1) and shaping; fracture and its cause; the deepest tip depth, how far past
the working length (over-instrumentation: more than :data:`OVER_MM`) and for how long; peak
file torque; reversals (and those the hard torque limit forced); the motor stalled (s, at its
current limit), feeding without progress (s, the pre-clinical experiment's definition:
:func:`~dentibot.app.batch.stalled_seconds`) and faults; fatigue: the simulator's Miner sum, the
one under the file's own strain-life constants (:mod:`dentibot.trials.fatigue`), the bending
cycles and the peak bending strain.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from numba import njit

from dentibot.app.batch import run_all, run_protocol, stalled_seconds
from dentibot.app.runner import ProtocolRunner
from dentibot.app.simulated import true_depth_mm
from dentibot.errors import ConfigError
from dentibot.protocol.schema import LIMIT_SHARE_OF_STRENGTH, Protocol
from dentibot.trials.population import Subject, draw
from dentibot.trials.spec import ArmSpec, TrialSpec

#: Over-instrumentation: the true tip more than this past the working length (mm), as the
#: patient-jerk experiment counts time past it.
OVER_MM = 0.2
#: Depth samples for the stall measure: every this many control ticks.
TRACE_EVERY = 50
#: The drilling step's state while it feeds.
FEEDING = "treating.drilling.feeding"

#: One row per procedure.
SCHEMA = pa.schema([
    ("arm", pa.string()), ("arm_index", pa.int32()), ("index", pa.int32()),
    ("seed", pa.int64()), ("sim_seed", pa.int64()),
    # settings of the arm
    ("strategy", pa.string()), ("tau_d_mnm", pa.float64()), ("fz_min_n", pa.float64()),
    ("fz_max_n", pa.float64()), ("rpm", pa.float64()), ("torque_limit_mnm", pa.float64()),
    ("tracking", pa.string()), ("drill_s", pa.float64()),
    # anatomy
    ("working_length_mm", pa.float64()), ("curvature", pa.string()),
    ("curve_angle_deg", pa.float64()), ("curve_radius_mm", pa.float64()),
    ("curve_start_mm", pa.float64()), ("tilt_deg", pa.float64()),
    ("apical_diameter_mm", pa.float64()), ("canal_taper", pa.float64()),
    ("material", pa.string()),
    # file and patient
    ("file_size", pa.int32()), ("file_taper", pa.float64()), ("file_length_mm", pa.float64()),
    ("rated_strength_mnm", pa.float64()), ("torsional_strength_mnm", pa.float64()),
    ("fatigue_c", pa.float64()), ("fatigue_b", pa.float64()),
    ("motion", pa.string()), ("sway_mm", pa.float64()),
    # outcome
    ("status", pa.string()), ("reason", pa.string()),
    ("reached_wl", pa.bool_()), ("t_wl_s", pa.float64()), ("passes", pa.int32()),
    ("completeness", pa.float64()), ("shaping", pa.float64()),
    ("fracture", pa.bool_()), ("fracture_cause", pa.string()),
    ("depth_max_mm", pa.float64()), ("overshoot_mm", pa.float64()),
    ("over_instrumented", pa.bool_()), ("past_wl_s", pa.float64()),
    ("peak_torque_mnm", pa.float64()), ("reversals", pa.int32()),
    ("limit_reversals", pa.int32()), ("motor_stall_s", pa.float64()),
    ("feed_stall_s", pa.float64()), ("faults", pa.int32()),
    ("fatigue_damage_sim", pa.float64()), ("fatigue_damage", pa.float64()),
    ("bending_cycles", pa.float64()), ("peak_strain", pa.float64()),
    ("simulated_s", pa.float64()), ("wall_s", pa.float64()),
])


@dataclass(frozen=True)
class Procedure:
    """One procedure: an arm's settings on a subject (picklable: it crosses processes)."""

    arm: ArmSpec
    arm_index: int
    subject: Subject
    seed: int
    rounds_s: tuple[float, ...]

    @property
    def index(self) -> int:
        return self.subject.index


@dataclass(frozen=True)
class Batch:
    arm_index: int
    arm: str
    start: int
    procedures: tuple[Procedure, ...]

    @property
    def filename(self) -> str:
        return f"{self.arm_index:03d}-{self.arm}-{self.start:06d}.parquet"


def procedures_of(spec: TrialSpec, arm_index: int, indices: Sequence[int]) -> list[Procedure]:
    """Procedures ``indices`` of arm ``arm_index``."""
    table = spec.table()
    arm = spec.arms[arm_index]
    return [Procedure(arm, arm_index, draw(table, spec.seed, i), spec.seed,
                      tuple(spec.rounds_s)) for i in indices]


def plan(spec: TrialSpec) -> list[Batch]:
    """Every batch of the trial, arm by arm, ``batch_size`` procedures each."""
    out = []
    for a, arm in enumerate(spec.arms):
        for start in range(0, spec.n, spec.batch_size):
            idx = range(start, min(start + spec.batch_size, spec.n))
            out.append(Batch(a, arm.name, start, tuple(procedures_of(spec, a, idx))))
    return out


# ---------------------------------------------------------------------------- one procedure
#: The world a trial's procedures run on (``Protocol.world``). The thesis's: on the
#: bench-fitted world, of 8 patients of a mixed population (head sway or still, curved and
#: tilted canals, 40 s), 2 more than on this one faulted under every arm, in the
#: patient-moved state's drift check (a force of 1.5-2.4 N not relieved as the arm followed
#: the patient 2 mm): the controller's answer to a moving patient in a dragging canal is not
#: yet what a trial of settings should measure (docs/sim-to-real.md).
TRIAL_WORLD = "thesis"


def protocol_for(proc: Procedure) -> Protocol:
    """The protocol procedure ``proc`` runs (on :data:`TRIAL_WORLD`)."""
    s, arm = proc.subject, proc.arm
    phantom: dict = {"working_length_mm": s.working_length_mm, "orifice_gap_mm": 2.0,
                     "tilt_deg": s.tilt_deg, "material": s.material}
    if s.curve_angle_deg > 0.0:
        phantom["curve"] = {"start_mm": s.curve_start_mm, "radius_mm": s.curve_radius_mm,
                            "angle_deg": s.curve_angle_deg}
    return Protocol.model_validate({
        "name": f"trial-{arm.name}-{s.index}", "seed": s.sim_seed, "world": TRIAL_WORLD,
        "file": {"size": s.file_size, "taper": s.file_taper,
                 "length_mm": int(s.file_length_mm),
                 "torsional_strength_mnm": s.rated_strength_mnm},
        "phantom": phantom,
        "patient": {"motion": s.motion, "tracker": arm.tracker, "tracking": arm.tracking},
        "limits": {"torque_limit_mnm": arm.torque_limit_share * s.rated_strength_mnm},
        "recording": {"enabled": False},
        "steps": [{"calibrate_load": {}}, {"align": {"duration_s": 0.2, "fz_n": 1.0}},
                  {"drill": arm.drill(list(proc.rounds_s))}],
    })


def _prepare(s: Subject) -> Callable[[ProtocolRunner], None]:
    """What the protocol cannot state, set on the world before the run."""

    def prepare(runner: ProtocolRunner) -> None:
        w = runner.world
        p = w.canal.p
        if (p.initial_apical_mm, p.initial_taper) != (s.apical_diameter_mm, s.canal_taper):
            params = dataclasses.replace(p, initial_apical_mm=s.apical_diameter_mm,
                                         initial_taper=s.canal_taper)
            w.canal = type(w.canal)(params)          # the world's own canal class
            w.config.canal = params
        if w.file.torsional_strength_mnm != s.torsional_strength_mnm:
            w.file = dataclasses.replace(w.file, torsional_strength_mnm=s.torsional_strength_mnm)
            w.config.file = w.file
        if s.motion == "head" and s.sway_mm != 1.0:
            # the world's sway from the same stream (World: SeedSequence(seed).spawn(3)[2]),
            # with this amplitude
            rng = np.random.default_rng(np.random.SeedSequence(s.sim_seed).spawn(3)[2])
            w.motion = type(w.motion)(rng, amplitude_mm=s.sway_mm)

    return prepare


#: The meter's state array: torque peak, deepest true depth, ticks past the working length,
#: stalled ticks, Miner damage, bending cycles, peak strain, the last file position and
#: whether there is one.
M_PEAK, M_DEPTH, M_PAST, M_STALL, M_DAMAGE, M_CYCLES, M_STRAIN, M_POS, M_HAS_POS = range(9)


@njit(cache=True)
def meter_ticks(st: np.ndarray, rows: np.ndarray, n: int, over_mm: float, c: float,
                inv_b: float) -> None:
    """Take ``n`` ticks' figures (``rows``: :data:`~dentibot.app.drill_kernels.OUT_FIELDS`,
    the file intact) into the meter's state ``st``: peaks, ticks past ``over_mm`` (the
    working length plus the over-instrumentation margin), stalls, and fatigue: each bent
    revolution counts ``(eps / c) ** (1 / b)`` (Miner's sum under the file's strain-life
    law)."""
    for i in range(n):
        tq, d, stalled, pos, eps = rows[i, 0], rows[i, 1], rows[i, 2], rows[i, 3], rows[i, 4]
        if tq > st[M_PEAK]:
            st[M_PEAK] = tq
        if d > st[M_DEPTH]:
            st[M_DEPTH] = d
        if d > over_mm:
            st[M_PAST] += 1.0
        if stalled != 0.0:
            st[M_STALL] += 1.0
        if st[M_HAS_POS] != 0.0 and eps > 0.0 and pos != st[M_POS]:
            rev = abs(pos - st[M_POS]) / 360.0
            st[M_CYCLES] += rev
            st[M_DAMAGE] += rev * (eps / c) ** inv_b
            if eps > st[M_STRAIN]:
                st[M_STRAIN] = eps
        st[M_POS] = pos
        st[M_HAS_POS] = 1.0


meter_ticks(np.zeros(9), np.zeros((1, 7)), 1, 1.0, 1.0, 1.0)   # compiled at import


class _Meter:
    """Called after every tick (``on_tick``, or ``ticks`` for many at once): peaks, stalls,
    time past the working length, and fatigue under the file's own strain-life constants
    (Miner: sum of |revolutions| / N_f(strain)); :func:`meter_ticks` counts."""

    def __init__(self, s: Subject) -> None:
        self.wl = s.working_length_mm
        self.inv_b = 1.0 / s.fatigue_b
        self.c = s.fatigue_c
        self.st = np.zeros(9)
        self.st[M_DEPTH] = -np.inf
        self._row = np.zeros((1, 6))
        self.t: list[float] = []
        self.depth: list[float] = []
        self.feeding: list[bool] = []

    peak = property(lambda self: float(self.st[M_PEAK]))
    depth_max = property(lambda self: float(self.st[M_DEPTH]))
    past_ticks = property(lambda self: int(self.st[M_PAST]))
    stall_ticks = property(lambda self: int(self.st[M_STALL]))
    damage = property(lambda self: float(self.st[M_DAMAGE]))
    cycles = property(lambda self: float(self.st[M_CYCLES]))
    peak_strain = property(lambda self: float(self.st[M_STRAIN]))

    def __call__(self, runner: ProtocolRunner) -> None:
        """After each tick (from the first estimate on, as a telemetry row would be)."""
        rt, w = runner.rt, runner.world
        if rt.last is None:
            return
        hp = w.handpiece
        tq = abs(hp.torque_mnm)
        if w.fractured is not None:       # the stub sinks unresisted: nothing to measure
            if tq > self.st[M_PEAK]:
                self.st[M_PEAK] = tq
            return
        row = self._row
        row[0] = (tq, true_depth_mm(w), hp.stalled, hp.pos_deg, w.interaction.max_strain, w.t)
        self.ticks(runner, row, 1, rt.ticks - 1, rt.state)

    def ticks(self, runner: ProtocolRunner, out: np.ndarray, n: int, k0: int,
              state: str) -> None:
        """``n`` ticks from tick ``k0`` in ``state`` (``out``: their figures, the file intact;
        many at once where they ran in one compiled call, :mod:`dentibot.app.drill_loop`)."""
        meter_ticks(self.st, out, n, self.wl + OVER_MM, self.c, self.inv_b)
        first = -k0 % TRACE_EVERY
        if first < n:
            sel = out[first:n:TRACE_EVERY]
            self.t.extend(sel[:, 5].tolist())
            self.depth.extend(sel[:, 1].tolist())
            self.feeding.extend([state == FEEDING] * len(sel))


def build_runner(proc: Procedure, tap: Callable[[dict, ProtocolRunner], None] | None = None
                 ) -> ProtocolRunner:
    """The procedure's runner, its world set up, not started; ``tap(row, runner)`` sees every
    telemetry row."""
    runner = ProtocolRunner(protocol_for(proc), no_record=True, live_summary=False,
                            limit_share=_limit_share(proc),
                            tap=None if tap is None else (lambda row: tap(row, runner)))
    _prepare(proc.subject)(runner)
    return runner


def _limit_share(proc: Procedure) -> float:
    return max(proc.arm.torque_limit_share, LIMIT_SHARE_OF_STRENGTH)


def run_procedure(proc: Procedure, compiled_ticks: bool = True) -> dict:
    """Run one procedure (blocking, lock-step time): its row of :data:`SCHEMA`. Its feeding,
    reversing and retracting ticks run compiled, many per call (``compiled_ticks=False``: tick
    by tick through the control task; the same row, wall time aside)."""
    s, arm = proc.subject, proc.arm
    meter = _Meter(s)
    wall = time.perf_counter()
    result, runner = run_protocol(protocol_for(proc), None, prepare=_prepare(s),
                                  limit_share=_limit_share(proc), on_tick=meter,
                                  compiled_ticks=compiled_ticks)
    wall = time.perf_counter() - wall
    w, rt = runner.world, runner.rt
    ts = rt.ts
    log = rt.events_log
    drill_tick = next((tick for tick, kind, detail in log
                       if kind == "command" and detail == "drill"), 0)
    # arrivals of the file, not of the stub after a fracture
    end = w.fractured.t / ts if w.fractured is not None else np.inf
    arrivals = [tick for tick, kind, _ in log
                if kind == "working_length_reached" and tick <= end]
    t_wl = (arrivals[0] - drill_tick) * ts if arrivals else None
    limit_rev = sum(1 for _, kind, detail in log
                    if kind == "reversal_needed" and detail.startswith("file torque"))
    depth_max = float(meter.depth_max) if np.isfinite(meter.depth_max) else float("nan")
    overshoot = max(0.0, depth_max - s.working_length_mm) if np.isfinite(depth_max) else 0.0
    until = None if not arrivals else arrivals[0] * ts
    summ = result.summary
    return {
        "arm": arm.name, "arm_index": proc.arm_index, "index": s.index, "seed": proc.seed,
        "sim_seed": s.sim_seed, "strategy": arm.strategy, "tau_d_mnm": arm.tau_d_mnm,
        "fz_min_n": arm.fz_min_n, "fz_max_n": arm.fz_max_n, "rpm": arm.rpm,
        "torque_limit_mnm": arm.torque_limit_share * s.rated_strength_mnm,
        "tracking": arm.tracking if arm.tracker else "force (no tracker)",
        "drill_s": float(sum(proc.rounds_s)),
        "working_length_mm": s.working_length_mm, "curvature": s.curvature,
        "curve_angle_deg": s.curve_angle_deg, "curve_radius_mm": s.curve_radius_mm,
        "curve_start_mm": s.curve_start_mm, "tilt_deg": s.tilt_deg,
        "apical_diameter_mm": s.apical_diameter_mm, "canal_taper": s.canal_taper,
        "material": s.material, "file_size": s.file_size, "file_taper": s.file_taper,
        "file_length_mm": s.file_length_mm, "rated_strength_mnm": s.rated_strength_mnm,
        "torsional_strength_mnm": s.torsional_strength_mnm, "fatigue_c": s.fatigue_c,
        "fatigue_b": s.fatigue_b, "motion": s.motion, "sway_mm": s.sway_mm,
        "status": summ.status, "reason": summ.reason or "",
        "reached_wl": bool(arrivals), "t_wl_s": t_wl, "passes": len(arrivals),
        "completeness": float(w.completeness()), "shaping": float(w.canal.shaping()),
        "fracture": w.fractured is not None,
        "fracture_cause": None if w.fractured is None else w.fractured.cause,
        "depth_max_mm": depth_max, "overshoot_mm": overshoot,
        "over_instrumented": overshoot > OVER_MM, "past_wl_s": meter.past_ticks * ts,
        "peak_torque_mnm": float(meter.peak), "reversals": int(rt.ctx.reversals),
        "limit_reversals": limit_rev, "motor_stall_s": meter.stall_ticks * ts,
        "feed_stall_s": stalled_seconds(meter.t, meter.depth, meter.feeding, until),
        "faults": sum(1 for _, kind, _ in log if kind == "fault"),
        "fatigue_damage_sim": float(w.fatigue_damage), "fatigue_damage": meter.damage,
        "bending_cycles": meter.cycles, "peak_strain": meter.peak_strain,
        "simulated_s": float(w.t), "wall_s": wall,
    }


# ---------------------------------------------------------------------------- the seam
def run_batch(procedures: Sequence[Procedure]) -> pa.Table:
    """The rows of ``procedures``, in their order (see the module's docstring: the seam a
    batched engine replaces)."""
    rows = [run_procedure(p) for p in procedures]
    return pa.Table.from_pylist(rows, schema=SCHEMA)


# ---------------------------------------------------------------------------- storage
BATCHES = "batches"
STATE = "trial.json"
PROCEDURES = "procedures.parquet"


def _meta(spec: TrialSpec, batch: Batch) -> dict[bytes, bytes]:
    return {b"dentibot.trial": spec.name.encode(), b"dentibot.spec_hash":
            spec.spec_hash().encode(), b"dentibot.batch": batch.filename.encode()}


def write_batch(out: Path, spec: TrialSpec, batch: Batch, table: pa.Table) -> Path:
    """``table`` as the batch's file, whole or not at all (temporary file, then rename)."""
    path = out / BATCHES / batch.filename
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    pq.write_table(table.replace_schema_metadata(_meta(spec, batch)), tmp)
    os.replace(tmp, path)
    return path


def batch_done(out: Path, spec: TrialSpec, batch: Batch) -> bool:
    """The batch's file is there, of this spec, with every procedure."""
    path = out / BATCHES / batch.filename
    if not path.is_file():
        return False
    try:
        f = pq.ParquetFile(path)
        meta = f.schema_arrow.metadata or {}
        return (meta.get(b"dentibot.spec_hash") == spec.spec_hash().encode()
                and f.metadata.num_rows == len(batch.procedures))
    except (OSError, pa.ArrowException):
        return False


def open_out(out: Path, spec: TrialSpec) -> None:
    """Make ``out`` this trial's directory, or check it already is (the spec hash)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / BATCHES).mkdir(exist_ok=True)
    state = out / STATE
    want = {"name": spec.name, "spec_hash": spec.spec_hash()}
    if state.is_file():
        try:
            have = json.loads(state.read_text())
        except (OSError, ValueError):
            have = {}
        if have.get("spec_hash") != want["spec_hash"]:
            raise ConfigError("--out", str(out),
                              "a directory of this trial or a new one: it holds the batches "
                              f"of another trial spec ({have.get('name')!r}, hash "
                              f"{have.get('spec_hash')}; this spec's is {want['spec_hash']}): "
                              "choose another directory, or remove it to start again")
    else:
        state.write_text(json.dumps(want, indent=1) + "\n")


# ---------------------------------------------------------------------------- scheduling
Done = Callable[[Batch, pa.Table], None]


def _run_local(batches: list[Batch], workers: int, done: Done) -> None:
    """The batches in ``workers`` local processes, each written as it finishes; procedures
    log only what is critical (each would warn that depth is taken in the robot's base frame,
    and log each fault its run meets: the rows count them)."""
    run_all(_batch_procedures, batches, workers=workers, done=done, log_level=logging.CRITICAL)


def _batch_procedures(batch: Batch) -> pa.Table:
    return run_batch(batch.procedures)


def _run_ray(batches: list[Batch], address: str, done: Done) -> None:
    try:
        import ray
    except ImportError:
        raise ConfigError("--ray", address, "ray installed (pip install 'dentibot[ray]')",
                          "ray is not importable here") from None
    if not ray.is_initialized():
        ray.init(address=address, log_to_driver=False)
    remote = ray.remote(run_batch)
    pending = {remote.remote(b.procedures): b for b in batches}
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                done(pending.pop(ref), ray.get(ref))
    except BaseException:
        for ref in pending:
            ray.cancel(ref)
        raise


@dataclass
class TrialRun:
    """What :func:`run_trial` did: the rows of every procedure and how it got them."""

    table: pa.Table
    ran: int            # batches run now
    kept: int           # batches found on disk and kept
    wall_s: float


def run_trial(spec: TrialSpec, out: str | Path, workers: int = 1,
              ray_address: str | None = None,
              start: Callable[[int, int], None] | None = None,
              advance: Callable[[Batch], None] | None = None) -> TrialRun:
    """Run the batches of ``spec`` not yet in ``out`` and return every procedure's row.

    ``start(total, kept)`` is called once with the number of procedures and of those already
    on disk; ``advance(batch)`` after each batch is written. Ctrl-C (KeyboardInterrupt) stops
    it with the finished batches on disk."""
    out = Path(out)
    open_out(out, spec)
    batches = plan(spec)
    todo = [b for b in batches if not batch_done(out, spec, b)]
    if start is not None:
        start(spec.n * len(spec.arms),
              sum(len(b.procedures) for b in batches) - sum(len(b.procedures) for b in todo))
    t0 = time.perf_counter()

    def done(batch: Batch, table: pa.Table) -> None:
        write_batch(out, spec, batch, table)
        if advance is not None:
            advance(batch)

    if ray_address is not None:
        _run_ray(todo, ray_address, done)
    else:
        _run_local(todo, workers, done)
    table = pa.concat_tables([pq.read_table(out / BATCHES / b.filename, schema=SCHEMA)
                              for b in batches])
    table = table.replace_schema_metadata({b"dentibot.trial": spec.name.encode(),
                                           b"dentibot.spec_hash": spec.spec_hash().encode()})
    pq.write_table(table, out / PROCEDURES)
    return TrialRun(table, len(todo), len(batches) - len(todo), time.perf_counter() - t0)
