"""What each state of the treatment machine does, in one place per state: what it sets up on
entry, which events it detects every tick. What it asks of the arm and the file is data
(:data:`dentibot.states.modes.MODES`); the control task applies both.

A behaviour sees the running procedure through ``rt`` (the control task: its configuration
``cfg``, period ``ts``, tick count ``ticks``, current ``mode`` and file command ``file_cmd``,
the forward chain ``chain`` and flange orientation ``r_0_6`` of this tick, the joint limits
``kin.joint_limits_deg``, and ``set_gravity`` / ``set_tool_tip`` for calibration results), and
keeps what outlives one tick in :class:`Context` (shared by the states) or in itself (its own
counters). Events are ``(trigger, cause)`` pairs handed to the state machine.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dentibot.control.depth import depth_along
from dentibot.control.feedrate import FeedrateController
from dentibot.control.torque_rise import TorqueRise
from dentibot.states import feeding_kernels as fk
from dentibot.states.load_calibration import LoadCalibration, TcpRoutine
from dentibot.states.modes import Mode, state_mode
from dentibot.states.strategies import Decision, DrillingStrategy
from dentibot.states.treatment import LEAF_STATES

Event = tuple[str, "str | None"]

#: The leaf states of the treatment machine (values: the machine's dotted names, so a State
#: compares equal to the name the machine reports).
State = enum.StrEnum("State", {name.upper().replace(".", "_"): name for name in LEAF_STATES})


@dataclass
class Context:
    """What the states share across ticks of one procedure."""

    strategy: DrillingStrategy
    #: (orifice point, canal axis) in {0}: depth is measured along the axis from the point
    depth_ref: tuple | None = None
    #: the insertion force decision of the drilling strategy (or the alignment PD)
    decision: Decision = field(default_factory=lambda: Decision(0.0, 0.0))
    decided: int = -1                    # the tick it was taken in
    align_pd: FeedrateController | None = None
    script_target: np.ndarray | None = None   # joint target of a scripted arm motion (deg)
    pedal: bool = False
    reversals: int = 0
    patient_episodes: int = 0
    #: the tracked tooth (a runtime ToothFrame) when a patient tracker is configured: the
    #: depth reference is then also kept in the tooth's frame and follows the patient
    tooth: Any = None
    #: self-alignment's orientation loop (control.canal_axis.CanalAxisServo), when the plan
    #: has one and the tip is the reference point
    axis_servo: Any = None
    #: the tip ({0}, mm) where the file was last known out of the canal: where the procedure
    #: started (assumption: with the file out), at the end of the load calibration (free
    #: air) and whenever a withdrawal or the depth says it is out
    out_point: tuple | None = None
    #: the file torque's slope and projection while feeding (control.torque_rise.TorqueRise)
    torque_rise: TorqueRise | None = None


def feed_force_n(mode, ctx: Context, plan) -> float:
    """The desired insertion force fz of f_d (4.4) that ``mode.feed`` asks for (N). An
    insertion force is scaled down while the file is bent through the canal's tilt
    (:meth:`~dentibot.control.canal_axis.CanalAxisServo.feed_scale`)."""
    if mode.feed in ("strategy", "align"):
        fz = ctx.decision.fz_n if mode.feed == "strategy" or ctx.align_pd is not None \
            else plan.align_fz_n
        if fz > 0.0 and ctx.axis_servo is not None:
            fz *= ctx.axis_servo.feed_scale()
        return fz
    if mode.feed == "retract":
        return -plan.retract_fz_n
    return 0.0


def advance_mm(ctx: Context, est) -> float:
    """How far (mm) the tip is beyond where the file was last known out of the canal, along
    the file's axis now (0 when that is not known)."""
    if ctx.out_point is None:
        return 0.0
    return depth_along(est.tip_0, (ctx.out_point, est.axis_0))


def set_depth_reference(ctx: Context, rt, est) -> None:
    """Depth 0 is the canal orifice, ``orifice_gap_mm`` ahead of the tip along the tool axis
    when the file first goes in. It is kept for the file's whole stay in the canal, whatever
    brings it back (idle, dragging, another alignment): see :class:`Free`."""
    if ctx.depth_ref is None and est is not None:
        gap = rt.cfg.plan.orifice_gap_mm
        a = est.axis_0
        ctx.depth_ref = (tuple(est.tip_0[i] + gap * a[i] for i in range(3)), a)
        est.depth_mm = -gap
        rt.treatment.depth_known = True
        if ctx.tooth is not None:
            ctx.tooth.register(*ctx.depth_ref)


class Behaviour:
    """A state with nothing to set up or detect. Subclasses override :meth:`enter`,
    :meth:`guard` (a limit whose event ends the tick's detection) and :meth:`events`."""

    def enter(self, ctx: Context, rt, est, prev: str | None) -> None:
        """The state was just entered (``prev`` the state before it)."""

    def guard(self, ctx: Context, rt, est) -> Event | None:
        return None

    def events(self, ctx: Context, rt, est) -> list[Event]:
        return []

    def overload(self, ctx: Context, rt, est) -> list[Event]:
        """A turning file above the torque limit outside feeding is a fault."""
        th = rt.cfg.thresholds
        tau = est.file_torque_mnm
        if fk.overloaded(float(tau), float(th.torque_limit_mnm), turning_commanded(rt)):
            return [("fault", (f"file torque {tau:.1f} mNm > limit "
                               f"{th.torque_limit_mnm:.1f} mNm in {rt.state}"))]
        return []

    def detect(self, ctx: Context, rt, est) -> list[Event]:
        """Every tick in this state: the events it sees in the estimate ``est``."""
        g = self.guard(ctx, rt, est)
        if g is not None:
            return [g]
        return [*self.events(ctx, rt, est), *self.overload(ctx, rt, est)]


def current_mode(state: str, ctx: Context, rt) -> Mode:
    """The mode of ``state`` where the file is now (:func:`~dentibot.states.modes.state_mode`):
    in the canal while a depth reference is held or the tip may be in (:class:`Free`)."""
    return state_mode(state, ctx.depth_ref is not None or rt.treatment.maybe_in)


class Free(Behaviour):
    """Idle and dragging. The depth reference stays while the file is in the canal (depth
    above ``retract_to_mm``): an operator who stops, drags and aligns again with the file
    inside keeps counting depth from the same orifice, so the working length still holds
    and a retraction still withdraws the file. Once the file is out (or no depth is known)
    the reference goes, and the next insertion sets a new one.

    Without a reference (no camera: the orifice is only known once alignment starts) a file
    dragged into the canal is not seen by depth. What is known is where the file was last out
    of the canal (:attr:`Context.out_point`): a tip that has gone further than that along the
    file's axis may be in (``maybe_in``), and a retraction then withdraws it back past that
    point (:class:`Retracting`)."""

    def enter(self, ctx, rt, est, prev):
        self._drop_when_out(ctx, rt, est)
        self._watch_out_point(ctx, rt, est)

    def events(self, ctx, rt, est):
        self._drop_when_out(ctx, rt, est)
        self._watch_out_point(ctx, rt, est)
        return []

    @staticmethod
    def _drop_when_out(ctx, rt, est) -> None:
        if ctx.depth_ref is None:
            return
        depth = None if est is None else est.depth_mm
        if depth is None or depth <= rt.cfg.plan.retract_to_mm:
            ctx.depth_ref = None
            rt.treatment.depth_known = False
            if est is not None:
                ctx.out_point = tuple(est.tip_0)
            if ctx.tooth is not None:
                ctx.tooth.forget()

    @staticmethod
    def _watch_out_point(ctx, rt, est) -> None:
        if est is None:
            return
        if ctx.out_point is None and ctx.depth_ref is None:
            ctx.out_point = tuple(est.tip_0)     # assumption: a procedure starts with it out
        rt.treatment.maybe_in = ctx.depth_ref is None \
            and advance_mm(ctx, est) > -rt.cfg.plan.retract_to_mm


class SelfAligning(Behaviour):
    """4.4: f_d = (0, 0, fz) at the tip; optionally the feedrate PD on the file torque
    (Table 6.4 config C, no reversal); a depth beyond the working length is a fault."""

    def enter(self, ctx, rt, est, prev):
        plan = rt.cfg.plan
        fr = plan.align_feedrate
        ctx.align_pd = FeedrateController(fr, rt.ts) if fr is not None else None
        ctx.decision = Decision(plan.align_fz_n, plan.align_fz_n)
        set_depth_reference(ctx, rt, est)

    def guard(self, ctx, rt, est):
        wl, margin = rt.cfg.plan.working_length_mm, rt.cfg.thresholds.align_depth_margin_mm
        if est.depth_mm is not None and est.depth_mm > wl + margin:
            return ("fault", (f"depth_limit: depth {est.depth_mm:.2f} mm during alignment > "
                              f"working length {wl} + {margin} mm"))
        return None

    def events(self, ctx, rt, est):
        if ctx.align_pd is not None:
            out = ctx.align_pd.step(est.file_torque_mnm)
            ctx.decision = Decision(out.fz_n, out.fz_star_n)
            ctx.decided = rt.ticks
        return []


class Drilling(Behaviour):
    """Any drilling state: a patient movement (fig 5.6), the depth and the axial force limits
    end drilling before anything else is looked at."""

    def guard(self, ctx, rt, est):
        th, wl = rt.cfg.thresholds, rt.cfg.plan.working_length_mm
        has_depth = est.depth_mm is not None
        code = fk.drilling_guard(float(est.force_norm_n), float(th.patient_moved_n), has_depth,
                                 float(est.depth_mm) if has_depth else 0.0,
                                 float(wl + th.depth_margin_mm), float(est.wrench_h[2]),
                                 float(th.axial_force_limit_n))
        if code == fk.GUARD_PATIENT_MOVED:
            ctx.patient_episodes += 1
            return ("patient_moved", f"||f_H|| = {est.force_norm_n:.2f} N > {th.patient_moved_n} N")
        if code == fk.GUARD_DEPTH_LIMIT:
            return ("depth_limit", (f"depth {est.depth_mm:.2f} mm > working length {wl} + "
                                    f"{th.depth_margin_mm} mm"))
        if code == fk.GUARD_FORCE_LIMIT:
            return ("force_limit", (f"axial force {-est.wrench_h[2]:.2f} N > "
                                    f"{th.axial_force_limit_n} N"))
        return None


def turning_commanded(rt) -> bool:
    """The state turns the file forward (or aligning) and it was not stopped since."""
    return rt.mode.file in ("forward", "align") and rt.file_cmd != ("stop",)


def spin_up_rpm(handpiece) -> float:
    """Below this motor speed the file is still spinning up (feeding's torque-rise check is
    off: the current accelerates the rotor)."""
    return 0.9 * handpiece.drilling_rpm


class Feeding(Drilling):
    """5.4: the drilling strategy decides the feed every tick; a torque above the hard limit,
    or rising so fast that it will be before a reversal takes effect
    (:mod:`dentibot.control.torque_rise`), asks for a reversal."""

    def enter(self, ctx, rt, est, prev):
        set_depth_reference(ctx, rt, est)
        ctx.torque_rise = TorqueRise(ts=rt.ts)
        if prev == State.TREATING_DRILLING_REVERSING:
            ctx.strategy.reversed()
        ctx.strategy.start_pass(est.depth_mm if est and est.depth_mm is not None else 0.0)
        ctx.decision = Decision(0.0, 0.0)

    def events(self, ctx, rt, est):
        th = rt.cfg.thresholds
        tau = est.file_torque_mnm
        depth = est.depth_mm if est.depth_mm is not None else 0.0
        ctx.decision = dec = ctx.strategy.step(tau, depth)
        ctx.decided = rt.ticks
        ev: list[Event] = []
        r = ctx.torque_rise
        code, ahead = fk.feeding_checks(
            fk.REVERSAL_NEEDED if "reversal_needed" in dec.events else 0, float(tau),
            float(est.motor_rpm), float(spin_up_rpm(rt.cfg.handpiece)),
            float(th.torque_limit_mnm), r.st, float(r._a), float(r.ts),
            float(r.p.min_slope_mnm_s), float(r.p.horizon_s))
        if code == fk.REVERSE_LIMIT:
            ev.append(("reversal_needed", (f"file torque {tau:.1f} mNm > limit "
                                           f"{th.torque_limit_mnm:.1f} mNm")))
        elif code == fk.REVERSE_RISE:
            ev.append(("reversal_needed", (
                f"file torque {tau:.1f} mNm rising at {r.slope_mnm_s:.0f} mNm/s: "
                f"{ahead:.1f} mNm within {r.p.horizon_s * 1e3:.0f} ms > limit "
                f"{th.torque_limit_mnm:.1f} mNm")))
        for e in dec.events:
            ev.append((e, f"tau {tau:.1f} mNm, fz* {dec.fz_star_n:.3f} N, depth {depth:.2f} mm"))
        return ev

    def overload(self, ctx, rt, est):
        return []                         # feeding reverses instead (events above)


class Reversing(Drilling):
    """5.2: the file turned back ``reversal_deg``; finished when it has and stands still, a
    fault when it could not within the timeout (file bound)."""

    def enter(self, ctx, rt, est, prev):
        ctx.reversals += 1
        self.start = (est.motor_pos_deg if est else 0.0, rt.ticks)

    def events(self, ctx, rt, est):
        hp = rt.cfg.handpiece
        start_pos, start_tick = self.start
        turned = start_pos - est.motor_pos_deg
        code = fk.reversal_over(float(start_pos), float(est.motor_pos_deg),
                                float(hp.reversal_deg), float(est.motor_rpm), int(rt.ticks),
                                int(start_tick), float(rt.ts), float(hp.reversal_timeout_s))
        if code == fk.REVERSAL_DONE:
            return [("reversal_finished", f"turned back {turned:.1f} deg")]
        if code == fk.REVERSAL_TIMEOUT:
            return [("fault", (f"reversal: turned {turned:.1f} of {hp.reversal_deg} deg "
                               f"in {hp.reversal_timeout_s} s (file bound?)"))]
        return []


class PatientMoved(Behaviour):
    """Fig 5.6: file stopped, fz = 0, the arm follows; released when the force stays below the
    release threshold long enough. A force that is not released within ``patient_persist_s``
    (held up, or crossing the threshold back and forth faster than the release time), or that
    the arm's measured travel does not relieve, is not a patient (sensor drift, a collision, a
    contact ringing through the arm's delay): a fault."""

    def enter(self, ctx, rt, est, prev):
        self.release_ticks = 0
        self.above_ticks = 0              # ticks at or above the release threshold
        self.peak_n = 0.0
        self.ticks = 0
        self.f0 = est.force_norm_n if est is not None else math.inf
        self.p0 = est.tip_0 if est is not None else None

    def events(self, ctx, rt, est):
        th = rt.cfg.thresholds
        self.ticks += 1
        if self.p0 is None:
            self.p0 = est.tip_0
        travel = math.dist(est.tip_0, self.p0)
        if self.ticks * rt.ts >= th.drift_window_s and travel > th.drift_travel_mm and \
                est.force_norm_n >= self.f0:
            return [("fault", (f"force {est.force_norm_n:.2f} N not relieved after the arm "
                               f"followed it {travel:.1f} mm in {self.ticks * rt.ts:.2f} s "
                               f"(it was {self.f0:.2f} N): F/T offset drift suspected, not a "
                               "patient movement"))]
        if est.force_norm_n < th.patient_release_n:
            self.release_ticks += 1
            if self.release_ticks * rt.ts >= th.patient_release_s:
                return [("patient_released", f"||f_H|| = {est.force_norm_n:.2f} N")]
        else:
            self.release_ticks = 0
            self.above_ticks += 1
        self.peak_n = max(self.peak_n, est.force_norm_n)
        # not released in time, whether the force stayed up or kept crossing the threshold
        # (a contact ringing through the arm's delay is never below it long enough)
        if self.ticks * rt.ts > th.patient_persist_s:
            above = 100.0 * self.above_ticks / self.ticks
            return [("fault", (f"force not released {th.patient_persist_s} s after the "
                               f"patient-moved trigger while the arm follows: at or above "
                               f"{th.patient_release_n} N {above:.0f} "
                               f"% of the time, now {est.force_norm_n:.2f} N, peak "
                               f"{self.peak_n:.2f} N: sensor drift, a collision or a "
                               "ringing contact, not a patient movement"))]
        return []


class Retracting(Behaviour):
    """Withdrawing the file (negative fz) until the retract depth; a file bound on the way out
    (screw-in, taper lock) stops turning and is withdrawn straight, rather than left stopped
    in the canal. A file that may have been dragged in before any depth reference is
    withdrawn along its axis back past where it was last known out (that point as depth 0: the
    orifice can only be deeper)."""

    def enter(self, ctx, rt, est, prev):
        self.unknown_mm = None
        if ctx.depth_ref is None and ctx.out_point is not None and est is not None:
            ctx.depth_ref = (tuple(ctx.out_point), tuple(est.axis_0))
            est.depth_mm = self.unknown_mm = advance_mm(ctx, est)
            rt.treatment.depth_known = True
            rt.treatment.maybe_in = False

    def events(self, ctx, rt, est):
        has_depth = est.depth_mm is not None
        if fk.retracted(has_depth, float(est.depth_mm) if has_depth else 0.0,
                        float(rt.cfg.plan.retract_to_mm)):
            ctx.out_point = tuple(est.tip_0)
            if self.unknown_mm is not None:
                return [("retracted", (
                    f"no depth reference: withdrawn {self.unknown_mm - est.depth_mm:.1f} mm "
                    "along the file, back past where it was last known out of the canal"))]
            return [("retracted", f"depth {est.depth_mm:.2f} mm")]
        return []

    def overload(self, ctx, rt, est):
        th = rt.cfg.thresholds
        tau = est.file_torque_mnm
        if super().overload(ctx, rt, est):
            return [("file_stopped", (f"file torque {tau:.1f} mNm > limit "
                                      f"{th.torque_limit_mnm:.1f} mNm while retracting: "
                                      "withdrawn without turning"))]
        return []


class CalibratingTcp(Behaviour):
    """Eq 3.21-3.23: each pedal press records the flange pose (the operator holds the file tip
    on one fixed point); enough poses give the new tool tip."""

    def enter(self, ctx, rt, est, prev):
        self.routine = TcpRoutine(rt.cfg.tcp_points)
        self.pedal_prev = ctx.pedal

    def events(self, ctx, rt, est):
        pressed = ctx.pedal and not self.pedal_prev
        self.pedal_prev = ctx.pedal
        if not pressed:
            return []
        tcp = self.routine
        flange = rt.chain[1][5]                  # 0R_6 by columns, then the origin
        result = tcp.add(flange[:3].T.copy(), flange[3].copy())
        if result is None:
            return [("tcp_point", f"pose {len(tcp.rotations)} recorded")]
        if isinstance(result, str):
            if len(tcp.rotations) >= tcp.max_points:
                return [("fault", f"TCP calibration: {result}")]
            return [("tcp_point", f"pose {len(tcp.rotations)}: {result}")]
        rt.set_tool_tip(result.p_6_H_mm)
        return [("calibration_done", (f"TCP {np.round(result.p_6_H_mm, 3).tolist()} mm, "
                                      f"residual max {result.residual_max_mm:.3f} mm"))]


class CalibratingLoad(Behaviour):
    """Eq 4.18-4.24: the arm is scripted through the calibration poses; the identified load
    becomes the gravity model."""

    def enter(self, ctx, rt, est, prev):
        self.routine = None
        ctx.script_target = None
        if est is not None:
            self.routine = LoadCalibration(est.q_deg, rt.ts, limits_deg=rt.kin.joint_limits_deg)

    def events(self, ctx, rt, est):
        calib = self.routine
        if calib is None:
            return []
        ctx.script_target = calib.step(est.q_deg, est.wrench_s, rt.r_0_6)
        if calib.result is not None:
            rt.set_gravity(calib.result.model)
            ctx.out_point = tuple(est.tip_0)           # the calibration runs in free air
            return [("calibration_done", f"load: {calib.result.mass_kg * 1e3:.1f} g")]
        if calib.error is not None:
            return [("fault", f"load calibration: {calib.error}")]
        return []


#: The behaviour of each leaf state (a class: every procedure gets its own instances).
BEHAVIOURS: dict[State, type[Behaviour]] = {
    State.IDLE: Free,
    State.CALIBRATING_TCP: CalibratingTcp,
    State.CALIBRATING_LOAD: CalibratingLoad,
    State.DRAGGING: Free,
    State.SELF_ALIGNING: SelfAligning,
    State.TREATING_DRILLING_FEEDING: Feeding,
    State.TREATING_DRILLING_REVERSING: Reversing,
    State.TREATING_PATIENT_MOVED: PatientMoved,
    State.TREATING_PAUSED: Behaviour,
    State.TREATING_RETRACTING: Retracting,
    State.DONE: Behaviour,
    State.FAULT: Behaviour,
}


def make_behaviours() -> dict[str, Behaviour]:
    """One behaviour instance per state, for one procedure."""
    return {state: cls() for state, cls in BEHAVIOURS.items()}
