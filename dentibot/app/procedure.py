"""One procedure: its devices, its control task running one continuous loop from start to stop,
and the gate through which the protocol's steps, the operator and tests drive it.

Whoever drives a procedure (the protocol runner, the interactive session, a user's test, an
experiment, the selftest) does it the same way: commands and set-up go through the
:class:`~dentibot.runtime.gate.TickGate` (executed by the control task between two ticks), and
waits are for ticks of the running loop (:meth:`Procedure.run_for`). Time is one of two clocks
(docs/architecture.md, "Time"):

- real time (:class:`~dentibot.runtime.clock.RealTimeClock`): real devices or the wire
  simulators; the loop ticks at its period whoever waits;
- lock step (:class:`~dentibot.runtime.clock.LockStepClock`) on the built-in simulator, one
  world step per tick:

  - ``"lockstep"`` (default): held; ticks run only while a step waits for them (``drive``):
    a run's figures depend on its seed alone, never on the machine or the event loop;
  - ``"free"``: as fast as the machine allows, whoever waits;
  - ``"paced"``: at the speed of the real world (each tick waits for its deadline).
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Callable
from typing import Any

import structlog

from dentibot.app.simulated import Truth, World, WorldConfig, plan_config, sim_devices, \
    true_gravity_model
from dentibot.app.tracking import sim_tooth_config
from dentibot.control.wrench import GravityModel
from dentibot.runtime.clock import Clock, LockStepClock, RealTimeClock
from dentibot.runtime.config import RuntimeConfig
from dentibot.runtime.control_task import Runtime
from dentibot.runtime.estimate import Devices
from dentibot.runtime.gate import GateClosed, TickGate
from dentibot.sim.tracker_device import TrackerSimParams
from dentibot.states.treatment import Refusal

log = structlog.get_logger("dentibot.procedure")

#: The built-in simulator's time options (see the module docstring).
SIM_TIMES = ("lockstep", "free", "paced")
#: Longest time a retraction may take while it withdraws the file (procedure s): the
#: deepest canal (30 mm) at the slowest progress allowed below.
RETRACT_TIMEOUT_S = 150.0
#: A retraction that withdraws the file less than ``RETRACT_PROGRESS_MM`` in
#: ``RETRACT_STALL_S`` is stuck (assumption: the canal's drag can slow the -0.5 N retraction
#: from about 3 mm/s to under 1 mm/s; 0.2 mm/s is well below that).
RETRACT_PROGRESS_MM, RETRACT_STALL_S = 1.0, 5.0
#: Longest time the safe stop records the file and the arm coming to rest (procedure s).
REST_TIMEOUT_S = 1.0

RowSink = Callable[[dict], None]
EventSink = Callable[[int, str, str], None]


def _at_rest(rt: Runtime) -> bool:
    """The file still and no joint commanded to move in the last tick (none: at rest)."""
    e, qdot = rt.last, rt.qdot_cmd
    return e is not None and abs(e.motor_rpm) < 1.0 and (
        qdot is None or max(abs(float(x)) for x in qdot) == 0.0)


class Procedure:
    """One procedure's runtime, clock, gate and control loop (see the module docstring).

    Build it with :meth:`simulated` or :meth:`over`; the loop starts with the first command,
    call or wait (or :meth:`start`) and ends with :meth:`stop` (``async with`` stops it too).
    ``drive``: waits grant the ticks they wait for (a held lock-step clock); otherwise they
    only wait for ticks that run anyway or that someone else grants.
    """

    def __init__(self, runtime: Runtime, *, world: World | None = None,
                 drive: bool = False, rows: list[dict] | None = None) -> None:
        self.runtime = runtime
        self.clock: Clock = runtime.clock
        self.world = world
        #: every telemetry row, when built with ``keep_rows`` (tests)
        self.rows = rows
        self.gate = TickGate()
        self.gate.open(runtime)
        if isinstance(self.clock, LockStepClock):
            self.clock.serve = self.gate.run_actions
            self.gate.on_submit = self.clock.wake
        self.drive = drive and isinstance(self.clock, LockStepClock)
        #: why the control loop died (None while it runs or after a clean stop)
        self.error: str | None = None
        #: ``on_stopped(error)`` is called when the control loop ends
        self.on_stopped: Callable[[str | None], None] | None = None
        self._task: asyncio.Task | None = None

    # ------------------------------------------------------------------ building
    @classmethod
    def simulated(cls, world: World | WorldConfig | None = None,
                  config: RuntimeConfig | None = None, *, calibrated: bool = True,
                  time: str = "lockstep", drive: bool = True,
                  sink: RowSink | None = None, event_sink: EventSink | None = None,
                  keep_rows: bool = False, step_name: str = "",
                  devices: Callable[[World, Devices], Devices] | None = None,
                  tracker: TrackerSimParams | None = None,
                  hybrid: bool = False) -> Procedure:
        """The built-in simulator under a runtime. ``config`` defaults to one that agrees with
        the world (:func:`~dentibot.app.simulated.plan_config`); ``calibrated``: the load is
        known (the sensor's true offsets), else a load calibration must come first; ``time``
        one of :data:`SIM_TIMES`; ``devices(world, devices)`` may wrap the simulated devices
        (fault injection); ``tracker``: a simulated patient tracker of this geometry, and
        depth measured in the tooth's frame (unless ``config`` says otherwise); ``hybrid``:
        and its motion fed forward to the arm."""
        if time not in SIM_TIMES:
            raise ValueError(f"time {time!r}: one of {', '.join(SIM_TIMES)}")
        w = world if isinstance(world, World) else World(world)
        cfg = plan_config(w, config)
        dev = sim_devices(w, tracker)
        if tracker is not None and cfg.tooth is None:
            cfg = dataclasses.replace(cfg, tooth=sim_tooth_config(w, tracker, hybrid))
        if devices is not None:
            dev = devices(w, dev)
        clock = LockStepClock(w.step, cfg.period_s, paced=time == "paced",
                              held=time == "lockstep")
        rows: list[dict] | None = [] if keep_rows else None
        if rows is not None:
            sink = rows.append if sink is None else _both(rows.append, sink)
        rt = Runtime(dev, cfg, clock, gravity=true_gravity_model(w) if calibrated else None,
                     sink=sink, event_sink=event_sink, truth=Truth(w), step_name=step_name)
        return cls(rt, world=w, drive=drive and time == "lockstep", rows=rows)

    @classmethod
    def over(cls, devices, config: RuntimeConfig, *, clock: Clock | None = None,
             gravity: GravityModel | None = None, sink: RowSink | None = None,
             event_sink: EventSink | None = None) -> Procedure:
        """A procedure over open devices (anything with ``arm``, ``ft``, ``motor`` and ``aux``:
        what :func:`dentibot.io.devices.open_devices` yields, drivers of real hardware or of the
        wire simulators); ``clock`` defaults to real time at the configured period. Without
        ``gravity`` a load calibration must come first."""
        rt = Runtime(Devices(devices.arm, devices.ft, devices.motor, devices.aux,
                             getattr(devices, "tracker", None)), config,
                     clock or RealTimeClock(config.period_s), gravity=gravity, sink=sink,
                     event_sink=event_sink)
        return cls(rt)

    # ------------------------------------------------------------------ the loop
    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    @property
    def held(self) -> bool:
        """True for lock-step time that passes only by granted ticks."""
        return isinstance(self.clock, LockStepClock) and self.clock.held

    def start(self) -> None:
        """Start the control loop (once; a stopped procedure stays stopped)."""
        if self._task is None and self.gate.closed is None:
            self._task = asyncio.get_running_loop().create_task(
                self._loop(), name="dentibot-control")

    async def _loop(self) -> None:
        """The control loop: what was submitted before the start, then tick after tick until
        stopped; however it ends, the file and the arm are stopped and the gate closed."""
        rt = self.runtime
        why = "the procedure was stopped"
        try:
            await rt.prepare()
            await self.gate.run_actions()
            await rt.run(between=self.gate.between)
        except asyncio.CancelledError:
            why = "the control loop was cancelled"
            raise
        except Exception as exc:  # noqa: BLE001 - reported; devices stopped below
            why = self.error = f"the control task died: {type(exc).__name__}: {exc}"
            log.error("procedure.control_died", error=str(exc))
        finally:
            self.gate.close(why)
            await rt.stop_devices()
            for t in list(rt.unfinished_stops):   # a silent link's stop: given up here
                t.cancel()
            if self.on_stopped is not None:
                self.on_stopped(self.error)

    async def stop(self) -> None:
        """End the control loop after the current tick; the file and the arm are then told to
        stop (a procedure that has stopped leaves nothing moving). To withdraw the file
        first, :meth:`safe_stop`."""
        if self._task is None:
            self.gate.close("the procedure was stopped")
            return
        self.runtime.request_stop()
        if isinstance(self.clock, LockStepClock):
            self.clock.halt()
        if not self._task.done():
            await asyncio.wait([self._task])

    async def __aenter__(self) -> Procedure:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.stop()

    # ------------------------------------------------------------------ driving
    async def call(self, action: Callable[[], Any]) -> Any:
        """``action()`` between two ticks (awaited if it returns an awaitable); its result."""
        self.start()
        return await self.gate.submit(action)

    async def command(self, trigger: str) -> Refusal | None:
        """An operator command through the state machine, between two ticks."""
        rt = self.runtime
        return await self.call(lambda: rt.command(trigger))

    async def run_for(self, seconds: float | None = None, *, ticks: int | None = None,
                      until: Callable[[Runtime], bool] | None = None,
                      drive: bool | None = None) -> bool:
        """Return after ``ticks`` ticks (or ``seconds`` of procedure time) or the first tick
        where ``until(runtime)`` holds; True when it held. With ``drive`` (default: the
        procedure's) the ticks are granted to a held lock-step clock and it holds again in
        that very tick."""
        rt = self.runtime
        n = ticks if ticks is not None else (
            None if seconds is None else max(1, round(seconds / rt.ts)))
        drive = self.drive if drive is None else drive
        if drive and (n is None or not isinstance(self.clock, LockStepClock)):
            raise ValueError("a driven wait needs a lock-step clock and a number of ticks")
        self.start()
        clock = self.clock
        if drive:
            fut = self.gate.wait(until, n, on_done=clock.hold)
            clock.grant(n)
        else:
            fut = self.gate.wait(until, n)
        try:
            await fut
        except asyncio.CancelledError:
            if drive:
                clock.hold()
            raise
        return until is not None and bool(until(rt))

    def outcome(self, ok_reason: str = "") -> tuple[str, str]:
        """``(status, reason)`` of the procedure so far. A fracture is what the controller
        detected (from the motor's torque signature); on the built-in simulator the world's
        truth is added to the report (never to the controller), saying whether the controller
        saw it."""
        rt = self.runtime
        detected = next((c for c in rt.treatment.fault_causes
                         if c.startswith("fracture_suspected")), None)
        w = self.world
        if w is not None and w.fractured is not None:
            f = w.fractured
            seen = f"detected: {detected}" if detected else "not detected by the controller"
            return "fracture", (f"file fractured by {f.cause} at {f.t:.2f} s, "
                                f"{f.torque_mnm:.1f} mNm, depth {f.depth_mm:.2f} mm ({seen})")
        if detected is not None:
            return "fracture", detected
        if rt.state == "fault":
            return "fault", "; ".join(rt.treatment.fault_causes)
        return "ok", ok_reason

    async def estop(self, cause: str) -> None:
        """Software emergency stop between two ticks: file and arm stopped at once, then the
        latched fault."""
        rt = self.runtime
        await self.call(lambda: rt.estop(cause))

    async def safe_stop(self) -> None:
        """End the treatment, withdraw the file where possible (the machine's retraction,
        from any state in which the file is in the canal: treating, or a stop, drag or
        alignment that left it there, or a drag that may have taken it in before any depth
        reference), stop, and record the file and the arm coming to rest; the devices are
        stopped in any case. Never raises."""
        rt = self.runtime

        def end_treatment() -> None:
            rt.treatment.passes_left = 0

        try:
            await self.call(end_treatment)
            tr = rt.treatment
            in_canal = tr.in_state("treating") or tr.depth_known or tr.maybe_in
            if in_canal and rt.state not in ("treating.retracting", "fault"):
                await self.command("retract")
            why = await self.finish_retraction()
            if why is not None:
                log.warning("safe stop: %s", why)
            if rt.state != "fault":
                await self.command("stop")
            await self.run_for(REST_TIMEOUT_S, until=_at_rest)
        except GateClosed:
            pass
        except Exception as exc:  # noqa: BLE001 - the devices are stopped below regardless
            log.warning("safe stop: %s", exc)
        finally:
            await self._stop_now()

    async def finish_retraction(self, run_for=None) -> str | None:
        """Wait while the machine retracts, as long as the file comes out: at least
        :data:`RETRACT_PROGRESS_MM` every :data:`RETRACT_STALL_S`, for
        :data:`RETRACT_TIMEOUT_S` at most. None once it no longer retracts (the file out, or
        another state), else why it stopped waiting. ``run_for(seconds, until)``: how to wait
        (default :meth:`run_for`)."""
        rt = self.runtime
        wait = run_for or (lambda s, until: self.run_for(s, until=until))
        waited = 0.0

        def depth() -> float | None:
            return None if rt.last is None else rt.last.depth_mm

        while rt.state == "treating.retracting":
            d0 = depth()
            await wait(RETRACT_STALL_S, lambda r: r.state != "treating.retracting")
            waited += RETRACT_STALL_S
            if rt.state != "treating.retracting":
                return None
            d1 = depth()
            if d0 is not None and d1 is not None and d0 - d1 < RETRACT_PROGRESS_MM:
                return (f"retraction stalled: the file withdrew {d0 - d1:.2f} mm in "
                        f"{RETRACT_STALL_S:g} s, at {d1:.1f} mm")
            if waited >= RETRACT_TIMEOUT_S:
                return (f"retraction unfinished after {waited:g} s, the file at "
                        f"{'?' if d1 is None else f'{d1:.1f}'} mm")
        return None

    async def _stop_now(self) -> None:
        """File and arm stopped: between two ticks while the loop runs, else at once."""
        rt = self.runtime
        if self.running:
            try:
                await self.call(rt.stop_devices)
                return
            except GateClosed:
                pass
        await rt.stop_devices()


def _both(a: RowSink, b: RowSink) -> RowSink:
    def sink(row: dict) -> None:
        a(row)
        b(row)
    return sink
