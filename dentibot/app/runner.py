"""Run a validated protocol end to end: on the built-in simulator in lock-step time (default),
or on devices from a configuration (wire simulators or hardware) in real time.

Each step (:mod:`dentibot.app.steps`) drives the runtime through operator commands only
(no step bypasses the state machine, the limits or the supervisor). Every tick goes to the MCAP recorder and to the live
summary; both see the same rows, so ``dentibot report`` on the file prints the same summary.
Cancelling the run (Ctrl-C) stops it safely: file stopped, file withdrawn from the canal where
possible, arm stopped; the recording and the summary are still written (status "aborted").
"""

from __future__ import annotations

import asyncio
import signal
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import structlog

from dentibot.app.device_bounds import stale_bound_conflict
from dentibot.app.drill_loop import CHUNK, DrillLoop
from dentibot.app.procedure import Procedure
from dentibot.app.steps import Aborted, StepExecutor
from dentibot.app.tracking import sim_tracking, tracked_config
from dentibot.control.filebeam import FileBeam
from dentibot.errors import ConfigError
from dentibot.io.devices import DevicesConfig, open_devices
from dentibot.io.tasks import in_thread
from dentibot.protocol.loader import ProtocolFileError
from dentibot.protocol.schema import LIMIT_SHARE_OF_STRENGTH, WORLDS, Protocol, SimulatorSpec
from dentibot.runtime.config import RuntimeConfig, Thresholds, ToolGeometry, TreatmentPlan
from dentibot.runtime.control_task import Runtime
from dentibot.runtime.tool import tool_matrix
from dentibot.sim.arm import ArmParams
from dentibot.sim.bench_physics import BENCH
from dentibot.sim.canal import CanalParams, material_params
from dentibot.sim.ftsensor import FTSensorParams
from dentibot.sim.nitifile import NiTiFile
from dentibot.sim.world import WorldConfig
from dentibot.telemetry.blocks import WIDTH, TickBlock
from dentibot.telemetry.foxglove import FoxgloveView
from dentibot.telemetry.live import LiveView
from dentibot.telemetry.recorder_process import (
    Recorder,
    RecorderProcess,
    Wire,
    open_recorder,
    prestart_recorder_process,
)
from dentibot.telemetry.schema import TelemetryError
from dentibot.telemetry.summary import RunSummary, SummaryAccumulator

log = structlog.get_logger("dentibot.protocol")

#: A canal whose lumen already has the target preparation's shape.
PRESHAPED = {"initial_apical_mm": CanalParams.target_apical_mm,
             "initial_taper": CanalParams.target_taper}
EXIT_CODES = {"ok": 0, "fault": 3, "fracture": 4, "aborted": 130}
#: The signals that stop a run safely (file stopped and withdrawn, arm stopped, recording
#: finished), and the reason each gives.
SIGNALS = {signal.SIGINT: "stopped by the operator (Ctrl-C)",
           signal.SIGTERM: "terminated (SIGTERM)"}


def simulator_physics(spec: SimulatorSpec, canal: CanalParams) -> tuple[ArmParams, CanalParams]:
    """The arm, and ``canal`` with the walls' drag, that a protocol's ``simulator`` section
    asks for (ideal or fitted to the bench)."""
    if spec.canal_drag == "bench":
        canal = BENCH.canal_drag(canal)
    return (BENCH.arm() if spec.arm == "bench" else ArmParams()), canal


def served_world(world: str, seed: int = 0, motion: str = "static") -> WorldConfig:
    """A world without a protocol (the wire simulators'): the default phantom and file, with
    the physics (arm, canal drag) of the protocols' ``world`` of that name (:data:`WORLDS`)."""
    arm, canal = simulator_physics(SimulatorSpec(**WORLDS[world].get("simulator", {})),
                                   CanalParams())
    return WorldConfig(seed=seed, motion=motion, arm=arm, canal=canal)


def world_config(p: Protocol) -> WorldConfig:
    ph = p.phantom
    curve = {}
    if ph.curve is not None:
        curve = {"curve_start_mm": ph.curve.start_mm, "curve_radius_mm": ph.curve.radius_mm,
                 "curve_angle_deg": ph.curve.angle_deg}
    tool = np.eye(4)
    tool[:3, 3] = p.tool.tip_mm
    canal = CanalParams(working_length_mm=ph.working_length_mm, tilt_deg=ph.tilt_deg,
                        **curve, **(PRESHAPED if ph.preshaped else {}),
                        **material_params(ph.material.name, **ph.material.overrides()))
    arm, canal = simulator_physics(p.simulator, canal)
    return WorldConfig(
        seed=p.seed, ts=1.0 / p.control.rate_hz, tool=tool, arm=arm,
        sensor=FTSensorParams(offset_mm=p.tool.sensor_offset_mm),
        file=NiTiFile(size=p.file.size, taper=p.file.taper, length_mm=float(p.file.length_mm),
                      torsional_strength_mnm=p.file.torsional_strength_mnm),
        canal=canal, orifice_gap_mm=ph.orifice_gap_mm, motion=p.patient.motion)


def runtime_config(p: Protocol) -> RuntimeConfig:
    lim = p.limits
    return RuntimeConfig(
        period_s=1.0 / p.control.rate_hz,
        tool=ToolGeometry(tip_6_mm=p.tool.tip_mm,
                          sensor_origin_6_mm=(0.0, 0.0, p.tool.sensor_offset_mm),
                          grip_h_mm=p.tool.grip_mm),
        thresholds=Thresholds(file_strength_mnm=p.file.torsional_strength_mnm,
                              patient_moved_n=lim.patient_moved_n,
                              patient_release_n=min(1.0, 0.66 * lim.patient_moved_n),
                              torque_limit_mnm=lim.torque_limit_mnm,
                              axial_force_limit_n=lim.axial_force_limit_n,
                              stale_periods=lim.stale_periods.model_dump()),
        plan=TreatmentPlan(working_length_mm=p.phantom.working_length_mm,
                           orifice_gap_mm=p.phantom.orifice_gap_mm,
                           lateral_free_ref_mm=p.control.lateral_free_ref_mm,
                           axial_lag_s=(None if p.control.axial_lag_ms is None
                                        else p.control.axial_lag_ms / 1e3)),
        file=FileBeam(size=p.file.size, taper=p.file.taper, length_mm=float(p.file.length_mm)),
        cpus=p.control.cpus)


def recording_path(p: Protocol, override: str | Path | None = None) -> Path | None:
    """Where the run records: ``override`` (``--out``), the protocol's ``recording.path``, or
    by default the first free name of ``runs/<name>-<seed>.mcap``, ``runs/<name>-<seed>-2.mcap``
    ... (a default never replaces an earlier run's recording)."""
    if override is not None:
        return Path(override)
    if not p.recording.enabled:
        return None
    if p.recording.path:
        return Path(p.recording.path)
    path, n = Path(f"runs/{p.name}-{p.seed}.mcap"), 1
    while path.exists():
        n += 1
        path = Path(f"runs/{p.name}-{p.seed}-{n}.mcap")
    return path


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


@dataclass
class RunResult:
    summary: RunSummary
    recording: Path | None
    #: the exit code of a run ended by a signal other than Ctrl-C (128 + its number)
    signal_exit: int | None = None

    @property
    def exit_code(self) -> int:
        if self.summary.status == "aborted" and self.signal_exit is not None:
            return self.signal_exit
        return EXIT_CODES.get(self.summary.status, 1)


def _close_unused(sink) -> None:
    """A recorder or live view opened after its run was cancelled: finished, empty."""
    sink.close("aborted", "cancelled before the first tick")


class ProtocolRunner:
    """Build the procedure of ``protocol`` (on the built-in simulator, or over ``devices``) and
    run its steps.

    ``progress(figures)`` is called every ``progress_every`` ticks with the live key figures
    (step, state, t, depth, working length, file torque and its limit, force). ``tap(row)``
    sees every telemetry row; with ``live_summary=False`` the rows feed only the tap and the
    recording, not the live summary (the summary then carries the status and its reason).
    ``on_tick(runner)`` is called at the end of every tick; when nothing else needs the rows
    (no recording, live view, live summary, tap or progress) none is built, and an ``on_tick``
    with a ``ticks`` method that takes ticks in bulk lets the simulator's feeding, reversing
    and retracting ticks run compiled, many per call (:mod:`dentibot.app.drill_loop`; the
    same outcome; ``compiled_ticks=False``: tick by tick). Without ``on_tick`` or ``tap`` (a
    caller's hook may read the world as each tick ends) they run compiled too, their rows
    handed to the summary, the recorder, the live view and the progress in blocks
    (:class:`~dentibot.telemetry.blocks.TickBlock`): the same rows, the same recording.
    ``limit_share``: the largest share of the file's strength the protocol's hard torque limit
    may be (90 %; a study of strategies without the runtime's net on the built-in simulator may
    go up to 1). ``live``: a port on 127.0.0.1 where the run's channels are served live over the
    Foxglove WebSocket protocol (0: a free port).
    """

    def __init__(self, protocol: Protocol, *, recording: str | Path | None = None,
                 progress: Callable[[dict], None] | None = None,
                 progress_every: int = 250, overwrite: bool = False,
                 no_record: bool = False, devices: DevicesConfig | None = None,
                 tap: Callable[[dict], None] | None = None,
                 on_tick: Callable[[ProtocolRunner], None] | None = None,
                 compiled_ticks: bool = True,
                 live_summary: bool = True,
                 limit_share: float = LIMIT_SHARE_OF_STRENGTH,
                 live: int | None = None, resume_arm: bool = False) -> None:
        if not 0.0 < limit_share <= (1.0 if devices is None else LIMIT_SHARE_OF_STRENGTH):
            raise ConfigError("limit_share", limit_share,
                              f"0 < share <= {LIMIT_SHARE_OF_STRENGTH} of the file's strength "
                              "(up to 1 only on the built-in simulator)")
        problems = protocol.cross_checks(limit_share)
        if problems:
            raise ProtocolFileError("<protocol>", [(None, ".".join(map(str, loc)), text)
                                                   for loc, text in problems])
        self.p = protocol
        self.progress = progress
        self.progress_every = progress_every
        self.path = None if no_record else recording_path(protocol, recording)
        if self.path is not None and self.path.exists() and not overwrite:
            raise ConfigError("recording.path", str(self.path),
                              "a new file: it exists, and a recording is never replaced "
                              "silently (choose another path, or --force to replace it)")
        self.summary: RunSummary | None = None
        self.acc = SummaryAccumulator(rate_hz=protocol.control.rate_hz)
        self._tap = tap
        self._on_tick = on_tick
        self._compiled_ticks = compiled_ticks
        self._live_summary = live_summary
        calibrate = any(s.kind == "calibrate_load" for s in protocol.steps)
        self.devices = devices
        self.resume_arm = resume_arm
        self.procedure: Procedure | None = None
        if devices is None:
            self.procedure = Procedure.simulated(
                world_config(protocol), runtime_config(protocol), calibrated=not calibrate,
                sink=self._row, event_sink=self._event, **sim_tracking(protocol))
        else:
            self._cfg = tracked_config(protocol, runtime_config(protocol), devices)
            conflict = stale_bound_conflict(protocol, devices)
            if conflict:
                log.warning(conflict, protocol=protocol.name)
        if devices is not None and not calibrate:
            raise ConfigError("steps", [s.kind for s in protocol.steps],
                              "a calibrate_load step (real devices need the load identified "
                              "before any force control)")
        self.recorder = None
        self.live: LiveView | None = None
        self._live_port = live
        self._overwrite = overwrite
        self._abort_reason = ""
        #: the run has ended: a real-time control task still ticking while the recording is
        #: finished (off the loop) delivers nothing more, so that the file, the live view and
        #: the summary end at the same tick
        self._ended = False

    @property
    def rt(self) -> Runtime | None:
        return None if self.procedure is None else self.procedure.runtime

    @property
    def world(self):
        """The simulated world (None over devices)."""
        return None if self.procedure is None else self.procedure.world

    # ---------------------------------------------------------------- sinks
    def _row(self, row: dict) -> None:
        if self._ended:
            return
        if self._live_summary:
            self.acc.add(row)
        if self.recorder is not None:
            self.recorder.record(row)
        if self.live is not None:
            self.live.record(row)
        if self._tap is not None:
            self._tap(row)
        if self.progress is not None and row["tick"] % self.progress_every == 0:
            self._progress(row)

    def _block(self, block: TickBlock) -> None:
        """A block of rows (the simulator's compiled drilling ticks): the same as
        :meth:`_row` of each, the summary and the recorder taking the block whole (a run with
        a tap has no blocks: its ticks stay in the control task)."""
        self._block_read(block, self.recorder)

    def _block_read(self, block: TickBlock, recorder: Recorder | None = None) -> None:
        """:meth:`_block` with the recorder given (without it: the compiled ticks sent the
        rows to the recorder themselves)."""
        if self._ended:
            return
        if self._live_summary:
            self.acc.add_block(block)
        if recorder is not None:
            recorder.record_block(block)
        if self.live is not None:
            self.live.record_block(block)
        if self.progress is not None:
            every, k0 = self.progress_every, block.k0
            for k in range(k0 + -k0 % every, k0 + len(block), every):
                self._progress(block.row(k - k0))

    def _progress(self, row: dict) -> None:
        self.progress({
            "step": row["step"], "state": row["state"], "t": row["t"],
            "depth_mm": row["depth_mm"], "working_length_mm": row["working_length_mm"],
            "file_torque_mnm": row["file_torque_mnm"],
            "torque_limit_mnm": self.rt.cfg.thresholds.torque_limit_mnm,
            "force_n": float(np.linalg.norm(row["wrench_h"][:3])),
            "completeness": row.get("completeness"),
        })

    def _event(self, tick: int, kind: str, detail: str) -> None:
        if self._ended:
            return
        t = tick * self.rt.ts
        self.acc.add_event(kind, detail, t=t, tick=tick)
        if self.recorder is not None:
            self.recorder.event(kind, detail, t=t, tick=tick)
        if self.live is not None:
            self.live.event(kind, detail, t=t, tick=tick)

    # ---------------------------------------------------------------- run
    def abort(self, reason: str = "stopped by the operator (Ctrl-C)") -> None:
        """Stop the procedure safely after the current tick (signal handlers, UIs): the
        running step ends, the file is withdrawn, the recording and summary are written."""
        self._abort_reason = reason

    async def run(self, handle_sigint: bool = False) -> RunResult:
        """Run the steps. With ``handle_sigint``, Ctrl-C (SIGINT) and SIGTERM call
        :meth:`abort` (a safe stop that still writes the recording and the summary) instead of
        ending the process; the exit code then says which (130, 143)."""
        if not handle_sigint:
            return await self._run_devices()
        loop = asyncio.get_running_loop()
        for sig, why in SIGNALS.items():
            loop.add_signal_handler(sig, self.abort, why)
        try:
            result = await self._run_devices()
        finally:
            for sig in SIGNALS:
                loop.remove_signal_handler(sig)
        if self._abort_reason == SIGNALS[signal.SIGTERM]:
            result.signal_exit = 128 + signal.SIGTERM
        return result

    async def _run_devices(self) -> RunResult:
        if self.path is not None:        # before any device is due a message: see its doc
            prestart_recorder_process()
        if self.devices is None:
            async with self.procedure:
                return await self._run()
        async with open_devices(self.devices, resume_arm=self.resume_arm) as d:
            self.procedure = Procedure.over(d, self._cfg, sink=self._row,
                                            event_sink=self._event)
            async with self.procedure:
                return await self._run()

    async def _run(self) -> RunResult:
        p = self.p
        drills = [s.spec for s in p.steps if s.kind == "drill"]
        proc, rt = self.procedure, self.procedure.runtime
        th = rt.cfg.thresholds
        meta = {
            "protocol": p.name, "seed": p.seed, "rate_hz": p.control.rate_hz,
            "devices": ({"arm": "sim", "ft": "sim", "handpiece": "sim", "aux": "sim"}
                        if self.devices is None else
                        {"arm": "meca500", "ft": "netft", "handpiece": "epos4",
                         "aux": "modbus" if self.devices.aux else "none"}),
            "file_strength_mnm": p.file.torsional_strength_mnm,
            # what is enforced: the runtime's limit, and the drive's current limit's torque
            "torque_limit_mnm": th.torque_limit_mnm, "drive_limit_mnm": th.drive_limit_mnm,
            # where depth is measured: "tooth" (patient tracker) or "base" (the thesis's way)
            "depth_frame": "tooth" if rt.ctx.tooth is not None else "base",
            **({"tau_d_mnm": drills[0].tau_d_mnm} if drills else {})}
        if drills and rt.ctx.tooth is None:
            log.warning("depth in the robot's base frame (no patient tracker): the working "
                        "length is not protected against the patient moving along the canal",
                        protocol=p.name)
        tool = rt.cfg.tool
        view = FoxgloveView(tool_6_h=tool_matrix(np.reshape(tool.R_6_H, (3, 3)), tool.tip_6_mm),
                            file_length_mm=float(p.file.length_mm))
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # in a thread: the recorder's process and journal take tens of ms, and the
            # drive already watches this loop's heartbeat (30 ms)
            path, overwrite = self.path, self._overwrite
            self.recorder = await in_thread(
                lambda: open_recorder(path, meta, overwrite=overwrite, validate=False,
                                      view=view),    # rows checked in tests
                "dentibot-recorder-open", orphan=_close_unused)
            meta = self.recorder.metadata
        if self._live_port is not None:
            port = self._live_port                   # its server's start, likewise
            self.live = await in_thread(lambda: LiveView(meta, port=port, view=view),
                                        "dentibot-live-open", orphan=_close_unused)
        if self._on_tick is not None:
            rt.on_tick = lambda _rt: self._on_tick(self)
        compiled = proc.world is not None and proc.drive and self._compiled_ticks
        if not (self._live_summary or self.recorder or self.live or self._tap or self.progress):
            rt.sink = None                      # nobody reads rows: none is built
            bulk = getattr(self._on_tick, "ticks", None)
            if bulk is not None and compiled:
                # drilling ticks compiled, many per call (the reader takes them in bulk)
                rt.on_ticks = lambda out, n, k0, state: bulk(self, out, n, k0, state)
                rt.fused = DrillLoop(proc.world, proc.gate, proc.clock,
                                     every=getattr(self._on_tick, "every", None))
        elif self._on_tick is None and self._tap is None and compiled:
            # drilling ticks compiled, their rows handed over in blocks; a recorder's block
            # is at most half its budget of ticks not yet in its file, as its writer flushes
            rt.on_block = self._block
            rt.fused = DrillLoop(proc.world, proc.gate, proc.clock, block_ticks=(
                self.recorder.budget // 2 if self.recorder is not None else CHUNK))
            if isinstance(self.recorder, RecorderProcess):
                # the compiled ticks send their blocks to the recorder's process themselves
                rt.block_wire = Wire(self.recorder, WIDTH, CHUNK)
                rt.on_block_read = self._block_read
        steps = StepExecutor(proc, aborted=lambda: bool(self._abort_reason))
        try:
            for i, step in enumerate(p.steps):
                name = f"{i + 1}:{step.kind}"
                await proc.call(lambda name=name: setattr(rt, "step_name", name))
                await steps.step(step.kind, step.spec)
                if rt.state == "fault":
                    break
            if proc.error is not None:
                raise RuntimeError(proc.error)
            status, reason = proc.outcome()
        except Aborted:
            await proc.safe_stop()
            return RunResult(await self._close("aborted", self._abort_reason), self.path)
        except asyncio.CancelledError:
            await proc.safe_stop()
            await self._close("aborted", self._abort_reason or "cancelled by the operator")
            raise
        except Exception as exc:  # noqa: BLE001 - a fault of the run, not of its input
            # (a device error the control task could not turn into a fault, the control task
            # dying, the recording failing): stopped safely, reported as the run's fault
            await proc.safe_stop()
            why = proc.error or f"{type(exc).__name__}: {exc}"
            return RunResult(await self._close("fault", why), self.path)
        except BaseException as exc:
            await proc.safe_stop()
            await self._close("fault", f"{type(exc).__name__}: {exc}")
            raise
        return RunResult(await self._close(status, reason), self.path)

    async def _close(self, status: str, reason: str) -> RunSummary:
        """Finish the live view and the recording (in threads: their writers are joined while
        the devices, still open, watch this loop), then the summary."""
        self._ended = True
        if self.live is not None:
            live = self.live
            await in_thread(lambda: live.close(status, reason), "dentibot-live-close")
        if self.recorder is not None:
            rec = self.recorder
            try:
                await in_thread(lambda: rec.close(status, reason), "dentibot-recorder-close")
            except TelemetryError as exc:     # the summary is still written and returned
                status = "fault"
                reason = f"{reason}; recording: {exc}" if reason else f"recording: {exc}"
        self.summary = self.acc.finish(status, reason)
        return self.summary
