"""The protocol's steps on a running procedure: what ``calibrate_load``,
``calibrate_tracker``, ``drag``, ``align`` and ``drill`` do.

One :class:`StepExecutor` serves both the protocol runner (unattended: a refused command
faults the runtime and the run ends) and the interactive session (a refused command ends the
step and is shown to the operator: it overrides :meth:`StepExecutor.command`). Both drive the
procedure the same way: commands and set-up between two ticks through its gate, waits for the
ticks of its running loop (:class:`~dentibot.app.procedure.Procedure`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from dentibot.app.procedure import Procedure
from dentibot.app.tracker_calibration import (
    TrackerCalibration,
    TrackerCalibrationParams,
    calibrate_tracker,
)
from dentibot.control.admittance import EXPERIMENT_1
from dentibot.control.canal_axis import AxisServoParams
from dentibot.control.feedrate import FeedrateParams
from dentibot.errors import ConfigError, DentibotError
from dentibot.runtime.config import TreatmentPlan
from dentibot.runtime.control_task import Runtime
from dentibot.runtime.tooth import ToothFrame
from dentibot.states.strategies import StrategyParams

#: Longest time a single pass may take before the runner stops waiting (simulated s).
PASS_TIMEOUT_S = 600.0
#: Thesis 5.3: spindle speed 60 rpm.
DRILLING_RPM = 60.0
#: The step kinds of a protocol, each a method of :class:`StepExecutor`.
STEP_KINDS = ("calibrate_load", "calibrate_tracker", "drag", "align", "drill")


class Aborted(Exception):
    """The procedure was asked to stop (the runner's ``abort``): stop safely."""


def align_plan(plan: TreatmentPlan, spec) -> TreatmentPlan:
    """The treatment plan for an align step (Table 6.4 when ``spec.config`` is set; those
    configurations run the thesis's admittance alone unless ``axis_servo`` asks otherwise)."""
    servo_on = spec.axis_servo if spec.axis_servo is not None else spec.config is None
    plan = dataclasses.replace(
        plan, axis_servo=(plan.axis_servo or AxisServoParams()) if servo_on else None)
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


def drill_setup(rt: Runtime, spec) -> None:
    """Set up ``rt`` for a drill step (between two ticks): strategy, tau_d and fz bounds
    (eq 5.7), file speed."""
    strategy = StrategyParams(
        name=spec.strategy, section_mm=spec.section_mm, min_rounds=spec.min_rounds,
        feedrate=FeedrateParams(tau_d_mnm=spec.tau_d_mnm, fz_min_n=spec.fz_min_n,
                                fz_max_n=spec.fz_max_n))
    rt.configure(plan=dataclasses.replace(rt.cfg.plan, strategy=strategy),
                 handpiece=dataclasses.replace(rt.cfg.handpiece, drilling_rpm=spec.rpm),
                 restart_strategy=True)


def _passes(rt: Runtime, n: int) -> Callable[[], None]:
    def set_passes() -> None:
        rt.treatment.passes_left = n
    return set_passes


class StepExecutor:
    """Runs protocol steps on the procedure ``proc`` (and, on the built-in simulator, acts the
    operator's hand on its world). ``aborted()`` is checked before every wait and in every
    tick of it: when true the step raises :class:`Aborted`."""

    def __init__(self, proc: Procedure, aborted: Callable[[], bool] = lambda: False) -> None:
        self.proc = proc
        self.rt = proc.runtime
        self.world = proc.world
        self._aborted = aborted
        #: the last ``calibrate_tracker`` step's result (None before one ran)
        self.tracker_calibration: TrackerCalibration | None = None

    async def step(self, kind: str, spec) -> None:
        """Run one step of kind ``kind`` (one of :data:`STEP_KINDS`)."""
        if kind not in STEP_KINDS:
            raise ValueError(f"step kind {kind!r}: one of {', '.join(STEP_KINDS)}")
        await getattr(self, kind)(spec)

    async def run_for(self, seconds: float, until=None) -> None:
        """Let the procedure run ``seconds`` (or until ``until(rt)``, a fault or an abort)."""
        aborted = self._aborted
        if aborted():
            raise Aborted
        await self.proc.run_for(seconds, until=lambda r: r.state == "fault" or aborted() or (
            until is not None and until(r)))
        if aborted():
            raise Aborted

    async def command(self, trigger: str, already: str | None = None) -> None:
        """Send ``trigger`` unless the runtime is already in state ``already``. Unattended, a
        refusal is a fault naming it."""
        if already is not None and self.rt.state == already:
            return
        refusal = await self.proc.command(trigger)
        if refusal is not None:
            rt = self.rt

            async def fault() -> None:
                await rt.command("fault")
                rt.treatment.fault_causes[-1] = f"protocol step: {refusal}"

            await self.proc.call(fault)

    # ---------------------------------------------------------------- the steps
    async def calibrate_load(self, spec) -> None:
        await self.command("calibrate_load")
        await self.run_for(60.0, until=lambda r: not r.treatment.in_state("calibrating"))

    async def calibrate_tracker(self, spec) -> None:
        """The tracker's anchors identified on the set-up
        (:func:`~dentibot.app.tracker_calibration.calibrate_tracker`), the result kept in
        :attr:`tracker_calibration` and recorded as a ``tracker_calibration`` event (the
        report and the anchors in the device file's format). When every string passes, the
        identified anchors replace the runtime's for the rest of the procedure; a failed
        calibration (bounds, identifiability, a pose not reached, the clamp moving) is a
        fault naming why, as a refused command is. Refused (ConfigError) without a tracker."""
        rt, proc = self.rt, self.proc
        if rt.dev.tracker is None or rt.cfg.tooth is None:
            raise ConfigError("patient.tracker", False, "a patient tracker: the calibration "
                              "identifies its anchors (set patient.tracker: true)")
        params = TrackerCalibrationParams(rotation_deg=spec.rotation_deg,
                                          translation_mm=spec.translation_mm)
        try:
            result = await calibrate_tracker(proc, params=params, aborted=self._aborted)
        except DentibotError as exc:
            if self._aborted():
                raise Aborted from exc
            if rt.state != "fault":
                await self._fault(f"tracker calibration: {exc}")
            return
        self.tracker_calibration = result

        def apply() -> None:
            rt.note("tracker_calibration", result.report())
            if not result.ok:
                return
            tooth = dataclasses.replace(rt.cfg.tooth, geometry=result.geometry,
                                        start_pose=result.poses[0])
            rt.cfg = dataclasses.replace(rt.cfg, tooth=tooth)
            rt.ctx.tooth = ToothFrame(tooth, rt.ts)

        await proc.call(apply)
        if not result.ok:
            why = "; ".join(f"string {s.string}: {s.why}" for s in result.strings if not s.ok)
            await self._fault(f"tracker calibration failed: {why}")

    async def _fault(self, cause: str) -> None:
        """The latched fault, its cause the protocol step's."""
        rt = self.rt

        async def fault() -> None:
            await rt.command("fault")
            rt.treatment.fault_causes[-1] = f"protocol step: {cause}"

        await self.proc.call(fault)

    async def drag(self, spec) -> None:
        await self.command("drag", already="dragging")
        if self.world is None:            # a real operator's hand moves the handpiece
            await self.run_for(spec.duration_s)
            return
        self.world.hand_force_0 = tuple(spec.hand_force_n)
        try:
            await self.run_for(spec.duration_s)
        finally:
            self.world.hand_force_0 = (0.0, 0.0, 0.0)

    async def align(self, spec) -> None:
        rt = self.rt
        await self.proc.call(lambda: rt.configure(plan=align_plan(rt.cfg.plan, spec)))
        await self.command("align", already="self_aligning")
        await self.run_for(spec.duration_s)

    async def drill(self, spec) -> None:
        """Rounds of drilling passes until each round's time is up, then a retraction; without
        rounds, one pass."""
        rt, proc = self.rt, self.proc
        await proc.call(lambda: drill_setup(rt, spec))
        finished = ("done", "fault")
        if not spec.rounds:
            await self.start_drilling(passes=0)
            await self.run_for(PASS_TIMEOUT_S, until=lambda r: r.state in finished)
            return
        for rnd in spec.rounds:
            await self.start_drilling(passes=10**6)   # cleaning until the round's time is up
            await self.run_for(rnd.duration_s, until=lambda r: r.state in finished)
            if rt.state == "fault":
                return
            await proc.call(_passes(rt, 0))
            if rt.state != "treating.retracting":
                await self.command("retract")
            why = await proc.finish_retraction(self.run_for)
            if why is not None:
                await self._fault(why)
                return

    async def start_drilling(self, passes: int) -> None:
        """The drill command, with ``passes`` more passes after the first."""
        await self.proc.call(_passes(self.rt, passes))
        await self.command("drill")
