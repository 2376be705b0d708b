"""The fixed-period control task (docs/architecture.md, "The tick"): read and supervise ->
estimate -> the state's behaviour detects events for the machine -> entry of a new state ->
control law and commands -> one telemetry row.

Events are detected before the commands of the same tick: a patient movement, a torque spike
or an emergency stop seen in tick k is acted on by the commands of tick k, not k + 1. What each
state does lives in :mod:`dentibot.states.behaviours` and :mod:`dentibot.states.modes`; the
maths of the tick in :mod:`dentibot.control.tick`.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Awaitable, Callable

import numpy as np
import structlog

from dentibot.control.admittance import SELF_ALIGNMENT, AdmittanceController
from dentibot.control.kinematics import Meca500
from dentibot.control.wrench import GravityModel
from dentibot.errors import DentibotError, DeviceFault
from dentibot.runtime.clock import Clock, DeadlineStats, realtime_policy
from dentibot.runtime.actuate import apply_mode, arm_command, recover_all, stop_all
from dentibot.runtime.config import RuntimeConfig
from dentibot.runtime.estimate import Devices, Estimate, estimate
from dentibot.runtime.rows import telemetry_row
from dentibot.runtime.supervisor import Finding, Supervisor
from dentibot.runtime.tool import reference_transforms, set_tool_tip, tool_matrix
from dentibot.runtime.tooth import ToothFrame
from dentibot.states.behaviours import Context, current_mode, make_behaviours
from dentibot.states.modes import MODES, Mode, send_file_command
from dentibot.states.strategies import make_strategy
from dentibot.states.treatment import Refusal, Treatment

log = structlog.get_logger("dentibot.runtime")

#: Events that are recorded but are not triggers of the state machine.
NOTES = frozenset({"tcp_point", "inputs_invalid", "file_stopped"})


class Runtime:
    """One procedure's control task, state machine and bookkeeping.

    ``truth`` (simulator only) returns extra telemetry fields known only to a simulation
    (phantom pose, true depth, completeness, fracture); the control never reads them.
    ``on_tick(runtime)``, when set, ends every tick (a study reading the world needs no row).
    """

    def __init__(self, devices: Devices, config: RuntimeConfig, clock: Clock, *,
                 gravity: GravityModel | None = None, sink: Callable[[dict], None] | None = None,
                 event_sink: Callable[[int, str, str], None] | None = None,
                 truth: Callable[[], dict] | None = None, step_name: str = "") -> None:
        self.dev = devices
        self.cfg = config
        self.clock = clock
        self.ts = config.period_s
        self.R_6_H = np.reshape(np.asarray(config.tool.R_6_H, dtype=np.float64), (3, 3))
        self.kin = Meca500(tool=tool_matrix(self.R_6_H, config.tool.tip_6_mm))
        self.admittance = AdmittanceController(self.kin, SELF_ALIGNMENT, self.ts)
        self.speed_limits = [float(x) for x in self.kin.joint_speed_limits_deg_s]
        self.treatment = Treatment(passes_left=config.plan.passes - 1)
        self.gravity: GravityModel | None = None
        self._to_h: dict = {}
        if gravity is not None:
            self.set_gravity(gravity)
        self.ctx = Context(make_strategy(config.plan.strategy, config.plan.working_length_mm,
                                         self.ts))
        self.behaviours = make_behaviours()
        self.ctx.tooth = ToothFrame(config.tooth, self.ts) if config.tooth and devices.tracker \
            else None
        self.supervisor = Supervisor(config.thresholds.stale_periods, self.ts,
                                     config.thresholds.supervisor)
        self.stats = DeadlineStats(self.ts, deadlines=clock.realtime)
        self.sink = sink
        self.truth = truth
        self.step_name = step_name
        #: ``event_sink(tick, kind, detail)`` gets every event, command and fault as it happens.
        self.event_sink = event_sink
        self.on_tick: Callable[[Runtime], None] | None = None
        #: in real time the drive's cycle runs right after the tick's commands (Handpiece)
        self._cycle_soon = clock.realtime and getattr(devices.motor, "cycle_soon", None)
        #: ticks run in bulk (:mod:`dentibot.app.drill_loop`); readers of their figures and rows
        #: (``on_block``: all; ``on_block_read``: all but a recorder fed via ``block_wire``)
        self.fused: Callable[[Runtime], Awaitable[int]] | None = None
        self.on_ticks = self.on_block = self.on_block_read = self.block_wire = None
        self.ticks = 0
        self.events_log: list[tuple[int, str, str]] = []   # (tick, kind, detail)
        self.last: Estimate | None = None
        self.last_row: dict | None = None
        self.mode: Mode = MODES["idle"]
        self._state = self._ref = self.file_cmd = self.qdot_cmd = None   # qdot: last tick's
        #: events for the next tick (a command the supervisor refused)
        self.pending: list[tuple[str, str | None]] = []
        self._stop = asyncio.Event()
        #: stop commands still waiting for their device's answer (a silent link)
        self.unfinished_stops: set[asyncio.Task] = set()

    def set_gravity(self, gravity: GravityModel) -> None:
        """Use ``gravity`` (a load calibration result) for compensation from now on."""
        self.gravity = gravity
        self._to_h = reference_transforms(self.cfg.tool, gravity.mount_angle_deg)
        self.treatment.gravity_known = True

    @property
    def state(self) -> str:
        return self.treatment.state

    async def command(self, trigger: str) -> Refusal | None:
        """An operator command (pedal, terminal, protocol step): through the machine only. A
        reset out of ``fault`` also brings every device back to ready, or faults again."""
        was_fault = self.state == "fault"
        refusal = await self.treatment.fire(trigger, "operator" if trigger == "fault" else None)
        self.note("command", trigger if refusal is None else str(refusal))
        if refusal is None and was_fault and trigger == "reset":
            cause = await recover_all(self.dev.motor, self.dev.arm, self.dev.aux)
            if cause is not None:
                await self.treatment.fire("fault", cause)
                self.note("fault", cause)
        return refusal

    async def estop(self, cause: str = "software emergency stop") -> None:
        """Software emergency stop: file and arm stopped now (not at the next tick), then
        the latched fault; only ``reset`` leaves it."""
        await self.stop_devices()
        await self.treatment.fire("fault", cause)
        self.note("fault", cause)

    async def stop_devices(self) -> None:
        """File and arm stopped at once, bounded (:func:`~dentibot.runtime.actuate.stop_all`)."""
        await stop_all(self.dev.motor, self.dev.arm, self.unfinished_stops)
        self.file_cmd = ("stop",)

    async def prepare(self) -> None:
        """Before the first tick: the drive's current limit from the file's strength."""
        limit = self.cfg.thresholds.drive_limit_mnm
        if limit is not None:
            await self.dev.motor.set_current_limit(self.cfg.handpiece.current_for(limit))

    def configure(self, *, plan=None, handpiece=None, restart_strategy: bool = False) -> None:
        """A new plan and/or handpiece settings from the next tick (a step's set-up, between
        two ticks); ``restart_strategy``: a fresh drilling strategy from the plan's."""
        self.cfg = dataclasses.replace(self.cfg, plan=plan or self.cfg.plan,
                                       handpiece=handpiece or self.cfg.handpiece)
        if restart_strategy:
            self.ctx.strategy = make_strategy(self.cfg.plan.strategy,
                                              self.cfg.plan.working_length_mm, self.ts)

    def request_stop(self) -> None:
        """Ask :meth:`run` to return after the current tick."""
        self._stop.set()

    async def run(self, until: Callable[[Runtime], bool] | None = None,
                  max_ticks: int | None = None,
                  between: Callable[[], Awaitable[None]] | None = None) -> None:
        """Tick until ``until(self)`` is true, ``max_ticks`` ticks ran or ``request_stop``.
        ``between()`` is awaited after every tick (``fused``'s: after its last), before waiting
        for the next one (the procedure's gate). Real time: priority raised, collector in the
        slack after a tick (:func:`~dentibot.runtime.clock.realtime_policy`)."""
        self._stop.clear()
        self.clock.start()
        await self.clock.wait_first()
        lateness = 0.0
        n = 0
        fused = self.fused if until is None and max_ticks is None else None
        with realtime_policy(self.clock, self.cfg.cpus) as collect:
            while not self._stop.is_set():
                t0 = time.perf_counter()
                ran = await fused(self) if fused is not None else 0
                if not ran:
                    await self.tick(lateness)
                    self.stats.add(lateness, time.perf_counter() - t0)
                n += ran or 1
                if (max_ticks is not None and n >= max_ticks) or (
                        until is not None and until(self)):
                    break
                collect(n)
                if between is not None:
                    await between()
                    if self._stop.is_set():
                        break
                lateness = await self.clock.wait_next()
        self.stats.skipped = self.clock.skipped

    async def tick(self, lateness_s: float = 0.0) -> None:
        t_start = time.perf_counter()
        k = self.ticks
        tr = self.treatment
        events: list[tuple[str, str | None]] = self.pending
        self.pending = []
        # 1. read + supervise
        est, findings = await self._read_and_estimate(k)
        for f in findings:
            events.append(("fault", str(f)))
        # a command between ticks (operator, protocol) changed the state: its entry first
        if tr.state != self._state and not findings:
            await self._enter(tr.state, est)
        # 3. events from the estimates
        if est is not None and not findings:
            events.extend(self.behaviours[tr.state].detect(self.ctx, self, est))
        for trigger, cause in events:
            if trigger in NOTES:              # worth recording, not a transition
                self.note(trigger, cause or "")
                if trigger == "file_stopped":
                    await self.dev.motor.stop()
                    self.file_cmd = ("stop",)
                continue
            if trigger == "fault" and tr.latched(cause):
                continue
            refusal = await tr.fire(trigger, cause)
            self.note(trigger, (cause or "") if refusal is None else str(refusal))
        # 4. entry actions, 5. control law and commands; a device error latches the fault now
        qdot = None
        try:
            if tr.state != self._state:
                await self._enter(tr.state, est)
            elif est is not None and self.mode.arm == "admittance" and (
                    m := current_mode(tr.state, self.ctx, self)) is not self.mode:
                apply_mode(self, m, est)              # dragging: the file went in or out
            if est is not None:
                qdot = await arm_command(self, est)
        except (DentibotError, OSError) as exc:
            qdot, cause = None, f"device_command: {type(exc).__name__}: {exc}"
            events.append(("fault", cause))
            await tr.fire("fault", cause)
            self.note("fault", cause)
            await self._enter(tr.state, est)
        if self._cycle_soon:
            self._cycle_soon()
        # 6. telemetry, every tick (inputs failed: the last estimate again, "inputs_invalid")
        self.ticks, self.qdot_cmd = k + 1, qdot
        if est is not None:
            self.last = est
        if self.sink is not None and self.last is not None:
            if est is None:
                events = [*events, ("inputs_invalid", None)]
            self.last_row = row = telemetry_row(self, k, self.last, qdot, events, lateness_s,
                                                time.perf_counter() - t_start)
            self.sink(row)
        if self.on_tick is not None:
            self.on_tick(self)

    async def _read_and_estimate(self, k: int):
        try:
            js, w, m, aux = await self.dev.read()
            strings = await self.dev.read_tracker()
        except DeviceFault as exc:
            return None, [Finding("device", str(exc))]
        self.ctx.pedal = bool(aux.pedal) if aux is not None else False
        if aux is not None:
            self.treatment.estop_active = aux.estop
        q, raw = np.asarray(js.q_deg, dtype=float), w.as_array()
        findings = self.supervisor.check_inputs(k, js, w, m, aux, raw, q)
        if any(f.kind.startswith("nonfinite") for f in findings):
            return None, findings
        est = self._estimate(q, raw, m)
        tooth = self.ctx.tooth and self.ctx.tooth.tick(strings, self.chain, self.ctx, est)
        findings += [tooth] if tooth else []
        if not findings:
            findings = self.supervisor.observe(self.file_cmd, m, est, self.ctx.depth_ref
                                               is not None and self.mode.arm == "admittance")
        if not findings and self.gravity is not None:
            turning = self.mode.file in ("forward", "align") and abs(m.velocity_rpm) > 5.0
            findings = self.supervisor.check_estimate(
                est, self.kin, self.chain[1], self.ctx.depth_ref, self.cfg.plan.working_length_mm,
                turning)
        return est, findings

    def _estimate(self, q: np.ndarray, raw: np.ndarray, m) -> Estimate:
        to_h = self._to_h[self._ref or "B"] if self.gravity is not None else None
        est, self.chain, self.r_0_6 = estimate(q, raw, m, self.admittance, self.gravity, to_h,
                                               self.cfg.handpiece, self.ctx.depth_ref)
        return est

    set_tool_tip = set_tool_tip

    async def _enter(self, state: str, est: Estimate | None) -> None:
        """Entry of ``state``: the mode's arm and file set-up, then the state's behaviour."""
        prev = self._state
        self._state = state
        mode = current_mode(state, self.ctx, self)
        if mode.arm == "stop":
            self.mode = mode
            await self.stop_devices()
            return
        apply_mode(self, mode, est)
        self.behaviours[state].enter(self.ctx, self, est, prev)
        self.file_cmd = await send_file_command(self.dev.motor, mode, self.cfg, self.file_cmd)

    def note(self, kind: str, detail: str) -> None:
        self.events_log.append((self.ticks, kind, detail))
        if self.event_sink is not None:
            self.event_sink(self.ticks, kind, detail)
        if kind == "fault":
            log.error("fault", tick=self.ticks, cause=detail)
        else:
            log.debug("event", tick=self.ticks, kind=kind, detail=detail)
