"""The protocol's steps on a running runtime: what ``calibrate_load``, ``drag``, ``align`` and
``drill`` do, and the safe stop.

One :class:`StepExecutor` serves both the protocol runner (unattended: a refused command
faults the runtime and the run ends) and the interactive session (a refused command ends the
step and is shown to the operator: it overrides :meth:`StepExecutor.command`). The executor
uses only the runtime's ``run``, ``command``, ``state``, ``treatment``, ``cfg`` and devices, so
the session can hand it a view of its running control task.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import structlog

from dentibot.control.admittance import EXPERIMENT_1
from dentibot.control.feedrate import FeedrateParams
from dentibot.runtime.config import TreatmentPlan
from dentibot.runtime.control_task import Runtime
from dentibot.states.strategies import StrategyParams, make_strategy

log = structlog.get_logger("dentibot.protocol")

#: Longest time a single pass may take before the runner stops waiting (simulated s).
PASS_TIMEOUT_S = 600.0
#: Longest time the safe stop may spend withdrawing the file (simulated s).
RETRACT_TIMEOUT_S = 20.0
#: Thesis 5.3: spindle speed 60 rpm.
DRILLING_RPM = 60.0
#: The step kinds of a protocol, each a method of :class:`StepExecutor`.
STEP_KINDS = ("calibrate_load", "drag", "align", "drill")


class Aborted(Exception):
    """The procedure was asked to stop (the runner's ``abort``): stop safely."""


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
    rt.ctx.strategy = make_strategy(strategy, rt.cfg.plan.working_length_mm, rt.ts)


def _at_rest(rt: Runtime) -> bool:
    e = rt.last
    return e is not None and abs(e.motor_rpm) < 1.0 and rt.last_row is not None and \
        max(abs(x) for x in rt.last_row["qdot_cmd_deg_s"]) == 0.0


class StepExecutor:
    """Runs protocol steps on ``rt`` (and, on the built-in simulator, acts the operator's hand
    on ``world``). ``aborted()`` is polled before and after every wait: when true the step
    raises :class:`Aborted`."""

    def __init__(self, rt, world=None, aborted: Callable[[], bool] = lambda: False) -> None:
        self.rt = rt
        self.world = world
        self._aborted = aborted

    async def step(self, kind: str, spec) -> None:
        """Run one step of kind ``kind`` (one of :data:`STEP_KINDS`)."""
        if kind not in STEP_KINDS:
            raise ValueError(f"step kind {kind!r}: one of {', '.join(STEP_KINDS)}")
        await getattr(self, kind)(spec)

    async def run_for(self, seconds: float, until=None) -> None:
        """Let the runtime run ``seconds`` (or until ``until(rt)`` or a fault)."""
        if self._aborted():
            raise Aborted
        await self.rt.run(until=lambda r: r.state == "fault" or (until is not None and until(r)),
                          max_ticks=max(1, round(seconds / self.rt.ts)))
        if self._aborted():
            raise Aborted

    async def command(self, trigger: str, already: str | None = None) -> None:
        """Send ``trigger`` unless the runtime is already in state ``already``. Unattended, a
        refusal is a fault naming it."""
        if already is not None and self.rt.state == already:
            return
        refusal = await self.rt.command(trigger)
        if refusal is not None:
            await self.rt.command("fault")
            self.rt.treatment.fault_causes[-1] = f"protocol step: {refusal}"

    # ---------------------------------------------------------------- the steps
    async def calibrate_load(self, spec) -> None:
        await self.command("calibrate_load")
        await self.run_for(60.0, until=lambda r: not r.treatment.in_state("calibrating"))

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
        rt.cfg = dataclasses.replace(rt.cfg, plan=align_plan(rt.cfg.plan, spec))
        await self.command("align", already="self_aligning")
        await self.run_for(spec.duration_s)

    async def drill(self, spec) -> None:
        """Rounds of drilling passes until each round's time is up, then a retraction; without
        rounds, one pass."""
        rt = self.rt
        apply_drill(rt, spec)
        finished = ("done", "fault")
        if not spec.rounds:
            rt.treatment.passes_left = 0
            await self.command("drill")
            await self.run_for(PASS_TIMEOUT_S, until=lambda r: r.state in finished)
            return
        for rnd in spec.rounds:
            rt.treatment.passes_left = 10**6     # keep cleaning until the round's time is up
            await self.command("drill")
            await self.run_for(rnd.duration_s, until=lambda r: r.state in finished)
            if rt.state == "fault":
                return
            rt.treatment.passes_left = 0
            if rt.state != "treating.retracting":
                await self.command("retract")
            await self.run_for(RETRACT_TIMEOUT_S, until=lambda r: r.state in finished)

    # ---------------------------------------------------------------- safe stop
    async def safe_stop(self) -> None:
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
