"""The interactive session without its screen: devices, the running control task, commands.

:class:`SessionController` owns one :class:`~dentibot.app.procedure.Procedure`: ``connect``
builds it over the built-in simulator or over the real drivers
(:func:`~dentibot.io.devices.open_devices`, as ``dentibot run --devices`` does) and starts its
control task, which then ticks until ``quit``. Every operator command goes through the state
machine (``Runtime.command``), executed between two ticks by the procedure's gate: no command
bypasses the machine, the limits or the supervisor, and a refused command comes back with the
machine's reason (which state, what it needs first).

Timed steps (``step drag duration_s=2``, ``drill`` to the working length, rounds) are the
protocol runner's own steps (:class:`~dentibot.app.steps.StepExecutor`), run as a
background *activity* against the running control task; the operator can pause, reverse,
retract, stop or e-stop meanwhile. The live panel reads :meth:`SessionController.snapshot`
(never blocks the control task).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import structlog

from dentibot.app.device_bounds import stale_bound_conflict
from dentibot.app.procedure import Procedure
from dentibot.app.runner import runtime_config, world_config
from dentibot.app.steps import StepExecutor, align_plan
from dentibot.app.tracker_calibration import START_STATES as CALIBRATION_START_STATES
from dentibot.app.tracking import sim_tracking, tracked_config
from dentibot.errors import DentibotError
from dentibot.io.devices import DevicesConfig, load_devices_config, open_devices
from dentibot.io.tasks import in_thread
from dentibot.protocol.schema import Protocol
from dentibot.runtime.control_task import Runtime
from dentibot.runtime.gate import GateClosed
from dentibot.session.commands import (
    COMMANDS,
    Command,
    CommandError,
    help_text,
    parse,
    validate_step,
)
from dentibot.states.treatment import Refusal
from dentibot.telemetry.recorder_process import Recorder, open_recorder
from dentibot.telemetry.schema import TelemetryError

log = structlog.get_logger("dentibot.session")

#: The session's clocks on the built-in simulator and the procedure's time for each: the
#: stepped clock is held lock-step time that only :meth:`SessionController.advance` drives.
SIM_TIME = {"realtime": "paced", "lockstep": "free", "stepped": "lockstep"}
CLOCKS = tuple(SIM_TIME)

#: Operator triggers and the command that sends each (``status`` lists what the state takes).
OPERATOR_TRIGGERS = {
    "calibrate_load": "calibrate load", "calibrate_tcp": "calibrate tcp", "drag": "drag",
    "align": "align", "drill": "drill", "pause": "pause", "resume": "resume",
    "reverse": "reverse", "retract": "retract", "stop": "stop", "fault": "estop",
    "reset": "reset",
}
#: Commands accepted while a safe stop or a connection is in progress.
_WHILE_BUSY = {"estop", "quit", "help", "status"}
ESTOP_CAUSE = "software emergency stop"


def default_protocol() -> Protocol:
    """The session's world and limits when no protocol is given (the schema's defaults)."""
    return Protocol.model_validate({"name": "session", "steps": [{"calibrate_load": {}}]})


@dataclass
class SessionOptions:
    """What ``dentibot session`` was started with.

    - ``protocol``: world (simulator), limits and the steps ``step N`` runs; default
      :func:`default_protocol`.
    - ``devices``: real drivers (hardware or ``dentibot sim serve``); None: the built-in
      simulator.
    - ``clock`` (built-in simulator): ``realtime`` (default), ``lockstep`` (as fast as
      possible) or ``stepped`` (time advances only by :meth:`SessionController.advance`).
    - ``calibrated`` (built-in simulator): start with the simulated load known, as if a load
      calibration had been done (default False: ``calibrate load`` first, as at the bench).
    """

    protocol: Protocol | None = None
    devices: DevicesConfig | None = None
    clock: str = "realtime"
    calibrated: bool = False
    record_dir: Path = Path("runs")

    def __post_init__(self) -> None:
        if self.clock not in CLOCKS:
            from dentibot.errors import ConfigError
            raise ConfigError("session.clock", self.clock, f"one of {', '.join(CLOCKS)}")


@dataclass(frozen=True)
class Reply:
    """What a command did: ``ok``, ``refused`` (with the reason), ``error`` or ``info``."""

    kind: str
    text: str


@dataclass
class PanelData:
    """The live panel's figures (units in the names)."""

    connected: bool
    source: str
    state: str
    fault_causes: list[str] = field(default_factory=list)
    activity: str | None = None
    busy: str | None = None
    t_s: float = 0.0
    depth_mm: float | None = None
    working_length_mm: float = 0.0
    true_depth_mm: float | None = None
    completeness: float | None = None
    #: where depth is measured: "tooth" (patient tracker), "base" (the robot's frame)
    depth_frame: str = "base"
    #: the tracked tooth's position in the base frame (mm), None without it
    tooth_mm: list[float] | None = None
    wrench_h: list[float] | None = None
    file_torque_mnm: float | None = None
    torque_limit_mnm: float = 0.0
    tau_d_mnm: float | None = None
    motor_rpm: float | None = None
    patient_moved: bool = False
    patient_episodes: int = 0
    reversals: int = 0
    realtime: bool = True
    period_s: float = 0.002
    rate_hz: float | None = None
    timing: dict = field(default_factory=dict)
    recording: str | None = None
    recording_rows: int = 0
    calibrated: bool = False
    control_error: str | None = None


class StepRefused(DentibotError):
    """The state machine refused a step's command (the step ends, nothing faults)."""

    def __init__(self, refusal: Refusal) -> None:
        self.refusal = refusal
        super().__init__(str(refusal))


class _LiveSteps(StepExecutor):
    """The protocol's steps on the session's running procedure. A refused command ends the
    step with the refusal (the runner, unattended, faults instead)."""

    def __init__(self, session: SessionController) -> None:
        super().__init__(session.procedure)
        #: the outcome of the step's first command (None: taken, else the Refusal)
        self.first: asyncio.Future = asyncio.get_running_loop().create_future()

    async def command(self, trigger: str, already: str | None = None) -> None:
        refusal = None
        if already is None or self.rt.state != already:
            refusal = await self.proc.command(trigger)
        if not self.first.done():
            self.first.set_result(refusal)
        if refusal is not None:
            raise StepRefused(refusal)


class SessionController:
    """One interactive procedure (see the module docstring)."""

    def __init__(self, options: SessionOptions | None = None) -> None:
        self.opt = options or SessionOptions()
        self.protocol = self.opt.protocol or default_protocol()
        self.procedure: Procedure | None = None
        self.runtime: Runtime | None = None
        self.world = None
        self.devices_cfg = self.opt.devices
        self.recorder: Recorder | None = None
        self.recording_error: str | None = None
        self.control_error: str | None = None
        self.closed = False
        #: (kind, text) for the screen: events of the control task, steps that ended ...
        self.messages: collections.deque[tuple[str, str]] = collections.deque(maxlen=1000)
        self._stack: contextlib.AsyncExitStack | None = None
        self._activity: asyncio.Task | None = None
        self._activity_name: str | None = None
        self._activity_end = ""
        self._busy: str | None = None
        self._closing: asyncio.Task | None = None
        self._steps_named = 0
        self._rate = (0.0, 0)                  # (wall time, ticks) of the last snapshot
        self._rate_hz: float | None = None

    # ------------------------------------------------------------------ properties
    @property
    def connected(self) -> bool:
        return self.procedure is not None and self.procedure.running

    @property
    def state(self) -> str:
        return self.runtime.state if self.runtime is not None else "not connected"

    @property
    def source(self) -> str:
        if self.devices_cfg is not None:
            a = self.devices_cfg.arm
            return f"devices (arm {a.host}:{a.control_port}, real time)"
        kind = {"realtime": "real time", "lockstep": "lock-step, as fast as possible",
                "stepped": "lock-step, stepped"}[self.opt.clock]
        return f"built-in simulator ({kind})"

    def _post(self, kind: str, text: str) -> None:
        self.messages.append((kind, text))

    async def _name_step(self, what: str) -> None:
        """Telemetry rows from the next tick belong to session step ``"<n>:<what>"`` (the
        summary and ``dentibot report`` group by it, as for a protocol's steps)."""
        self._steps_named += 1
        rt, name = self.runtime, f"{self._steps_named}:{what.replace(' ', '_')}"
        await self.procedure.call(lambda: setattr(rt, "step_name", name))

    # ------------------------------------------------------------------ commands
    async def execute(self, line: str) -> list[Reply]:
        """Run one command line; the replies say what happened (or why not)."""
        try:
            cmd = parse(line)
        except CommandError as exc:
            return [Reply("error", str(exc))]
        if cmd is None:
            return []
        spec = COMMANDS[cmd.name]
        if self.closed and cmd.name not in ("help", "status", "quit"):
            return [Reply("refused", f"'{cmd.name}' refused: the session is closed")]
        if self._busy is not None and cmd.name not in _WHILE_BUSY:
            return [Reply("refused", f"'{cmd.name}' refused: {self._busy} is in progress "
                                     f"(estop and quit still work)")]
        if spec.needs_connection and not self.connected:
            why = "not connected" if self.control_error is None else self.control_error
            return [Reply("refused", f"'{cmd.name}' refused: {why}; it needs 'connect' "
                                     "first")]
        try:
            return await getattr(self, f"_cmd_{cmd.name}")(cmd)
        except CommandError as exc:
            return [Reply("error", str(exc))]
        except GateClosed as exc:
            return [Reply("error", f"'{cmd.name}' not done: control task stopped ({exc})")]
        except DentibotError as exc:
            return [Reply("error", f"'{cmd.name}' failed: {exc}")]

    async def _fire(self, trigger: str, what: str | None = None) -> Reply:
        rt = self.runtime
        refusal = await self.procedure.command(trigger)
        if refusal is not None:
            return Reply("refused", _refusal_text(refusal, what))
        return Reply("ok", f"{what or trigger}: state {rt.state}")

    async def _cmd_help(self, cmd: Command) -> list[Reply]:
        return [Reply("info", help_text(cmd.args[0] if cmd.args else None))]

    async def _cmd_connect(self, cmd: Command) -> list[Reply]:
        if self.connected:
            return [Reply("info", f"already connected: {self.source}")]
        args = [a for a in cmd.args if a != "resume-arm"]
        if args:
            self.devices_cfg = load_devices_config(args[0])
        self._busy = "connecting"
        try:
            await self.connect(resume_arm="resume-arm" in cmd.args)
        except (DentibotError, OSError) as exc:
            return [Reply("error", f"connect failed: {exc}")]
        finally:
            self._busy = None
        nxt = "calibrate load" if not self.runtime.treatment.gravity_known else "drag or align"
        replies = [Reply("ok", f"connected: {self.source}; state {self.state}; next: {nxt}")]
        if self.devices_cfg is not None and (
                conflict := stale_bound_conflict(self.protocol, self.devices_cfg)):
            replies.append(Reply("info", conflict))
        return replies

    async def _cmd_calibrate(self, cmd: Command) -> list[Reply]:
        trigger = f"calibrate_{cmd.sub}"
        reply = await self._fire(trigger, f"calibrate {cmd.sub}")
        if reply.kind != "ok":
            return [reply]
        await self._end_activity(f"calibrate {cmd.sub}")
        await self._name_step(trigger)
        if cmd.sub == "load":
            how = "the arm visits the calibration poses, then back to idle"
        else:
            press = "'pedal'" if self.world is not None else "the pedal"
            how = (f"hold the file tip on one fixed point and press {press} in each of at "
                   f"least {self.runtime.cfg.tcp_points} orientations (the arm "
                   "follows the hand); back to idle when the tip is solved, 'stop' to cancel")
        return [Reply("ok", f"{reply.text}: {how}")]

    async def _cmd_pedal(self, cmd: Command) -> list[Reply]:
        world = self.world
        if world is None:
            return [Reply("refused", "'pedal' refused: with devices the foot pedal is the real "
                                     "one (aux input); press it")]
        world.pedal = True                     # read by the next tick, released 3 ticks later

        def release() -> None:
            world.pedal = False

        self.procedure.gate.call_after(3, release)
        return [Reply("ok", f"pedal pressed (state {self.state})")]

    async def _cmd_drag(self, cmd: Command) -> list[Reply]:
        if cmd.params or cmd.args:
            raise CommandError("'drag' takes no parameters; on the simulator 'step drag "
                               "duration_s=2 hand_force_n=0,0,-1' scripts the hand")
        reply = await self._fire("drag")
        if reply.kind == "ok":
            await self._end_activity("drag")
            await self._name_step("drag")
        return [reply]

    async def _cmd_align(self, cmd: Command) -> list[Reply]:
        spec = validate_step("align", cmd.params, self.protocol)
        rt = self.runtime

        async def act():
            if await rt.treatment.may_trigger("align"):
                rt.configure(plan=align_plan(rt.cfg.plan, spec))
            return await rt.command("align")

        refusal = await self.procedure.call(act)
        if refusal is not None:
            return [Reply("refused", str(refusal))]
        await self._end_activity("align")
        await self._name_step("align")
        p = rt.cfg.plan
        return [Reply("ok", f"align: state {rt.state}; fz {p.align_fz_n} N, file "
                            f"{p.align_rpm} rpm" + (f", Table 6.4 config {spec.config}"
                                                   if spec.config else ""))]

    async def _cmd_drill(self, cmd: Command) -> list[Reply]:
        return await self._start_step("drill", validate_step("drill", cmd.params, self.protocol))

    async def _cmd_step(self, cmd: Command) -> list[Reply]:
        if not cmd.args:
            raise CommandError("usage: step KIND [key=value ...] | step N")
        what = cmd.args[0]
        if what.isdigit():
            steps = self.protocol.steps
            n = int(what)
            if not 1 <= n <= len(steps):
                raise CommandError(f"step {n}: the protocol '{self.protocol.name}' has "
                                   f"{len(steps)} step(s)")
            if cmd.params or len(cmd.args) > 1:
                raise CommandError("'step N' takes no parameters (the protocol's are used)")
            return await self._start_step(steps[n - 1].kind, steps[n - 1].spec)
        if len(cmd.args) > 1:
            raise CommandError(f"unexpected {' '.join(cmd.args[1:])!r}: parameters are "
                               "key=value")
        return await self._start_step(what, validate_step(what, cmd.params, self.protocol))

    async def _start_step(self, kind: str, spec) -> list[Reply]:
        """Run the protocol runner's ``kind`` step as the activity; first ask the machine
        whether the state takes it (so a refused step changes nothing: not the running
        strategy, not the plan, not the running step)."""
        trigger = kind                  # the protocol's step kinds are the triggers' names
        rt = self.runtime
        name = f"step {kind}" if kind != "drill" else "drill"
        # the tracker's calibration is a routine between ticks, not a state of the machine:
        # it needs the arm still and no treatment under way
        routine = kind == "calibrate_tracker"
        if routine and rt.state not in CALIBRATION_START_STATES:
            return [Reply("refused", f"{name}: needs state "
                                     f"{' or '.join(CALIBRATION_START_STATES)}, not {rt.state}")]
        if not routine and not (kind == "drag" and rt.state == "dragging") and not (
                kind == "align" and rt.state == "self_aligning"):
            async def check():
                if await rt.treatment.may_trigger(trigger):
                    return None
                return await rt.command(trigger)     # refused: the machine says why

            refusal = await self.procedure.call(check)
            if refusal is not None:
                return [Reply("refused", str(refusal))]
        await self._end_activity(name)
        steps = _LiveSteps(self)
        if routine:
            steps.first.set_result(None)             # no command: started once running
        await self._name_step(kind)
        self._activity_name = name
        self._activity_end = ""
        self._activity = task = asyncio.create_task(
            self._run_activity(name, steps.step(kind, spec), steps),
            name=f"dentibot-session-{kind}")
        await asyncio.wait([steps.first, task], return_when=asyncio.FIRST_COMPLETED)
        if steps.first.done() and steps.first.result() is not None:
            return [Reply("refused", f"{name}: {steps.first.result()}")]
        return [Reply("ok", f"{name}: started, state {rt.state} "
                            f"({_describe_spec(kind, spec, rt)})")]

    async def _run_activity(self, name: str, coro, steps: _LiveSteps) -> None:
        try:
            await coro
        except asyncio.CancelledError:
            self._post("info", f"{name}: ended ({self._activity_end or 'cancelled'}); "
                               f"state {self.state}")
            return
        except StepRefused as exc:
            if not (steps.first.done() and exc.refusal is steps.first.result()):
                # (the refusal of the first command is the command's reply)
                self._post("refused", f"{name}: {exc}")
        except GateClosed as exc:
            self._post("error", f"{name}: control task stopped ({exc})")
        except Exception as exc:  # noqa: BLE001 - shown to the operator, the session goes on
            self._post("error", f"{name}: {type(exc).__name__}: {exc}")
        else:
            rt = self.runtime
            extra = ""
            if rt.state == "fault":
                extra = "; fault: " + "; ".join(rt.treatment.fault_causes)
            elif rt.last_row is not None and rt.last_row.get("depth_mm") is not None:
                extra = f"; depth {rt.last_row['depth_mm']:.2f} mm"
            self._post("ok", f"{name}: finished in state {rt.state}{extra}")
        finally:
            self._activity_name = None

    async def _end_activity(self, why: str) -> None:
        t = self._activity
        if t is None or t.done():
            return
        self._activity_end = f"superseded by '{why}'"
        t.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await t

    async def _cmd_pause(self, cmd: Command) -> list[Reply]:
        return [await self._fire("pause")]

    async def _cmd_resume(self, cmd: Command) -> list[Reply]:
        return [await self._fire("resume")]

    async def _cmd_reverse(self, cmd: Command) -> list[Reply]:
        return [await self._fire("reverse")]

    async def _cmd_retract(self, cmd: Command) -> list[Reply]:
        rt = self.runtime

        async def act():
            refusal = await rt.command("retract")
            if refusal is None:
                rt.treatment.passes_left = 0     # the operator ends the treatment
            return refusal

        refusal = await self.procedure.call(act)
        if refusal is not None:
            return [Reply("refused", str(refusal))]
        await self._end_activity("retract")
        return [Reply("ok", f"retract: state {rt.state}; withdrawing to "
                            f"{rt.cfg.plan.retract_to_mm} mm, then done")]

    async def _cmd_stop(self, cmd: Command) -> list[Reply]:
        await self._end_activity("stop")
        return [await self._fire("stop")]

    async def _cmd_estop(self, cmd: Command) -> list[Reply]:
        return [await self.estop()]

    async def estop(self) -> Reply:
        """Software emergency stop between two ticks: ``Runtime.estop`` (file and arm stopped
        at once, then the latched fault with the cause named) when the runtime has it, else
        the machine's ``fault`` (the runtime stops both on entering it, in the next tick)."""
        if not self.connected:
            return Reply("info", "estop: not connected, nothing moves")
        rt = self.runtime
        await self.procedure.estop(ESTOP_CAUSE)
        await self._end_activity("estop")
        return Reply("ok", f"EMERGENCY STOP: state {rt.state}; arm and file stopped; "
                           "'reset' to leave fault")

    async def _cmd_reset(self, cmd: Command) -> list[Reply]:
        return [await self._fire("reset")]

    async def _cmd_status(self, cmd: Command) -> list[Reply]:
        return [Reply("info", self.status_text())]

    async def _cmd_record(self, cmd: Command) -> list[Reply]:
        if cmd.sub == "start":
            path = Path(cmd.args[0]) if cmd.args else None
            return [await self.record_start(path)]
        return [await self.record_stop()]

    async def _cmd_quit(self, cmd: Command) -> list[Reply]:
        return [await self.shutdown()]

    # ------------------------------------------------------------------ connect / loop
    async def connect(self, resume_arm: bool = False) -> None:
        """Open the devices, build the procedure, start its control task (``resume_arm``: an
        arm found paused is resumed, on the operator's word)."""
        p = self.protocol
        if self._stack is not None:            # a previous connection whose control task died
            await self._stack.aclose()
            self._stack = None
        if self.devices_cfg is None:
            proc = Procedure.simulated(
                world_config(p), runtime_config(p), calibrated=self.opt.calibrated,
                **sim_tracking(p),
                time=SIM_TIME[self.opt.clock], drive=False, sink=self._row,
                event_sink=self._event)
        else:
            cfg = tracked_config(p, runtime_config(p), self.devices_cfg)   # before connecting
            stack = contextlib.AsyncExitStack()
            try:
                d = await stack.enter_async_context(open_devices(self.devices_cfg,
                                                                 resume_arm=resume_arm))
            except BaseException:
                await stack.aclose()
                raise
            self._stack = stack
            proc = Procedure.over(d, cfg, sink=self._row, event_sink=self._event)
        proc.on_stopped = self._control_stopped
        self.procedure, self.world, self.runtime = proc, proc.world, proc.runtime
        self.control_error = None
        self._rate = (time.perf_counter(), 0)
        proc.start()
        log.info("session.connected", source=self.source)

    def _control_stopped(self, error: str | None) -> None:
        if error is not None:
            self.control_error = error
            self._post("error", error + "; file and arm stopped")

    async def advance(self, seconds: float | None = None, *, ticks: int | None = None,
                      until=None) -> None:
        """Stepped clock only: let ``seconds`` (or ``ticks``) of simulated time pass, or
        until ``until(runtime)`` (at most ``seconds``), and return when they have."""
        if self.opt.clock != "stepped" or self.procedure is None:
            raise DentibotError("advance() needs the stepped clock (SessionOptions(clock="
                                "'stepped'))")
        await self.procedure.run_for(seconds, ticks=ticks, until=until, drive=True)

    # ------------------------------------------------------------------ sinks
    def _row(self, row: dict) -> None:
        rec = self.recorder
        if rec is not None:
            try:
                rec.record(row)
            except TelemetryError as exc:      # a recording never stops silently
                self.recorder = None
                self.recording_error = str(exc)
                self._post("error", f"recording stopped: {exc}")

    def _event(self, tick: int, kind: str, detail: str) -> None:
        rt = self.runtime
        if kind != "command":
            self._post("event" if kind != "fault" else "error",
                       f"t {tick * rt.ts:8.3f} s  {kind}" + (f": {detail}" if detail else ""))
        rec = self.recorder
        if rec is not None:
            try:
                rec.event(kind, detail, t=tick * rt.ts, tick=tick)
            except TelemetryError as exc:
                self.recorder = None
                self.recording_error = str(exc)
                self._post("error", f"recording stopped: {exc}")

    # ------------------------------------------------------------------ recording
    async def record_start(self, path: Path | None = None) -> Reply:
        if self.recorder is not None:
            return Reply("info", f"already recording to {self.recorder.path}")
        if path is None:
            path = self.opt.record_dir / f"session-{time.strftime('%Y%m%d-%H%M%S')}.mcap"
        p = self.protocol
        meta = {"protocol": p.name, "seed": p.seed, "rate_hz": p.control.rate_hz,
                "session": True,
                "devices": ({"arm": "sim", "ft": "sim", "handpiece": "sim", "aux": "sim"}
                            if self.devices_cfg is None else
                            {"arm": "meca500", "ft": "netft", "handpiece": "epos4",
                             "aux": "modbus" if self.devices_cfg.aux else "none"}),
                "file_strength_mnm": p.file.torsional_strength_mnm}
        rt = self.runtime
        if rt is not None:
            # the rows' procedure time t is already running: the wall clock at t = 0, so that
            # each message's log time (start + t) is when its tick ran
            meta["start_wall_ns"] = time.time_ns() - round(rt.ticks * rt.ts * 1e9)
            th = rt.cfg.thresholds
            meta.update(torque_limit_mnm=th.torque_limit_mnm, drive_limit_mnm=th.drive_limit_mnm)

        def create():
            path.parent.mkdir(parents=True, exist_ok=True)
            return open_recorder(path, meta, validate=False)

        try:
            self.recorder = await in_thread(create, "dentibot-session-record-start")
        except (DentibotError, OSError) as exc:
            return Reply("error", f"record start: {exc}")
        self.recording_error = None
        return Reply("ok", f"recording to {path}")

    async def record_stop(self, status: str | None = None, reason: str = "") -> Reply:
        rec = self.recorder
        if rec is None:
            return Reply("info", "not recording")
        self.recorder = None                   # the control task stops feeding it first
        if status is None:
            status, reason = self._end_status(reason or "recording stopped by the operator")
        try:
            await in_thread(lambda: rec.close(status, reason), "dentibot-session-record-stop")
        except DentibotError as exc:
            return Reply("error", f"record stop: {exc}")
        return Reply("ok", f"recording closed: {rec.path} ({rec.rows_queued} ticks; "
                           f"dentibot report {rec.path})")

    def _end_status(self, reason: str) -> tuple[str, str]:
        if self.procedure is None:
            return "ok", reason
        return self.procedure.outcome(reason)

    # ------------------------------------------------------------------ stopping
    async def toggle_pause(self) -> list[Reply]:
        """The space key: pause when treating, resume when paused."""
        if self.runtime is not None and self.runtime.state == "treating.paused":
            return await self.execute("resume")
        return await self.execute("pause")

    async def safe_stop(self) -> Reply:
        """Esc: end the step, withdraw the file if it is in the canal, then stop (idle)."""
        if not self.connected:
            return Reply("info", "stop safely: not connected, nothing moves")
        if self._busy is not None:
            return Reply("refused", f"stop safely refused: {self._busy} is in progress")
        self._busy = "a safe stop"
        try:
            await self._end_activity("stop safely")
            await self.procedure.safe_stop()
        finally:
            self._busy = None
        return Reply("ok", f"stopped safely: state {self.state}")

    async def shutdown(self) -> Reply:
        """Quit: stop safely if moving, stop the control task, close recording and devices."""
        if self._closing is None:
            self._closing = asyncio.ensure_future(self._shutdown())
        return await asyncio.shield(self._closing)

    async def _shutdown(self) -> Reply:
        parts = []
        proc = self.procedure
        if proc is not None:
            rt = proc.runtime
            if proc.held:
                proc.clock.release()          # the safe stop needs its ticks
            self._busy = "quitting"
            await self._end_activity("quit")
            moving = rt.state not in ("idle", "done", "fault")
            await proc.safe_stop()
            if moving and proc.error is None:
                parts.append(f"stopped safely (state {rt.state})")
            await proc.stop()
        if self.recorder is not None:
            parts.append((await self.record_stop(reason="session ended")).text)
        if self._stack is not None:
            await self._stack.aclose()
            self._stack = None
            parts.append("devices closed")
        self.closed = True
        self._busy = None
        log.info("session.closed")
        return Reply("ok", "; ".join(["bye", *parts]))

    # ------------------------------------------------------------------ views
    def status_text(self) -> str:
        if self.runtime is None:
            return f"not connected ({self.source} on 'connect')"
        rt = self.runtime
        tr = rt.treatment
        takes = [OPERATOR_TRIGGERS[t] for t in tr.allowed() if t in OPERATOR_TRIGGERS]
        st = rt.stats.as_dict()
        lines = [
            f"state {rt.state}; takes: {', '.join(takes) or 'nothing'}",
            f"load calibration: {'done' if tr.gravity_known else 'needed (calibrate load)'}",
            (f"source: {self.source}; control task "
             f"{'running' if self.connected else (self.control_error or 'stopped')}"),
            f"step: {self._activity_name or 'none'}",
            (f"loop: {st['ticks']} ticks, lateness p50 <= {st['lateness_us_p50']:.0f} us, "
             f"p99 <= {st['lateness_us_p99']:.0f} us, max {st['lateness_us_max']:.0f} us, "
             f"overruns {st['overruns']}, skipped {rt.clock.skipped}, compute mean "
             f"{st['compute_us_mean']:.0f} us"),
            f"recording: {self.recorder.path if self.recorder else 'off'}"
            + (f" (last error: {self.recording_error})" if self.recording_error else ""),
        ]
        if tr.fault_causes:
            lines.insert(1, "fault: " + "; ".join(tr.fault_causes))
        return "\n".join(lines)

    def snapshot(self) -> PanelData:
        """The panel's figures now (cheap: reads the last row and the counters)."""
        if self.runtime is None:
            return PanelData(False, self.source, "not connected",
                             working_length_mm=self.protocol.phantom.working_length_mm,
                             torque_limit_mnm=self.protocol.limits.torque_limit_mnm,
                             busy=self._busy)
        rt = self.runtime
        row = rt.last_row or {}
        now = time.perf_counter()
        t0, k0 = self._rate
        if now - t0 >= 0.5:                   # ticks per wall second over >= 0.5 s
            self._rate_hz = (rt.ticks - k0) / (now - t0)
            self._rate = (now, rt.ticks)
        strat = rt.ctx.strategy.p
        wh = row.get("wrench_h")
        return PanelData(
            connected=self.connected, source=self.source, state=rt.state,
            fault_causes=list(rt.treatment.fault_causes), activity=self._activity_name,
            busy=self._busy, t_s=rt.ticks * rt.ts,
            depth_mm=row.get("depth_mm"), working_length_mm=rt.cfg.plan.working_length_mm,
            true_depth_mm=row.get("true_depth_mm"), completeness=row.get("completeness"),
            depth_frame="tooth" if rt.ctx.tooth is not None else "base",
            tooth_mm=None if row.get("tooth_pose") is None else list(row["tooth_pose"][:3]),
            wrench_h=[float(x) for x in wh] if wh is not None else None,
            file_torque_mnm=row.get("file_torque_mnm"),
            torque_limit_mnm=rt.cfg.thresholds.torque_limit_mnm,
            tau_d_mnm=strat.feedrate.tau_d_mnm if strat.name in ("automated", "feedrate")
            else None,
            motor_rpm=row.get("motor_rpm"),
            patient_moved=rt.state == "treating.patient_moved",
            patient_episodes=rt.ctx.patient_episodes, reversals=rt.ctx.reversals,
            realtime=rt.clock.realtime, period_s=rt.ts, rate_hz=self._rate_hz,
            timing={**rt.stats.as_dict(), "skipped": rt.clock.skipped},
            recording=str(self.recorder.path) if self.recorder is not None else None,
            recording_rows=self.recorder.rows_queued if self.recorder is not None else 0,
            calibrated=rt.treatment.gravity_known, control_error=self.control_error)


def _refusal_text(refusal: Refusal, what: str | None) -> str:
    text = str(refusal)
    if what and what != refusal.trigger:
        text = text.replace(f"'{refusal.trigger}'", f"'{what}'", 1)
    return text


def _describe_spec(kind: str, spec, rt) -> str:
    if kind == "drill":
        rounds = (f"rounds {[r.duration_s for r in spec.rounds]} s" if spec.rounds
                  else f"one pass to {rt.cfg.plan.working_length_mm} mm")
        return (f"strategy {spec.strategy}, tau_d {spec.tau_d_mnm} mNm, {spec.rpm} rpm, "
                f"{rounds}")
    data = spec.model_dump()
    return ", ".join(f"{k} {v}" for k, v in data.items()) or "no parameters"


__all__ = ["CLOCKS", "ESTOP_CAUSE", "PanelData", "Reply", "SessionController",
           "SessionOptions", "StepRefused", "default_protocol"]
