"""The fixed-period control task (docs/architecture.md, "The tick").

Every period:

1. read the newest sample of each stream; the supervisor checks freshness, finite values and
   the emergency stop (a finding -> ``fault`` at once);
2. estimate: external wrench in {S} (offset and gravity removed, eq 4.18), moved to the active
   reference point in {H} (eq 4.26-4.31); file torque from the motor current (eq 5.4-5.5);
   file-tip depth along the canal;
3. detect events (patient moved / released, reversal needed / finished, working length,
   retracted, limits) and hand them to the state machine;
4. apply the entry actions of a state just entered (file commands, admittance preset and
   reference point, depth reference, calibration routine);
5. control law of the current state's mode: admittance step -> joint rates through the tool
   Jacobian -> limits -> MoveJointsVel; the file command;
6. one telemetry row; deadline accounting.

Events are detected before the commands of the same tick (as docs/architecture.md
orders them): a patient movement, a torque spike or an emergency stop seen in tick k is
acted on by the commands of tick k, not k + 1.
"""

from __future__ import annotations

import asyncio
import dataclasses
import gc
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import structlog

from dentibot.control.admittance import DRAGGING, SELF_ALIGNMENT, AdmittanceController
from dentibot.control.feedrate import FeedrateController, file_torque_estimate_mnm
from dentibot.control.kinematics import Meca500, euler_xyz_deg
from dentibot.control.tick import admittance_command, external_wrench_h, forward_chain
from dentibot.control.wrench import GravityModel, WrenchTransform
from dentibot.errors import DentibotError, DeviceFault
from dentibot.io.interfaces import Arm, AuxIO, ForceSensor, Handpiece
from dentibot.runtime.clock import Clock, DeadlineStats
from dentibot.runtime.config import RuntimeConfig
from dentibot.states.load_calibration import LoadCalibration, TcpRoutine
from dentibot.states.strategies import Decision, make_strategy
from dentibot.runtime.supervisor import Finding, Supervisor
from dentibot.states.modes import MODES, Mode
from dentibot.states.treatment import Refusal, Treatment

log = structlog.get_logger("dentibot.runtime")

PRESETS = {"dragging": DRAGGING, "self_alignment": SELF_ALIGNMENT}
_ZERO6 = np.zeros(6)
#: Events that are recorded but are not triggers of the state machine.
NOTES = frozenset({"tcp_point", "inputs_invalid", "file_stopped"})


@dataclass
class Devices:
    arm: Arm
    ft: ForceSensor
    motor: Handpiece
    aux: AuxIO | None = None


@dataclass
class Estimate:
    """What step 2 of the tick produced (also the live view's figures)."""

    q_deg: np.ndarray
    wrench_s: np.ndarray       # raw sensor reading (N, N*m)
    wrench_h: np.ndarray       # external wrench at the reference point, {H}
    force_norm_n: float        # ||{H} f|| (fig 5.6: forces and torques, N and N*m)
    file_torque_mnm: float
    motor_rpm: float
    motor_current_a: float
    motor_pos_deg: float
    tip_0: tuple
    axis_0: tuple
    depth_mm: float | None


class Runtime:
    """One procedure's control task, state machine and bookkeeping.

    ``truth`` (simulator only) returns extra telemetry fields known only to a simulation
    (phantom pose, true depth, completeness, fracture); the control never reads them.
    """

    def __init__(self, devices: Devices, config: RuntimeConfig, clock: Clock, *,
                 gravity: GravityModel | None = None, sink: Callable[[dict], None] | None = None,
                 truth: Callable[[], dict] | None = None, step_name: str = "") -> None:
        self.dev = devices
        self.cfg = config
        self.clock = clock
        self.ts = config.period_s
        tool = np.eye(4)
        tool[:3, :3] = self._R_6_H = np.reshape(config.tool.R_6_H, (3, 3))
        tool[:3, 3] = config.tool.tip_6_mm
        self.kin = Meca500(tool=tool)
        self.admittance = AdmittanceController(self.kin, SELF_ALIGNMENT, self.ts)
        self._speed_limits = [float(x) for x in self.kin.joint_speed_limits_deg_s]
        self.treatment = Treatment(passes_left=config.plan.passes - 1)
        self.gravity: GravityModel | None = None
        self._to_h: dict[str, WrenchTransform] = {}
        if gravity is not None:
            self.set_gravity(gravity)
        self.strategy = make_strategy(config.plan.strategy, config.plan.working_length_mm,
                                      self.ts)
        self.supervisor = Supervisor(config.thresholds.stale_periods, self.ts,
                                     config.thresholds.supervisor)
        self.stats = DeadlineStats(self.ts, deadlines=clock.realtime)
        self.sink = sink
        self.truth = truth
        self.step_name = step_name
        #: ``event_sink(tick, kind, detail)`` gets every event, command and fault as it happens.
        self.event_sink: Callable[[int, str, str], None] | None = None
        self.ticks = 0
        self.events_log: list[tuple[int, str, str]] = []   # (tick, kind, detail)
        self.reversals = 0
        self.patient_episodes = 0
        self.last: Estimate | None = None
        self.last_row: dict | None = None
        self._state = None
        self._mode: Mode = MODES["idle"]
        self._ref = None
        self._file_cmd = None
        self._depth_ref = None
        self._calib: LoadCalibration | None = None
        self._reversal_start = None
        self._release_ticks = 0
        self._decision = Decision(0.0, 0.0)
        self._decided = -1
        self._align_pd: FeedrateController | None = None
        self._pedal = self._pedal_prev = False
        self._tcp: TcpRoutine | None = None
        self._pending: list[tuple[str, str | None]] = []
        self._stop = asyncio.Event()

    # ------------------------------------------------------------------ configuration
    def set_gravity(self, gravity: GravityModel) -> None:
        """Use ``gravity`` (a load calibration result) for compensation from now on."""
        self.gravity = gravity
        t = self.cfg.tool
        R = np.reshape(t.R_6_H, (3, 3))
        common = {"mount_angle_deg": gravity.mount_angle_deg, "p_6_S_mm": t.sensor_origin_6_mm}
        self._to_h = {
            "A": WrenchTransform.for_tool(R, t.tip_6_mm, q_H_mm=t.grip_h_mm, **common),
            "B": WrenchTransform.for_tool(R, t.tip_6_mm, **common),
        }
        self.treatment.gravity_known = True

    @property
    def state(self) -> str:
        return self.treatment.state

    # ------------------------------------------------------------------ commands
    async def command(self, trigger: str) -> Refusal | None:
        """An operator command (pedal, terminal, protocol step): through the machine only."""
        refusal = await self.treatment.fire(trigger, "operator" if trigger == "fault" else None)
        self._note("command", trigger if refusal is None else str(refusal))
        return refusal

    async def estop(self, cause: str = "software emergency stop") -> None:
        """Software emergency stop: file and arm stopped now (not at the next tick), then
        the latched fault; only ``reset`` leaves it."""
        await _quietly(self.dev.motor.stop())
        await _quietly(self.dev.arm.stop())
        await self.treatment.fire("fault", cause)
        self._note("fault", cause)

    def request_stop(self) -> None:
        """Ask :meth:`run` to return after the current tick."""
        self._stop.set()

    # ------------------------------------------------------------------ loop
    async def run(self, until: Callable[[Runtime], bool] | None = None,
                  max_ticks: int | None = None) -> None:
        """Tick until ``until(self)`` is true, ``max_ticks`` ticks ran or ``request_stop``.

        In real time the cyclic garbage collector runs only in the slack after a tick (young
        generation every 50 ticks, older every 5000), never in the middle of one: a full
        collection triggered by allocation can take milliseconds (tens with the simulators in
        the same process). Objects alive at the start are frozen out of the collector's sight
        (``gc.freeze``, which collects nothing itself).
        """
        self._stop.clear()
        realtime = self.clock.realtime
        gc_was_enabled = gc.isenabled()
        if realtime:
            gc.freeze()      # cheap (no collection): today's objects leave the collector's view
            gc.disable()
        self.clock.start()
        lateness = 0.0
        n = 0
        try:
            while not self._stop.is_set():
                t0 = time.perf_counter()
                await self.tick(lateness)
                self.stats.add(lateness, time.perf_counter() - t0)
                n += 1
                if (max_ticks is not None and n >= max_ticks) or (
                        until is not None and until(self)):
                    break
                if realtime and n % 50 == 0:
                    gc.collect(1 if n % 5000 == 0 else 0)
                lateness = await self.clock.wait_next()
        finally:
            if realtime:
                gc.unfreeze()
                if gc_was_enabled:
                    gc.enable()
        self.stats.skipped = self.clock.skipped

    async def tick(self, lateness_s: float = 0.0) -> None:
        t_start = time.perf_counter()
        k = self.ticks
        tr = self.treatment
        events: list[tuple[str, str | None]] = self._pending
        self._pending = []
        # 1. read + supervise
        est, findings = await self._read_and_estimate(k)
        for f in findings:
            events.append(("fault", str(f)))
        # a command between ticks (operator, protocol) changed the state: its entry first
        if tr.state != self._state and not findings:
            await self._enter(tr.state, est)
        # 3. events from the estimates
        if est is not None and not findings:
            events.extend(self._detect(est))
        for trigger, cause in events:
            if trigger in NOTES:              # worth recording, not a transition
                self._note(trigger, cause or "")
                if trigger == "file_stopped":
                    await self.dev.motor.stop()
                    self._file_cmd = ("stop",)
                continue
            if trigger == "fault" and tr.state == "fault" and _kind(cause) in {
                    _kind(c) for c in tr.fault_causes}:
                continue                      # latched already, for this kind of cause
            refusal = await tr.fire(trigger, cause)
            self._note(trigger, (cause or "") if refusal is None else str(refusal))
        # 4. entry actions
        if tr.state != self._state:
            await self._enter(tr.state, est)
        # 5. control law and commands
        qdot = None
        if est is not None:
            qdot = await self._command(est)
        # 6. telemetry: every tick, also when the inputs failed (then the last valid estimate
        # is repeated and the row's events say "inputs_invalid")
        self.ticks = k + 1
        if est is not None:
            self.last = est
        if self.sink is not None and self.last is not None:
            if est is None:
                events = [*events, ("inputs_invalid", None)]
            row = self._row(k, self.last, qdot, events, lateness_s,
                            time.perf_counter() - t_start)
            self.last_row = row
            self.sink(row)

    # ------------------------------------------------------------------ step 1-2
    async def _read_and_estimate(self, k: int):
        d = self.dev
        try:
            js = await d.arm.read()
            w = await d.ft.read()
            m = await d.motor.read()
            aux = await d.aux.read() if d.aux is not None else None
            self._pedal = bool(aux.pedal) if aux is not None else False
        except DeviceFault as exc:
            return None, [Finding("device", str(exc))]
        if aux is not None:
            self.treatment.estop_active = aux.estop
        findings = self.supervisor.check_inputs(k, js, w, m, aux)
        if any(f.kind.startswith("nonfinite") for f in findings):
            return None, findings
        raw = w.as_array()
        q = np.asarray(js.q_deg, dtype=float)
        est = self._estimate(q, raw, m)
        if not findings and self.gravity is not None:
            turning = self._mode.file in ("forward", "align") and abs(m.velocity_rpm) > 5.0
            findings = self.supervisor.check_estimate(
                est, self.kin, self._kin[1], self._depth_ref, self.cfg.plan.working_length_mm,
                turning)
        return est, findings

    def _estimate(self, q: np.ndarray, raw: np.ndarray, m) -> Estimate:
        kin, self._R06 = forward_chain(self.admittance, q)
        self._kin = kin
        wrench_h = _ZERO6 if self.gravity is None else external_wrench_h(
            self.gravity, self._to_h[self._ref or "B"], raw, self._R06)
        hp = self.cfg.handpiece
        tau = file_torque_estimate_mnm(m.current_a, m.velocity_rpm, hp.efficiency,
                                       hp.friction_current_a)
        tip, axis = self.kin.tool_tip_axis(kin[1])
        depth = None
        if self._depth_ref is not None:
            o, a = self._depth_ref
            depth = ((tip[0] - o[0]) * a[0] + (tip[1] - o[1]) * a[1]
                     + (tip[2] - o[2]) * a[2])
        return Estimate(q, raw, wrench_h, float(np.linalg.norm(wrench_h)), tau,
                        m.velocity_rpm, m.current_a, m.position_deg, tip, axis, depth)

    # ------------------------------------------------------------------ step 3
    def _detect(self, est: Estimate) -> list[tuple[str, str | None]]:
        th = self.cfg.thresholds
        st = self.treatment.state
        ev: list[tuple[str, str | None]] = []
        tau = est.file_torque_mnm
        if st == "self_aligning" and est.depth_mm is not None and \
                est.depth_mm > self.cfg.plan.working_length_mm + th.align_depth_margin_mm:
            return [("fault", (f"depth_limit: depth {est.depth_mm:.2f} mm during alignment > "
                               f"working length {self.cfg.plan.working_length_mm} + "
                               f"{th.align_depth_margin_mm} mm"))]
        if st.startswith("treating.drilling"):
            if est.force_norm_n > th.patient_moved_n:
                self.patient_episodes += 1
                return [("patient_moved", (f"||f_H|| = {est.force_norm_n:.2f} N "
                                          f"> {th.patient_moved_n} N"))]
            if est.depth_mm is not None and \
                    est.depth_mm > self.cfg.plan.working_length_mm + th.depth_margin_mm:
                return [("depth_limit", (f"depth {est.depth_mm:.2f} mm > working length "
                                         f"{self.cfg.plan.working_length_mm} + "
                                         f"{th.depth_margin_mm} mm"))]
            if -est.wrench_h[2] > th.axial_force_limit_n:
                return [("force_limit", (f"axial force {-est.wrench_h[2]:.2f} N > "
                                        f"{th.axial_force_limit_n} N"))]
        if st == "treating.drilling.feeding":
            depth = est.depth_mm if est.depth_mm is not None else 0.0
            self._decision = dec = self.strategy.step(tau, depth)
            self._decided = self.ticks
            if tau > th.torque_limit_mnm and "reversal_needed" not in dec.events:
                ev.append(("reversal_needed", (f"file torque {tau:.1f} mNm > limit "
                                              f"{th.torque_limit_mnm:.1f} mNm")))
            for e in dec.events:
                ev.append((e, f"tau {tau:.1f} mNm, fz* {dec.fz_star_n:.3f} N, depth {depth:.2f} mm"))
        elif st == "treating.drilling.reversing":
            hp = self.cfg.handpiece
            start_pos, start_tick = self._reversal_start
            turned = start_pos - est.motor_pos_deg
            if turned >= hp.reversal_deg - 1.0 and abs(est.motor_rpm) < 2.0:
                ev.append(("reversal_finished", f"turned back {turned:.1f} deg"))
            elif (self.ticks - start_tick) * self.ts > hp.reversal_timeout_s:
                ev.append(("fault", (f"reversal: turned {turned:.1f} of {hp.reversal_deg} deg "
                                    f"in {hp.reversal_timeout_s} s (file bound?)")))
        elif st == "treating.patient_moved":
            if est.force_norm_n < th.patient_release_n:
                self._release_ticks += 1
                self._persist_ticks = 0
                if self._release_ticks * self.ts >= th.patient_release_s:
                    ev.append(("patient_released", f"||f_H|| = {est.force_norm_n:.2f} N"))
            else:
                self._release_ticks = 0
                self._persist_ticks += 1
                if self._persist_ticks * self.ts > th.patient_persist_s:
                    ev.append(("fault", (f"force {est.force_norm_n:.2f} N persists "
                                         f"{th.patient_persist_s} s while the arm follows "
                                         f"(limit {th.patient_release_n} N): sensor drift or "
                                         "a collision, not a patient movement")))
        elif st == "self_aligning" and self._align_pd is not None:
            out = self._align_pd.step(tau)          # Table 6.4 config C: no reversal here
            self._decision = Decision(out.fz_n, out.fz_star_n)
            self._decided = self.ticks
        elif st == "treating.retracting":
            if est.depth_mm is not None and est.depth_mm <= self.cfg.plan.retract_to_mm:
                ev.append(("retracted", f"depth {est.depth_mm:.2f} mm"))
        elif st == "calibrating.tcp":
            ev.extend(self._tcp_step())
        elif st == "calibrating.load" and self._calib is not None:
            target = self._calib.step(est.q_deg, est.wrench_s, self._R06)
            self._calib_target = target
            if self._calib.result is not None:
                self.set_gravity(self._calib.result.model)
                ev.append(("calibration_done", f"load: {self._calib.result.mass_kg * 1e3:.1f} g"))
            elif self._calib.error is not None:
                ev.append(("fault", f"load calibration: {self._calib.error}"))
        if (tau > self.cfg.thresholds.torque_limit_mnm and self._mode.file in ("forward", "align")
                and st != "treating.drilling.feeding" and self._file_cmd != ("stop",)):
            if st == "treating.retracting":
                # a file bound on the way out (screw-in, taper lock): stop turning it and go
                # on withdrawing it straight, rather than leave it stopped in the canal
                ev.append(("file_stopped", (f"file torque {tau:.1f} mNm > limit "
                                            f"{th.torque_limit_mnm:.1f} mNm while retracting: "
                                            "withdrawn without turning")))
            else:
                ev.append(("fault", (f"file torque {tau:.1f} mNm > limit "
                                    f"{th.torque_limit_mnm:.1f} mNm in {st}")))
        return ev

    def _tcp_step(self) -> list[tuple[str, str | None]]:
        """Calibrating the TCP: each pedal press records the flange pose (the operator holds
        the file tip on one fixed point); enough poses -> eq 3.21-3.23 -> the new tool tip."""
        pressed = self._pedal and not self._pedal_prev
        self._pedal_prev = self._pedal
        if not pressed:
            return []
        cols, o6 = self._kin[1][-1]
        result = self._tcp.add(np.array(cols).T, np.array(o6))
        if result is None:
            return [("tcp_point", f"pose {len(self._tcp.rotations)} recorded")]
        if isinstance(result, str):
            if len(self._tcp.rotations) >= self._tcp.max_points:
                return [("fault", f"TCP calibration: {result}")]
            return [("tcp_point", f"pose {len(self._tcp.rotations)}: {result}")]
        self.set_tool_tip(result.p_6_H_mm)
        return [("calibration_done", (f"TCP {np.round(result.p_6_H_mm, 3).tolist()} mm, "
                                      f"residual max {result.residual_max_mm:.3f} mm"))]

    def set_tool_tip(self, tip_6_mm) -> None:
        """Use a new tool tip 6p_H (TCP calibration) from now on: kinematics, the {S}->{H}
        transforms and the configuration all follow."""
        tool = dataclasses.replace(self.cfg.tool, tip_6_mm=tuple(float(x) for x in tip_6_mm))
        self.cfg = dataclasses.replace(self.cfg, tool=tool)
        T = np.eye(4)
        T[:3, :3] = self._R_6_H
        T[:3, 3] = tool.tip_6_mm
        self.kin.set_tool(T)
        if self.gravity is not None:
            self.set_gravity(self.gravity)

    # ------------------------------------------------------------------ step 4
    async def _enter(self, state: str, est: Estimate | None) -> None:
        prev = self._state
        self._state = state
        mode = self._mode = MODES[state]
        d = self.dev
        if mode.arm == "stop":
            await _quietly(d.arm.stop())
            await _quietly(d.motor.stop())
            self._file_cmd = ("stop",)
            return
        if state == "self_aligning":
            fr = self.cfg.plan.align_feedrate
            self._align_pd = FeedrateController(fr, self.ts) if fr is not None else None
            self._decision = Decision(self.cfg.plan.align_fz_n, self.cfg.plan.align_fz_n)
        if mode.admittance is not None:
            params = PRESETS[mode.admittance]
            if state == "self_aligning" and self.cfg.plan.align_params is not None:
                params = self.cfg.plan.align_params
            ref_h = self.cfg.tool.grip_h_mm if mode.ref == "A" else None
            if (params, mode.ref) != (self.admittance.params, self._ref):
                self.admittance.set_params(params, ref_h)
                self._ref = mode.ref
                if est is not None:   # the reference point changed: redo step 2 with it
                    est2 = self._estimate(est.q_deg, est.wrench_s, _MotorView(est))
                    est.wrench_h, est.force_norm_n = est2.wrench_h, est2.force_norm_n
        if state in ("idle", "dragging"):
            self._depth_ref = None
        if state in ("self_aligning", "treating.drilling.feeding") and self._depth_ref is None \
                and est is not None:
            gap = self.cfg.plan.orifice_gap_mm
            a = est.axis_0
            self._depth_ref = (tuple(est.tip_0[i] + gap * a[i] for i in range(3)), a)
            est.depth_mm = -gap
        if state == "treating.drilling.feeding":
            came_back = prev in ("treating.drilling.reversing",)
            if came_back:
                self.strategy.reversed()
            self.strategy.start_pass(est.depth_mm if est and est.depth_mm is not None else 0.0)
            self._decision = Decision(0.0, 0.0)
        if state == "treating.drilling.reversing":
            self.reversals += 1
            self._reversal_start = (est.motor_pos_deg if est else 0.0, self.ticks)
        if state == "treating.patient_moved":
            self._release_ticks = 0
            self._persist_ticks = 0
        if state == "calibrating.tcp":
            self._tcp = TcpRoutine(self.cfg.tcp_points)
            self._pedal_prev = self._pedal
        if state == "calibrating.load" and est is not None:
            self._calib = LoadCalibration(est.q_deg, self.ts, limits_deg=self.kin.joint_limits_deg)
            self._calib_target = None
        await self._file(mode)

    async def _file(self, mode: Mode) -> None:
        hp = self.cfg.handpiece
        kind = mode.file
        if kind == "forward":
            cmd = ("vel", hp.drilling_rpm)
        elif kind == "align":
            cmd = ("vel", self.cfg.plan.align_rpm)
        elif kind == "reverse":
            await self.dev.motor.move_relative(-hp.reversal_deg)
            self._file_cmd = ("reverse",)
            return
        else:
            cmd = ("stop",)
        if cmd == self._file_cmd:
            return
        self._file_cmd = cmd
        if cmd[0] == "vel" and cmd[1] != 0.0:
            await self.dev.motor.set_velocity(cmd[1])
        else:
            await self.dev.motor.stop()

    # ------------------------------------------------------------------ step 5
    async def _command(self, est: Estimate):
        mode = self._mode
        arm = self.dev.arm
        if mode.arm == "stop":
            return None
        if mode.arm == "script":
            target = getattr(self, "_calib_target", None)
            if target is not None:
                await arm.move_joints(target)
            return None
        if mode.arm == "hold":
            await arm.move_joints_vel(_ZERO6)
            return _ZERO6
        cmd = admittance_command(self.admittance, est.q_deg, est.wrench_h, self._fz(mode),
                                 self._kin)
        bad = self.supervisor.check_command(cmd.qdot_deg_s, cmd.twist, self._speed_limits)
        if bad:
            self._pending.extend(("fault", str(f)) for f in bad)
            await arm.move_joints_vel(_ZERO6)
            return _ZERO6
        try:
            await arm.move_joints_vel(cmd.qdot_deg_s)
        except DentibotError as exc:
            self._pending.append(("fault", f"arm refused the command: {exc}"))
        return cmd.qdot_deg_s

    def _fz(self, mode: Mode) -> float:
        feed = mode.feed
        if feed == "strategy":
            return self._decision.fz_n
        if feed == "align":
            return self._decision.fz_n if self._align_pd is not None else self.cfg.plan.align_fz_n
        if feed == "retract":
            return -self.cfg.plan.retract_fz_n
        return 0.0

    # ------------------------------------------------------------------ step 6
    def _note(self, kind: str, detail: str) -> None:
        self.events_log.append((self.ticks, kind, detail))
        if self.event_sink is not None:
            self.event_sink(self.ticks, kind, detail)
        if kind == "fault":
            log.error("fault", tick=self.ticks, cause=detail)
        else:
            log.debug("event", tick=self.ticks, kind=kind, detail=detail)

    def _row(self, k, est: Estimate, qdot, events, lateness_s, compute_s) -> dict:
        mode = self._mode
        fz = self._fz(mode) if mode.arm == "admittance" else 0.0
        euler = euler_xyz_deg((self._R06 @ self._R_6_H).tolist())
        row = {
            "t": k * self.ts, "tick": k, "step": self.step_name, "state": self.treatment.state,
            "q_deg": est.q_deg.tolist(),
            "qdot_cmd_deg_s": [0.0] * 6 if qdot is None else [float(x) for x in qdot],
            "tool_pose": [*est.tip_0, *euler],
            "phantom_pose": None,
            "wrench_s": est.wrench_s.tolist(), "wrench_h": est.wrench_h.tolist(),
            "f_d": [0.0, 0.0, fz, 0.0, 0.0, 0.0],
            # the PD output that decided this tick (also when it just triggered a reversal)
            "fz_star_n": self._decision.fz_star_n if self._decided == k else fz,
            "fz_n": fz,
            "file_torque_mnm": est.file_torque_mnm, "motor_current_a": est.motor_current_a,
            "motor_rpm": est.motor_rpm,
            "depth_mm": est.depth_mm, "true_depth_mm": None, "working_length_mm": self.cfg.plan.working_length_mm,
            "completeness": None, "patient_moved": self.treatment.state ==
            "treating.patient_moved", "reversals": self.reversals, "fractured": False,
            "events": [e for e, _ in events],
            "lateness_us": max(lateness_s, 0.0) * 1e6, "compute_us": compute_s * 1e6,
            # lock-step time has no deadlines: nothing can be late
            "overrun": self.clock.realtime and lateness_s + compute_s > self.ts,
        }
        if self.truth is not None:
            row.update(self.truth())
        return row


class _MotorView:
    """The motor figures of an Estimate, shaped like a MotorState for re-estimation."""

    def __init__(self, est: Estimate) -> None:
        self.current_a = est.motor_current_a
        self.velocity_rpm = est.motor_rpm
        self.position_deg = est.motor_pos_deg


def _kind(cause: str | None) -> str:
    """The finding kind of a fault cause ("stale_ft: ..." -> "stale_ft")."""
    return (cause or "").split(":", 1)[0]


async def _quietly(coro) -> None:
    """Send a stop command; a device that is itself the fault must not hide the others."""
    try:
        await coro
    except Exception as exc:  # noqa: BLE001 - the stop of the other devices must go on
        log.warning("stop command failed", error=str(exc))

