"""Run summaries: the same figures live (fed tick by tick) and from a recording.

:class:`SummaryAccumulator` is fed one row at a time (``add``), plus the ``/events`` messages
(``add_event``), and ``finish(status, reason)`` gives a :class:`RunSummary`. The runner feeds it
live with the rows it records; ``dentibot report`` feeds it from the file
(:func:`summarize_recording`). Same code, same order of additions (rows in tick order; the
figures do not depend on how events interleave with rows), JSON float round trips are exact,
so both give exactly the same summary.

Definitions (whole run, and per protocol step over the ticks of that step):

- ``completeness``: last non-null ``completeness`` (0..1), None if never known.
- ``fractures``: ticks where ``fractured`` turns true (rising edges; before the first row: false).
- ``peak_file_torque_mNm``: max |file_torque_mnm| over all ticks.
- ``mean_file_torque_mNm``: mean |file_torque_mnm| over the ticks with ``motor_rpm != 0``
  (None if the motor never turned).
- ``peak_force_N``: max ||(fx, fy, fz)|| of ``wrench_h``.
- ``reversals``: increase of the cumulative ``reversals`` counter (sum of positive steps,
  counter taken as 0 before the first row): equal to the last value for the whole run.
- ``patient_moved_episodes``: rising edges of ``patient_moved``.
- ``deadline_misses``: ticks with ``overrun``.
- ``lateness_p99_us``: 99th percentile of ``lateness_us`` by the nearest-rank method (the
  ceil(0.99 n)-th smallest value: always a measured value).
- ``duration_s``: ticks x period when the rate is known; else the last ``t`` for the whole
  run and, per step, the sum of the ``t`` increments over its ticks.
- ``depth_reached_mm``: max ``depth_mm`` (None if never known).

Nulls and non-finite numbers are skipped (the recorder writes NaN as null, so live and file
agree).
"""

from __future__ import annotations

import json
import math
import os
from array import array
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from rich.table import Table

from dentibot.errors import ConfigError
from dentibot.telemetry.blocks import COL, TickBlock
from dentibot.telemetry.reader import MessageStream, Recording
from dentibot.telemetry.schema import END_STATUSES
from dentibot.telemetry.summary_kernels import (
    DURATION_RUN,
    DURATION_STEP,
    TORQUE_RUN,
    TORQUE_STEP,
    all_finite,
    block_figures,
)

__all__ = ["INCOMPLETE", "RunSummary", "StepSummary", "SummaryAccumulator", "summarize_file",
           "summarize_recording", "summarize_stream", "summary_json", "summary_table"]

INCOMPLETE = "incomplete"     # status of a recording without /run/end (crash, still running)
SUMMARY_STATUSES: tuple[str, ...] = (*END_STATUSES, INCOMPLETE)


@dataclass(kw_only=True)
class Figures:
    """The figures a whole run and each of its steps report (see the module docstring for
    the definitions)."""

    ticks: int = 0
    duration_s: float = 0.0
    depth_reached_mm: float | None = None
    completeness: float | None = None
    fractures: int = 0
    peak_file_torque_mNm: float | None = None
    mean_file_torque_mNm: float | None = None
    peak_force_N: float | None = None
    reversals: int = 0
    patient_moved_episodes: int = 0
    deadline_misses: int = 0
    lateness_p99_us: float | None = None


@dataclass(kw_only=True)
class StepSummary(Figures):
    """Figures of one protocol step."""

    name: str


@dataclass(kw_only=True)
class RunSummary(Figures):
    """Figures of a whole run, plus one :class:`StepSummary` per protocol step (in order of
    first appearance), the ``/events`` kinds counted (``events``) and the per-tick detected
    event names counted (``detections``)."""

    status: str
    reason: str = ""
    events: dict[str, int] = field(default_factory=dict)
    detections: dict[str, int] = field(default_factory=dict)
    steps: list[StepSummary] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable dict: status and reason first, then the figures; steps as a list
        of dicts in order, each with its name first."""
        d = asdict(self)
        d["steps"] = [{"name": st.pop("name"), **st} for st in d["steps"]]
        return {"status": d.pop("status"), "reason": d.pop("reason"), **d}


def _num(value: Any) -> float | None:
    """A finite number as float, anything else (None, NaN, bool, text) as None."""
    if type(value) is float:                    # the rows' case, first and cheapest
        return value if value - value == 0.0 else None    # inf - inf and nan are nan
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _p99(values: array) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    return ordered[(99 * len(ordered) + 99) // 100 - 1]      # ceil(0.99 n), in integers


def _max(a: float | None, b: float | None) -> float | None:
    if b is None:
        return a
    return b if a is None or b > a else a


class _Figures:
    """Running figures over a set of ticks (the whole run or one step)."""

    def __init__(self) -> None:
        self.ticks = 0
        self.duration_s = 0.0
        self.depth_max: float | None = None
        self.completeness: float | None = None
        self.fractures = 0
        self.torque_peak: float | None = None
        self.torque_abs_sum = 0.0
        self.torque_n = 0
        self.force_peak: float | None = None
        self.reversals = 0
        self.moved = 0
        self.misses = 0
        self.lateness = array("d")

    def add(self, tick: _Tick) -> None:
        self.ticks += 1
        self.duration_s += tick.dt
        self.depth_max = _max(self.depth_max, tick.depth)
        if tick.completeness is not None:
            self.completeness = tick.completeness
        self.fractures += tick.fracture_edge
        if tick.torque_abs is not None:
            self.torque_peak = _max(self.torque_peak, tick.torque_abs)
            if tick.turning:
                self.torque_abs_sum += tick.torque_abs
                self.torque_n += 1
        self.force_peak = _max(self.force_peak, tick.force)
        self.reversals += tick.reversals
        self.moved += tick.moved_edge
        self.misses += tick.overrun
        if tick.lateness is not None:
            self.lateness.append(tick.lateness)

    def figures(self, period_s: float | None) -> dict[str, Any]:
        return {
            "ticks": self.ticks,
            "duration_s": self.ticks * period_s if period_s is not None else self.duration_s,
            "depth_reached_mm": self.depth_max,
            "completeness": self.completeness,
            "fractures": self.fractures,
            "peak_file_torque_mNm": self.torque_peak,
            "mean_file_torque_mNm": (self.torque_abs_sum / self.torque_n
                                     if self.torque_n else None),
            "peak_force_N": self.force_peak,
            "reversals": self.reversals,
            "patient_moved_episodes": self.moved,
            "deadline_misses": self.misses,
            "lateness_p99_us": _p99(self.lateness),
        }


@dataclass(slots=True)
class _Tick:
    """What one row contributes, after the edges and increments are worked out."""

    dt: float
    depth: float | None
    completeness: float | None
    fracture_edge: int
    torque_abs: float | None
    turning: bool
    force: float | None
    reversals: int
    moved_edge: int
    overrun: int
    lateness: float | None


#: a block's ticks' lateness (none: the compiled ticks run in lock-step time)
_ZEROS = array("d", bytes(8 * 512))


#: the columns of a block of rows a summary reads: depth, completeness, file torque, motor
#: speed, the force (3)
_DEPTH, _DONE, _TORQUE, _RPM, _FORCE = (COL[name] for name in (
    "depth_mm", "completeness", "file_torque_mnm", "motor_rpm", "wrench_h"))
_BLOCK_READS = np.array([_DEPTH, _DONE, _TORQUE, _RPM, _FORCE, _FORCE + 1, _FORCE + 2],
                        dtype=np.intp)


class SummaryAccumulator:
    """Feed rows with :meth:`add`, events with :meth:`add_event`, get a RunSummary from
    :meth:`finish`. ``rate_hz`` (the control rate) makes durations ticks x period; without
    it they come from the rows' ``t``."""

    def __init__(self, rate_hz: float | None = None) -> None:
        if rate_hz is not None and not (_num(rate_hz) is not None and rate_hz > 0):
            raise ConfigError("summary.rate_hz", rate_hz, "a finite number > 0 (Hz) or None")
        self.period_s: float | None = 1.0 / rate_hz if rate_hz else None
        self._run = _Figures()
        self._steps: dict[str, _Figures] = {}
        self._events: dict[str, int] = {}
        self._detections: dict[str, int] = {}
        self._prev_t = 0.0
        self._prev_fractured = False
        self._prev_moved = False
        self._prev_reversals = 0

    def add(self, row: dict[str, Any]) -> None:
        """Take one tick row (a dict with the /tick fields; missing fields count as null)."""
        t = _num(row.get("t"))
        dt = 0.0
        if t is not None:
            dt, self._prev_t = max(t - self._prev_t, 0.0), t
        fractured = bool(row.get("fractured"))
        moved = bool(row.get("patient_moved"))
        rev = row.get("reversals")
        rev_step = 0
        if isinstance(rev, int) and not isinstance(rev, bool):
            rev_step, self._prev_reversals = max(rev - self._prev_reversals, 0), rev
        torque = _num(row.get("file_torque_mnm"))
        rpm = _num(row.get("motor_rpm"))
        wrench = row.get("wrench_h")
        force = None
        if isinstance(wrench, (list, tuple)) and len(wrench) >= 3:
            f = [_num(x) for x in wrench[:3]]
            if None not in f:
                force = math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
        tick = _Tick(
            dt=dt,
            depth=_num(row.get("depth_mm")),
            completeness=_num(row.get("completeness")),
            fracture_edge=int(fractured and not self._prev_fractured),
            torque_abs=None if torque is None else abs(torque),
            turning=rpm is not None and rpm != 0.0,
            force=force,
            reversals=rev_step,
            moved_edge=int(moved and not self._prev_moved),
            overrun=int(bool(row.get("overrun"))),
            lateness=_num(row.get("lateness_us")),
        )
        self._prev_fractured, self._prev_moved = fractured, moved
        self._run.add(tick)
        step = str(row.get("step") or "")
        figures = self._steps.get(step)
        if figures is None:
            figures = self._steps[step] = _Figures()
        figures.add(tick)
        for name in row.get("events") or ():
            self._detections[str(name)] = self._detections.get(str(name), 0) + 1

    def add_block(self, block: TickBlock) -> None:
        """Take a block of tick rows: the same as :meth:`add` of each of its rows, read from
        its columns (a block's ticks share their step and reversals and have no events, no
        fracture, no patient motion and no lateness). Maxima and norms are taken over the
        columns at once (the same operations, element by element); sums tick after tick, as
        :meth:`add` adds them."""
        n = len(block)
        if not n:
            return
        cols = block.cols
        if not all_finite(cols, _BLOCK_READS):   # an unknown value somewhere: row by row
            for row in block.rows():
                self.add(row)
            return
        step = str(block.step or "")
        figures = self._steps.get(step)
        if figures is None:
            figures = self._steps[step] = _Figures()
        rev = block.reversals
        rev_step, self._prev_reversals = max(rev - self._prev_reversals, 0), rev
        self._prev_fractured = self._prev_moved = False
        run = self._run
        sums = np.array([run.duration_s, figures.duration_s, run.torque_abs_sum,
                         figures.torque_abs_sum])
        depth_max, torque_peak, force_peak, turning, self._prev_t = block_figures(
            cols, _DEPTH, _TORQUE, _RPM, _FORCE, block.k0, block.ts, self._prev_t, sums)
        completeness = float(cols[-1, _DONE])
        lateness = _ZEROS[:n] if n <= len(_ZEROS) else array("d", bytes(8 * n))
        run.duration_s, figures.duration_s = float(sums[DURATION_RUN]), \
            float(sums[DURATION_STEP])
        run.torque_abs_sum, figures.torque_abs_sum = float(sums[TORQUE_RUN]), \
            float(sums[TORQUE_STEP])
        for fig in (run, figures):
            fig.ticks += n
            fig.depth_max = _max(fig.depth_max, depth_max)
            fig.completeness = completeness
            fig.torque_peak = _max(fig.torque_peak, torque_peak)
            fig.torque_n += turning
            fig.force_peak = _max(fig.force_peak, force_peak)
            fig.reversals += rev_step
            fig.lateness.extend(lateness)

    def add_event(self, kind: str, detail: str = "", *, t: float | None = None,
                  tick: int | None = None) -> None:
        """Take one ``/events`` message (counted by kind)."""
        self._events[kind] = self._events.get(kind, 0) + 1

    def finish(self, status: str, reason: str = "") -> RunSummary:
        """The summary so far, ended with ``status`` (ok, fault, fracture, aborted,
        incomplete) and ``reason``. May be called again after more rows."""
        if status not in SUMMARY_STATUSES:
            raise ConfigError("run.status", status, f"one of {list(SUMMARY_STATUSES)}")
        run = self._run.figures(self.period_s)
        if self.period_s is None:
            run["duration_s"] = self._prev_t          # the last t, exactly
        return RunSummary(
            status=status, reason=reason, **run,
            events=dict(self._events), detections=dict(self._detections),
            steps=[StepSummary(name=name, **fig.figures(self.period_s))
                   for name, fig in self._steps.items()])


def _summarize(rate_hz: Any, rows, events, end: dict[str, Any] | None,
               recovered: dict[str, str] | None) -> RunSummary:
    acc = SummaryAccumulator(rate_hz=rate_hz)
    for row in rows:
        acc.add(row)
    for ev in events:
        acc.add_event(str(ev.get("kind", "")), str(ev.get("detail", "")),
                      t=ev.get("t"), tick=ev.get("tick"))
    return _finish(acc, end, recovered)


def _finish(acc: SummaryAccumulator, end: dict[str, Any] | None,
            recovered: dict[str, str] | None = None) -> RunSummary:
    if end is None:
        if recovered is not None:
            return acc.finish(INCOMPLETE, "no /run/end: recovered from a recording cut short "
                              f"({recovered.get('source', '?')}, "
                              f"{recovered.get('ticks', '?')} ticks saved)")
        return acc.finish(INCOMPLETE, "no /run/end in the recording (cut short or still running)")
    status = end.get("status")
    if status not in SUMMARY_STATUSES:
        return acc.finish(INCOMPLETE, f"unknown end status {status!r}")
    return acc.finish(status, str(end.get("reason", "")))


def _rate(metadata: dict[str, Any]) -> float | None:
    rate = metadata.get("rate_hz")
    return rate if _num(rate) is not None and rate > 0 else None


def summarize_recording(rec: Recording) -> RunSummary:
    """The summary of a recording read by :func:`~dentibot.telemetry.reader.read_recording`.

    Without ``/run/end`` (crash, cut file, file rewritten by ``dentibot recover``) the status
    is ``incomplete``.
    """
    return _summarize(_rate(rec.metadata), rec.rows, rec.events, rec.end, rec.recovered)


def summarize_file(path: str | os.PathLike[str]) -> RunSummary:
    """The summary of the recording at ``path``, streamed (constant memory, any run length):
    the same result as ``summarize_recording(read_recording(path))``.

    Raises TelemetryError if the file is missing or not an MCAP file.
    """
    return summarize_stream(MessageStream(path))


def summarize_stream(stream: MessageStream) -> RunSummary:
    """:func:`summarize_file` over a :class:`MessageStream` not iterated yet; afterwards the
    stream's ``complete``, ``recovered`` and ``problems`` say what the file was like."""
    acc: SummaryAccumulator | None = None
    events: list[dict[str, Any]] = []
    end: dict[str, Any] | None = None
    for topic, obj in stream:
        if topic == "/tick":
            if acc is None:                      # no /run before the first row: no rate
                acc = SummaryAccumulator()
            acc.add(obj)
        elif topic == "/run" and acc is None:
            acc = SummaryAccumulator(rate_hz=_rate(obj) if isinstance(obj, dict) else None)
        elif topic == "/events":
            events.append(obj)
        elif topic == "/run/end":
            end = obj if isinstance(obj, dict) else None
    acc = acc or SummaryAccumulator()
    for ev in events:
        acc.add_event(str(ev.get("kind", "")), str(ev.get("detail", "")),
                      t=ev.get("t"), tick=ev.get("tick"))
    return _finish(acc, end, stream.recovered)


def summary_json(summary: RunSummary) -> str:
    """The summary as indented JSON (keys as in :class:`RunSummary`)."""
    return json.dumps(summary.to_dict(), indent=2)


def _fmt(value: Any, spec: str = ".1f") -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return format(value, spec)
    return str(value)


# Table rows: (label, RunSummary/StepSummary attribute, number format)
_ROWS: tuple[tuple[str, str, str], ...] = (
    ("duration (s)", "duration_s", ".2f"),
    ("ticks", "ticks", ""),
    ("depth reached (mm)", "depth_reached_mm", ".2f"),
    ("completeness", "completeness", ".1%"),
    ("file torque peak (mNm)", "peak_file_torque_mNm", ".1f"),
    ("file torque mean (mNm)", "mean_file_torque_mNm", ".1f"),
    ("force peak (N)", "peak_force_N", ".2f"),
    ("reversals", "reversals", ""),
    ("patient moved (episodes)", "patient_moved_episodes", ""),
    ("fractures", "fractures", ""),
    ("deadline misses", "deadline_misses", ""),
    ("lateness p99 (us)", "lateness_p99_us", ".0f"),
)


def summary_table(summary: RunSummary) -> Table:
    """A rich Table: one row per figure, one column per protocol step then the whole run;
    status and reason in the title, the /events counts in the caption."""
    title = f"DentiBot run: {summary.status}"
    if summary.reason:
        title += f" ({summary.reason})"
    caption = None
    if summary.events:
        caption = "events: " + ", ".join(f"{k} x{n}" for k, n in summary.events.items())
    table = Table(title=title, caption=caption)
    table.add_column("")
    for step in summary.steps:
        table.add_column(step.name or "(none)", justify="right")
    table.add_column("whole run", justify="right", style="bold")
    for label, attr, spec in _ROWS:
        table.add_row(label, *(_fmt(getattr(s, attr), spec) for s in (*summary.steps, summary)))
    return table
