"""Run a validated protocol end to end: on the built-in simulator in lock-step time (default),
or on devices from a configuration (wire simulators or hardware) in real time.

Each step drives the runtime through operator commands only (no step bypasses the state
machine, the limits or the supervisor). Every tick goes to the MCAP recorder and to the live
summary; both see the same rows, so ``dentibot report`` on the file prints the same summary.
Cancelling the run (Ctrl-C) stops it safely: file stopped, file withdrawn from the canal where
possible, arm stopped; the recording and the summary are still written (status "aborted").
"""

from __future__ import annotations

import asyncio
import dataclasses
import signal
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import structlog

from dentibot.control.admittance import EXPERIMENT_1
from dentibot.control.feedrate import FeedrateParams
from dentibot.errors import ConfigError
from dentibot.io.devices import DevicesConfig, open_devices
from dentibot.protocol.schema import Protocol
from dentibot.runtime.clock import RealTimeClock
from dentibot.runtime.config import RuntimeConfig, Thresholds, ToolGeometry, TreatmentPlan
from dentibot.runtime.control_task import Devices, Runtime
from dentibot.runtime.harness import SimHarness
from dentibot.runtime.strategies import StrategyParams, make_strategy
from dentibot.sim.canal import CanalParams, material_params
from dentibot.sim.ftsensor import FTSensorParams
from dentibot.sim.nitifile import NiTiFile
from dentibot.sim.world import WorldConfig
from dentibot.telemetry.recorder import McapRecorder
from dentibot.telemetry.summary import RunSummary, SummaryAccumulator

log = structlog.get_logger("dentibot.protocol")

#: Longest time a single pass may take before the runner stops waiting (simulated s).
PASS_TIMEOUT_S = 600.0
#: Longest time the safe stop may spend withdrawing the file (simulated s).
RETRACT_TIMEOUT_S = 20.0
#: A canal whose lumen already has the target preparation's shape.
PRESHAPED = {"initial_apical_mm": CanalParams.target_apical_mm,
             "initial_taper": CanalParams.target_taper}
#: Thesis 5.3: spindle speed 60 rpm.
DRILLING_RPM = 60.0
EXIT_CODES = {"ok": 0, "fault": 3, "fracture": 4, "aborted": 130}


def world_config(p: Protocol) -> WorldConfig:
    ph = p.phantom
    curve = {}
    if ph.curve is not None:
        curve = {"curve_start_mm": ph.curve.start_mm, "curve_radius_mm": ph.curve.radius_mm,
                 "curve_angle_deg": ph.curve.angle_deg}
    tool = np.eye(4)
    tool[:3, 3] = p.tool.tip_mm
    return WorldConfig(
        seed=p.seed, ts=1.0 / p.control.rate_hz, tool=tool,
        sensor=FTSensorParams(offset_mm=p.tool.sensor_offset_mm),
        file=NiTiFile(size=p.file.size, taper=p.file.taper, length_mm=float(p.file.length_mm),
                      torsional_strength_mnm=p.file.torsional_strength_mnm),
        canal=CanalParams(working_length_mm=ph.working_length_mm, tilt_deg=ph.tilt_deg,
                          **curve, **(PRESHAPED if ph.preshaped else {}),
                          **material_params(ph.material.name, **ph.material.overrides())),
        orifice_gap_mm=ph.orifice_gap_mm, motion=p.patient.motion)


def runtime_config(p: Protocol) -> RuntimeConfig:
    lim = p.limits
    return RuntimeConfig(
        period_s=1.0 / p.control.rate_hz,
        tool=ToolGeometry(tip_6_mm=p.tool.tip_mm,
                          sensor_origin_6_mm=(0.0, 0.0, p.tool.sensor_offset_mm),
                          grip_h_mm=p.tool.grip_mm),
        thresholds=Thresholds(patient_moved_n=lim.patient_moved_n,
                              patient_release_n=min(1.0, 0.66 * lim.patient_moved_n),
                              torque_limit_mnm=lim.torque_limit_mnm,
                              axial_force_limit_n=lim.axial_force_limit_n,
                              stale_periods=lim.stale_periods.model_dump()),
        plan=TreatmentPlan(working_length_mm=p.phantom.working_length_mm,
                           orifice_gap_mm=p.phantom.orifice_gap_mm))


def align_plan(plan: TreatmentPlan, spec) -> TreatmentPlan:
    """The treatment plan for an align step (Table 6.4 when ``spec.config`` is set)."""
    if spec.config is None:
        return dataclasses.replace(plan, align_fz_n=spec.fz_n, align_rpm=spec.rpm,
                                   align_params=None, align_feedrate=None)
    c = EXPERIMENT_1[spec.config]
    feedrate = None
    if c.fz_bounds_n is not None:
        lo, hi = c.fz_bounds_n
        feedrate = FeedrateParams(tau_d_mnm=spec.tau_d_mnm, fz_min_n=lo, fz_max_n=hi)
    return dataclasses.replace(
        plan, align_fz_n=c.fz_n if c.fz_n is not None else 0.0,
        align_rpm=DRILLING_RPM if c.file_rotation else 0.0,
        align_params=c.params, align_feedrate=feedrate)


def apply_drill(rt: Runtime, spec) -> None:
    """Set up ``rt`` for a drill step: strategy, tau_d and fz bounds (eq 5.7), file speed."""
    strategy = StrategyParams(
        name=spec.strategy, section_mm=spec.section_mm, min_rounds=spec.min_rounds,
        feedrate=FeedrateParams(tau_d_mnm=spec.tau_d_mnm, fz_min_n=spec.fz_min_n,
                                fz_max_n=spec.fz_max_n))
    rt.cfg = dataclasses.replace(
        rt.cfg, plan=dataclasses.replace(rt.cfg.plan, strategy=strategy),
        handpiece=dataclasses.replace(rt.cfg.handpiece, drilling_rpm=spec.rpm))
    rt.strategy = make_strategy(strategy, rt.cfg.plan.working_length_mm, rt.ts)


def recording_path(p: Protocol, override: str | Path | None = None) -> Path | None:
    if override is not None:
        return Path(override)
    if not p.recording.enabled:
        return None
    return Path(p.recording.path or f"runs/{p.name}-{p.seed}.mcap")


def _at_rest(rt: Runtime) -> bool:
    e = rt.last
    return e is not None and abs(e.motor_rpm) < 1.0 and rt.last_row is not None and \
        max(abs(x) for x in rt.last_row["qdot_cmd_deg_s"]) == 0.0


def step_duration_s(p: Protocol, step_name: str) -> float | None:
    """Planned (simulated) length of step ``"<n>:<kind>"``, None when open-ended."""
    try:
        step = p.steps[int(step_name.split(":", 1)[0]) - 1]
    except (ValueError, IndexError):
        return None
    spec = step.spec
    if step.kind in ("drag", "align"):
        return spec.duration_s
    if step.kind == "drill" and spec.rounds:
        return sum(r.duration_s for r in spec.rounds)
    return None


class _Aborted(Exception):
    """The operator asked to stop (see :meth:`ProtocolRunner.abort`)."""


@dataclass
class RunResult:
    summary: RunSummary
    recording: Path | None

    @property
    def exit_code(self) -> int:
        return EXIT_CODES.get(self.summary.status, 1)


class ProtocolRunner:
    """Build the simulated procedure of ``protocol`` and run its steps.

    ``progress(figures)`` is called every ``progress_every`` ticks with the live key figures
    (step, state, t, depth, working length, file torque and its limit, force).
    """

    #: Why the operator stopped the run ("" while running; see :meth:`abort`).
    _abort_reason = ""

    def __init__(self, protocol: Protocol, *, recording: str | Path | None = None,
                 progress: Callable[[dict], None] | None = None,
                 progress_every: int = 250, overwrite: bool = True,
                 no_record: bool = False, devices: DevicesConfig | None = None) -> None:
        self.p = protocol
        self.progress = progress
        self.progress_every = progress_every
        self.path = None if no_record else recording_path(protocol, recording)
        self.summary: RunSummary | None = None
        self.acc = SummaryAccumulator(rate_hz=protocol.control.rate_hz)
        calibrate = any(s.kind == "calibrate_load" for s in protocol.steps)
        self.devices = devices
        self.h: SimHarness | None = None
        self.world = None
        self.rt: Runtime | None = None
        if devices is None:
            self.h = SimHarness(world_config(protocol), runtime_config(protocol),
                                calibrated=not calibrate, sink=self._row)
            self.world = self.h.world
            self.rt = self.h.runtime
            self.rt.event_sink = self._event
        elif not calibrate:
            raise ConfigError("steps", [s.kind for s in protocol.steps],
                              "a calibrate_load step (real devices need the load identified "
                              "before any force control)")
        self.recorder = None
        self._overwrite = overwrite
        self._abort_reason = ""

    # ---------------------------------------------------------------- sinks
    def _row(self, row: dict) -> None:
        self.acc.add(row)
        if self.recorder is not None:
            self.recorder.record(row)
        if self.progress is not None and row["tick"] % self.progress_every == 0:
            self.progress({
                "step": row["step"], "state": row["state"], "t": row["t"],
                "depth_mm": row["depth_mm"], "working_length_mm": row["working_length_mm"],
                "file_torque_mnm": row["file_torque_mnm"],
                "torque_limit_mnm": self.rt.cfg.thresholds.torque_limit_mnm,
                "force_n": float(np.linalg.norm(row["wrench_h"][:3])),
                "completeness": row.get("completeness"),
            })

    def _event(self, tick: int, kind: str, detail: str) -> None:
        t = tick * self.rt.ts
        self.acc.add_event(kind, detail, t=t, tick=tick)
        if self.recorder is not None:
            self.recorder.event(kind, detail, t=t, tick=tick)

    # ---------------------------------------------------------------- run
    def abort(self, reason: str = "stopped by the operator (Ctrl-C)") -> None:
        """Stop the procedure safely after the current tick (signal handlers, UIs)."""
        self._abort_reason = reason
        if self.rt is not None:
            self.rt.request_stop()

    async def run(self, handle_sigint: bool = False) -> RunResult:
        """Run the steps. With ``handle_sigint``, Ctrl-C calls :meth:`abort` (a safe stop
        that still writes the recording and the summary) instead of cancelling the task."""
        if not handle_sigint:
            return await self._run_devices()
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGINT, self.abort)
        try:
            return await self._run_devices()
        finally:
            loop.remove_signal_handler(signal.SIGINT)

    async def _run_devices(self) -> RunResult:
        if self.devices is None:
            return await self._run()
        p = self.p
        async with open_devices(self.devices) as d:
            self.rt = Runtime(Devices(d.arm, d.ft, d.motor, d.aux), runtime_config(p),
                              RealTimeClock(1.0 / p.control.rate_hz), sink=self._row)
            self.rt.event_sink = self._event
            return await self._run()

    async def _run(self) -> RunResult:
        p = self.p
        drills = [s.spec for s in p.steps if s.kind == "drill"]
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.recorder = McapRecorder(self.path, {
                "protocol": p.name, "seed": p.seed, "rate_hz": p.control.rate_hz,
                "devices": ({"arm": "sim", "ft": "sim", "handpiece": "sim", "aux": "sim"}
                            if self.devices is None else
                            {"arm": "meca500", "ft": "netft", "handpiece": "epos4",
                             "aux": "modbus" if self.devices.aux else "none"}),
                "file_torque_limit_mnm": p.file.torsional_strength_mnm,
                **({"tau_d_mnm": drills[0].tau_d_mnm} if drills else {})},
                overwrite=self._overwrite, validate=False)   # rows are checked in tests
        status, reason = "ok", ""
        try:
            for i, step in enumerate(p.steps):
                self.rt.step_name = f"{i + 1}:{step.kind}"
                await getattr(self, f"_step_{step.kind}")(step.spec)
                if self.rt.state == "fault":
                    break
            status, reason = self._status()
        except _Aborted:
            await self._safe_stop()
            return RunResult(self._close("aborted", self._abort_reason), self.path)
        except asyncio.CancelledError:
            await self._safe_stop()
            status, reason = "aborted", self._abort_reason or "cancelled by the operator"
            self._close(status, reason)
            raise
        except BaseException as exc:
            await self._safe_stop()
            status, reason = "fault", f"{type(exc).__name__}: {exc}"
            self._close(status, reason)
            raise
        summary = self._close(status, reason)
        return RunResult(summary, self.path)

    def _status(self) -> tuple[str, str]:
        w = self.world
        if w is not None and w.fractured is not None:
            f = w.fractured
            return "fracture", (f"file fractured by {f.cause} at {f.t:.2f} s, "
                                f"{f.torque_mnm:.1f} mNm, depth {f.depth_mm:.2f} mm")
        if self.rt.state == "fault":
            return "fault", "; ".join(self.rt.treatment.fault_causes)
        return "ok", ""

    def _close(self, status: str, reason: str) -> RunSummary:
        if self.recorder is not None:
            self.recorder.close(status, reason)
        self.summary = self.acc.finish(status, reason)
        return self.summary

    async def _safe_stop(self) -> None:
        """File stopped, withdrawn where possible, arm stopped; never raises."""
        rt = self.rt
        try:
            if rt.treatment.in_state("treating") and rt.state != "treating.retracting":
                await rt.command("retract")
            if rt.state == "treating.retracting":
                await rt.run(until=lambda r: r.state != "treating.retracting",
                             max_ticks=round(RETRACT_TIMEOUT_S / rt.ts))
            if rt.state != "fault":
                await rt.command("stop")
            # record the file and the arm coming to rest (or 1 s of it)
            await rt.run(until=_at_rest, max_ticks=round(1.0 / rt.ts))
        finally:
            for dev in (rt.dev.motor, rt.dev.arm):
                try:
                    await dev.stop()
                except Exception as exc:  # noqa: BLE001 - stop the other device too
                    log.warning("safe stop: device stop failed", error=str(exc))

    async def _run_for(self, seconds: float, until=None) -> None:
        if self._abort_reason:
            raise _Aborted
        await self.rt.run(until=lambda r: r.state == "fault" or (until is not None and until(r)),
                          max_ticks=max(1, round(seconds / self.rt.ts)))
        if self._abort_reason:
            raise _Aborted

    # ---------------------------------------------------------------- steps
    async def _command(self, trigger: str, already: str | None = None) -> None:
        """Send ``trigger`` unless the runtime is already in state ``already``."""
        if already is not None and self.rt.state == already:
            return
        refusal = await self.rt.command(trigger)
        if refusal is not None:
            await self.rt.command("fault")
            self.rt.treatment.fault_causes[-1] = f"protocol step: {refusal}"

    async def _step_calibrate_load(self, spec) -> None:
        await self._command("calibrate_load")
        await self._run_for(60.0, until=lambda r: not r.treatment.in_state("calibrating"))

    async def _step_drag(self, spec) -> None:
        await self._command("drag", already="dragging")
        if self.world is None:            # a real operator's hand moves the handpiece
            await self._run_for(spec.duration_s)
            return
        self.world.hand_force_0 = tuple(spec.hand_force_n)
        try:
            await self._run_for(spec.duration_s)
        finally:
            self.world.hand_force_0 = (0.0, 0.0, 0.0)

    async def _step_align(self, spec) -> None:
        rt = self.rt
        rt.cfg = dataclasses.replace(rt.cfg, plan=align_plan(rt.cfg.plan, spec))
        await self._command("align", already="self_aligning")
        await self._run_for(spec.duration_s)

    async def _step_drill(self, spec) -> None:
        rt = self.rt
        apply_drill(rt, spec)
        finished = ("done", "fault")
        if not spec.rounds:
            rt.treatment.passes_left = 0
            await self._command("drill")
            await self._run_for(PASS_TIMEOUT_S, until=lambda r: r.state in finished)
            return
        for rnd in spec.rounds:
            rt.treatment.passes_left = 10**6     # keep cleaning until the round's time is up
            await self._command("drill")
            await self._run_for(rnd.duration_s, until=lambda r: r.state in finished)
            if rt.state == "fault":
                return
            rt.treatment.passes_left = 0
            if rt.state != "treating.retracting":
                await self._command("retract")
            await self._run_for(RETRACT_TIMEOUT_S, until=lambda r: r.state in finished)

