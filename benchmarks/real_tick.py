"""The real lock-step tick: the main job's drill step as ``dentibot run`` runs it, timed whole,
with and without the recorder, and broken down by component.

    .venv/bin/python benchmarks/real_tick.py [--seconds S] [--repeats 3] [--no-breakdown]

What runs is what the CLI runs: a :class:`~dentibot.app.runner.ProtocolRunner` over the main
job (``protocols/root-canal.yaml``) on the built-in simulator in lock-step time, with the live
summary, a progress callback every 250 ticks formatting the CLI's figures, and, by default,
the MCAP recorder (``--no-record``: without it). Every step of the protocol runs; the figures
are those of its drill step (``--seconds S``: one drilling round of S simulated seconds
instead of the protocol's rounds), timed from its first progress report to its last (the
progress callback is the timer; a tap on the rows would keep the drilling ticks out of the
compiled loop, :mod:`dentibot.app.drill_loop`, as it keeps any caller's tap).

- ``us_per_tick``: wall time per tick of the drill step; ``speed_factor``: simulated seconds
  per wall second;
- ``recorder_ratio``: us per tick with the recorder / without it, the two runs interleaved
  ``--repeats`` times (the median of each is reported; the machine is shared);
- ``writer_cpu_us_per_tick``: CPU time of the recorder's writer (its process, or its thread
  for an in-process recorder) during the drill step, and ``main_cpu_us_per_tick`` that of the
  control process (the control task's thread and the relay's that hands the compiled ticks'
  rows over; an in-process recorder's writer thread too);
- ``breakdown``: one more run with ``time.perf_counter_ns`` hooks around each component
  (exclusive time: a component's time excludes the hooked components it calls), us per tick:
  ``drill_kernel`` (the compiled drilling ticks: every law of those ticks, their rows' numbers
  and the world's steps between them; recording, also their blocks sent to the recorder's
  process, with any wait for room), ``drill_loop`` (preparing each compiled call and
  bringing the Python side up to date after it); for the ticks the control task runs itself:
  ``world_step``, ``control`` (forward chain, estimate, admittance law and arm command),
  ``supervisor``, ``state_machine`` (behaviours' detection and entry, the machine's
  transitions), ``device_shims`` (the in-process device reads and commands),
  ``telemetry_row`` (building the row) and ``sim_truth`` (the simulator's truth fields in it),
  ``live_summary`` (rows and blocks), ``recorder_record`` (the control thread's side of the
  recorder, rows and blocks, including any back-pressure wait), ``progress``, ``gate`` (work
  between two ticks) and ``glue`` (everything else: the tick's own code, the clock, the event
  loop). The hooks cost a little themselves (``hooked_us_per_tick`` beside ``us_per_tick``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import inspect
import logging
import os
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import structlog

sys.path.insert(0, str(Path(__file__).resolve().parent))

from dentibot.app import drill_kernels
from dentibot.app.drill_loop import DrillLoop
from dentibot.app.runner import ProtocolRunner
from dentibot.cli.run import _figures_text
from dentibot.protocol.loader import load_protocol
from dentibot.protocol.schema import Protocol
from dentibot.runtime import control_task
from dentibot.telemetry.recorder import McapRecorder
from dentibot.telemetry.recorder_process import RecorderProcess

ROOT = Path(__file__).resolve().parents[1]
PROTOCOL = ROOT / "protocols" / "root-canal.yaml"
DRILL = "drill"
COMPONENTS = ("drill_kernel", "drill_loop", "world_step", "control", "supervisor",
              "state_machine", "device_shims", "telemetry_row", "sim_truth", "live_summary",
              "recorder_record", "progress", "gate", "glue")


def main_job(seconds: float | None = None) -> Protocol:
    """The main job; with ``seconds``, its drill step drills one round of that length."""
    p = load_protocol(PROTOCOL)
    if seconds is None:
        return p
    d = p.model_dump(exclude_none=True)
    for step in d["steps"]:
        if DRILL in step:
            step[DRILL]["rounds"] = [{"duration_s": float(seconds)}]
    return Protocol.model_validate(d)


def drill_rounds_s(protocol: Protocol | None = None) -> float:
    """The simulated length of the main job's drill rounds (s)."""
    p = protocol or load_protocol(PROTOCOL)
    return sum(r.duration_s for s in p.steps if s.kind == DRILL for r in s.spec.rounds or ())


class _Hooks:
    """Exclusive wall time per component from wrappers around the components' callables."""

    def __init__(self) -> None:
        self.ns: dict[str, int] = defaultdict(int)
        self._stack: list[list[int]] = []
        self._undo: list[tuple[object, str, object, bool]] = []

    def _done(self, comp: str, frame: list[int], dt: int) -> None:
        self._stack.pop()
        self.ns[comp] += dt - frame[0]
        if self._stack:
            self._stack[-1][0] += dt

    def wrap(self, comp: str, fn):
        clock, stack, done = time.perf_counter_ns, self._stack, self._done
        if inspect.iscoroutinefunction(fn):
            async def awrapped(*a, **k):
                frame = [0]
                stack.append(frame)
                t0 = clock()
                try:
                    return await fn(*a, **k)
                finally:
                    done(comp, frame, clock() - t0)
            return awrapped

        def wrapped(*a, **k):
            frame = [0]
            stack.append(frame)
            t0 = clock()
            try:
                return fn(*a, **k)
            finally:
                done(comp, frame, clock() - t0)
        return wrapped

    def patch(self, obj, name: str, comp: str) -> None:
        """Replace ``obj.name`` by its timed wrapper (undone by :meth:`undo`)."""
        had = name in getattr(obj, "__dict__", {})
        old = getattr(obj, name)
        self._undo.append((obj, name, obj.__dict__.get(name) if had else None, had))
        setattr(obj, name, self.wrap(comp, old))

    def undo(self) -> None:
        for obj, name, old, had in reversed(self._undo):
            if had:
                setattr(obj, name, old)
            else:
                delattr(obj, name)
        self._undo.clear()


def _device_methods(dev) -> list[str]:
    return [n for n in dir(dev) if not n.startswith("_")
            and inspect.iscoroutinefunction(getattr(dev, n, None))]


def _hook_runner(h: _Hooks, runner: ProtocolRunner) -> None:
    """Timed wrappers around the components of ``runner``'s tick (see the module docstring)."""
    proc = runner.procedure
    rt = proc.runtime
    h.patch(proc.clock, "_step", "world_step")
    h.patch(rt, "_estimate", "control")
    h.patch(control_task, "arm_command", "control")
    for name in ("check_inputs", "observe", "check_estimate", "check_command"):
        h.patch(rt.supervisor, name, "supervisor")
    for b in {id(b): b for b in rt.behaviours.values()}.values():
        for name in ("detect", "enter"):
            h.patch(b, name, "state_machine")
    h.patch(rt.treatment, "fire", "state_machine")
    h.patch(rt.dev, "read", "device_shims")
    for dev in (rt.dev.arm, rt.dev.ft, rt.dev.motor, rt.dev.aux):
        if dev is not None:
            for name in _device_methods(dev):
                h.patch(dev, name, "device_shims")
    h.patch(control_task, "telemetry_row", "telemetry_row")
    h.patch(rt, "truth", "sim_truth")
    h.patch(runner.acc, "add", "live_summary")
    h.patch(runner.acc, "add_block", "live_summary")
    for cls in (McapRecorder, RecorderProcess):
        h.patch(cls, "record", "recorder_record")
        h.patch(cls, "record_block", "recorder_record")
    h.patch(runner, "progress", "progress")
    h.patch(proc.gate, "between", "gate")
    h.patch(drill_kernels, "drill_ticks", "drill_kernel")
    h.patch(DrillLoop, "__call__", "drill_loop")


def _process_cpu_s(pid: int) -> float | None:
    """CPU time (user + system) of process ``pid`` so far, from /proc (Linux)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _thread_cpu_s(thread) -> float | None:
    if thread is None or thread.ident is None or not hasattr(time, "pthread_getcpuclockid"):
        return None
    try:
        return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))
    except (OSError, ProcessLookupError):
        return None


class _DrillTap:
    """The runner's progress callback (every 250 ticks, formatting the CLI's figures): times
    the drill step from its first report to its last. Not a tap on the rows: a tap sees each
    row as its tick ends, which keeps the drilling ticks out of the compiled loop."""

    def __init__(self, hooks: _Hooks | None = None) -> None:
        self.runner: ProtocolRunner | None = None
        self.hooks = hooks
        self.ns: dict[str, int] = {}          # the hooks' figures over the window
        self.t0 = self.t1 = 0
        self.tick0 = self.tick1 = -1
        self.cpu0 = self.cpu1 = 0.0
        self.wcpu0 = self.wcpu1 = None

    def _writer_cpu_s(self) -> float | None:
        rec = self.runner.recorder if self.runner is not None else None
        if rec is None:
            return None
        pid = getattr(rec, "pid", None)        # the recorder process, or the writer thread
        return _process_cpu_s(pid) if pid is not None else _thread_cpu_s(rec._thread)

    def __call__(self, figures: dict) -> None:
        _figures_text(figures)
        if not figures["step"].endswith(":" + DRILL):
            return
        tick = round(figures["t"] / self.runner.rt.ts)
        if self.tick0 < 0:
            if self.hooks is not None:
                self.hooks.ns.clear()
            self.cpu0 = time.process_time()
            self.wcpu0 = self._writer_cpu_s()
            self.t0, self.tick0 = time.perf_counter_ns(), tick
        else:
            self.t1, self.tick1 = time.perf_counter_ns(), tick
            self.cpu1 = time.process_time()
            self.wcpu1 = self._writer_cpu_s()
            if self.hooks is not None:
                self.ns = dict(self.hooks.ns)


def run_cli(seconds: float | None = None, record: bool = True, breakdown: bool = False,
            out_dir: Path | None = None) -> dict:
    """The main job as ``dentibot run`` runs it; figures of its drill step."""
    protocol = main_job(seconds)
    path = (out_dir or Path(tempfile.gettempdir())) / "dentibot-bench-real-tick.mcap"
    hooks = _Hooks()
    tap = _DrillTap(hooks if breakdown else None)
    runner = ProtocolRunner(protocol, recording=path, progress=tap, overwrite=True,
                            no_record=not record)
    tap.runner = runner
    if breakdown:
        _hook_runner(hooks, runner)
    t0 = time.perf_counter()
    try:
        result = asyncio.run(runner.run())
    finally:
        hooks.undo()
    total_s = time.perf_counter() - t0
    ticks = tap.tick1 - tap.tick0
    if tap.tick0 < 0 or ticks <= 0:
        raise RuntimeError(f"the drill step did not run ({result.summary.status}: "
                           f"{result.summary.reason})")
    wall_ns = tap.t1 - tap.t0
    ts = runner.rt.ts
    out = {"record": record, "seconds": seconds, "ticks": ticks,
           "us_per_tick": wall_ns / 1e3 / ticks, "speed_factor": ticks * ts / (wall_ns / 1e9),
           "main_cpu_us_per_tick": (tap.cpu1 - tap.cpu0) * 1e6 / ticks,
           "writer_cpu_us_per_tick": (None if tap.wcpu0 is None or tap.wcpu1 is None
                                      else (tap.wcpu1 - tap.wcpu0) * 1e6 / ticks),
           "run_wall_s": total_s, "run_ticks": result.summary.ticks,
           "status": result.summary.status, "completeness": result.summary.completeness}
    rec = runner.recorder
    if rec is not None:
        out.update(file_bytes=rec.bytes_flushed, backpressure_waits=rec.backpressure_waits,
                   queue_depth_max=rec.queue_depth_max, flushes=rec.flushes)
        with contextlib.suppress(OSError):
            path.unlink()
    if breakdown:
        comp = {c: tap.ns.get(c, 0) / 1e3 / ticks for c in COMPONENTS if c != "glue"}
        comp["glue"] = max(out["us_per_tick"] - sum(comp.values()), 0.0)
        out["breakdown"] = comp
        out["hooked_us_per_tick"] = out["us_per_tick"]
    return out


def measure(seconds: float | None = None, repeats: int = 3, breakdown: bool = True) -> dict:
    """Recorder on and off, interleaved ``repeats`` times; then one run with the breakdown."""
    runs: dict[str, list[dict]] = {"recorder": [], "no_recorder": []}
    ratios = []
    for _ in range(repeats):
        on = run_cli(seconds, record=True)
        off = run_cli(seconds, record=False)
        runs["recorder"].append(on)
        runs["no_recorder"].append(off)
        ratios.append(on["us_per_tick"] / off["us_per_tick"])

    def med(name: str, key: str) -> float | None:
        vals = [r[key] for r in runs[name] if r.get(key) is not None]
        return statistics.median(vals) if vals else None

    res = {"protocol": "root-canal", "drill_seconds": seconds, "repeats": repeats,
           "ticks": runs["recorder"][0]["ticks"], "runs": runs,
           "us_per_tick": med("no_recorder", "us_per_tick"),
           "us_per_tick_recorder": med("recorder", "us_per_tick"),
           "speed_factor": med("no_recorder", "speed_factor"),
           "speed_factor_recorder": med("recorder", "speed_factor"),
           "recorder_ratio": statistics.median(ratios), "recorder_ratios": ratios,
           "writer_cpu_us_per_tick": med("recorder", "writer_cpu_us_per_tick"),
           "main_cpu_us_per_tick_recorder": med("recorder", "main_cpu_us_per_tick"),
           "main_cpu_us_per_tick": med("no_recorder", "main_cpu_us_per_tick")}
    if breakdown:
        b = run_cli(seconds, record=True, breakdown=True)
        res["breakdown"] = b["breakdown"]
        res["breakdown_us_per_tick"] = b["us_per_tick"]
    return res


def print_report(r: dict) -> None:
    what = ("the protocol's rounds" if r["drill_seconds"] is None
            else f"one {r['drill_seconds']:g} s round")
    print(f"real lock-step tick: main job's drill step ({what}, {r['ticks']} ticks), "
          f"CLI path, median of {r['repeats']}:")
    print(f"  recorder on : {r['us_per_tick_recorder']:7.1f} us/tick, "
          f"{r['speed_factor_recorder']:5.1f}x real time; control process CPU "
          f"{r['main_cpu_us_per_tick_recorder']:.1f} us/tick, writer CPU "
          f"{r['writer_cpu_us_per_tick'] or 0:.1f} us/tick")
    print(f"  recorder off: {r['us_per_tick']:7.1f} us/tick, {r['speed_factor']:5.1f}x real "
          f"time; control process CPU {r['main_cpu_us_per_tick']:.1f} us/tick")
    print(f"  on / off: x{r['recorder_ratio']:.2f} (each run: "
          f"{', '.join(f'{x:.2f}' for x in r['recorder_ratios'])})")
    b = r.get("breakdown")
    if b:
        tot = r["breakdown_us_per_tick"]
        print(f"  breakdown (recorder on, hooked run {tot:.1f} us/tick):")
        for c, us in sorted(b.items(), key=lambda kv: -kv[1]):
            print(f"    {c:<16}{us:7.1f} us  {100 * us / tot:5.1f} %")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=None,
                    help="one drilling round of this length (default: the protocol's rounds)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-breakdown", action="store_true")
    args = ap.parse_args()
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))
    print_report(measure(args.seconds, args.repeats, not args.no_breakdown))


if __name__ == "__main__":
    main()
