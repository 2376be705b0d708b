"""The built-in simulator's drilling ticks, many in one compiled call.

A procedure on the built-in simulator in lock-step time (an in-silico trial, a study that
reads the runtime and the world after each tick, a protocol run that records) spends most of
its ticks feeding the file (``treating.drilling.feeding``), turning it back
(``treating.drilling.reversing``) or withdrawing it (``treating.retracting``), where nothing
happens tick after tick but the laws themselves.
:class:`DrillLoop` runs such ticks in :func:`~dentibot.app.drill_kernels.drill_ticks`, which
calls the very kernels the control task calls, in the tick's order, and stops before the
first tick in which anything would happen (an event, a finding, a refused command): the
control task runs that one itself. The outcome is the same, number for number, as the
control task's tick after tick.

The control task awaits it (``Runtime.fused``) before each tick of a loop that runs without
an end condition of its own (a procedure's loop); it runs between 0 and :data:`CHUNK` ticks:

- only where the compiled ticks are the control task's own: feeding with a regulated or a
  constant feed, reversing, retracting; the admittance at the tip, no patient tracker, the load
  known, a depth reference, the plain simulated devices of an unpaced lock-step clock, a
  patient that does not turn, no emergency stop, the drive without fault;
- never past what the procedure waits for: the clock's granted ticks and the gate's waiters'
  tick counts (their conditions must change only with the state: the gate checks them after
  the last tick), nor past the end of the simulator's noise blocks.

``on_ticks(out, n, k0, state)`` (``Runtime.on_ticks``) replaces ``on_tick`` for the ticks run
here (``out``: :data:`~dentibot.app.drill_kernels.OUT_FIELDS` per tick, ``k0`` the first tick,
``state`` theirs); with ``every`` (the reader's ``every``) a call ends at the first tick that
is a multiple of it, so that a reader can look at the world there.
:class:`~dentibot.app.runner.ProtocolRunner` uses it when nothing reads rows and its
``on_tick`` has a ``ticks`` method taking them in bulk (the in-silico trials' meter, the
pre-clinical experiment's trace).

Where rows are read, ``on_block(block)`` (``Runtime.on_block``) replaces the ``sink`` for the
ticks run here: each call's rows as one :class:`~dentibot.telemetry.blocks.TickBlock`, their
numbers written by the compiled ticks, their compute time the call's shared out. With
``block_ticks`` below :data:`CHUNK` (the runner gives half a recorder's budget of ticks not
yet in its file, as its writer flushes: 25 for a budget of 50), the rows leave in blocks of
at most ``block_ticks`` ticks:

- to a recorder process that offers its journal (``rt.block_wire``, a
  :class:`~dentibot.telemetry.recorder_process.Wire`), the compiled ticks send each block
  themselves as they finish it (:mod:`~dentibot.app.relay_kernels`), in calls of up to
  :data:`CHUNK` ticks; the ticks after the call's last block go to it after the call, and
  ``on_block_read`` (the other readers) takes all the call's rows then;
- else each call runs at most ``block_ticks`` ticks and hands its rows to ``on_block``.
"""

from __future__ import annotations

import time

import numpy as np

from dentibot.app import drill_kernels as dk
from dentibot.app import relay_kernels as rk
from dentibot.control.kinematics import WRIST_CENTRE_FRAME, euler_xyz_deg
from dentibot.control.torque_rise import TorqueRise
from dentibot.runtime.clock import LockStepClock
from dentibot.runtime.estimate import Estimate
from dentibot.sim import arm as sim_arm
from dentibot.sim import canal_kernels as ck
from dentibot.sim import ftsensor_kernels as ftk
from dentibot.sim import handpiece_kernels as hpk
from dentibot.sim import world_kernels as wk
from dentibot.sim.devices import SimArm, SimAux, SimForceSensor, SimHandpiece
from dentibot.sim.ftsensor import NOISE_BLOCK as FT_NOISE_BLOCK
from dentibot.sim.handpiece import NOISE_BLOCK as HP_NOISE_BLOCK
from dentibot.states.behaviours import spin_up_rpm
from dentibot.states.strategies import Decision, KernelStrategy, StrategyParams, make_strategy
from dentibot.telemetry.blocks import COL, WIDTH, TickBlock

#: Most ticks in one call: the event loop is served between calls (about 3 ms).
CHUNK = 256
FEEDING, REVERSING = "treating.drilling.feeding", "treating.drilling.reversing"
RETRACTING = "treating.retracting"
#: The states whose ticks run here, and their phase in the kernel.
STATES = {FEEDING: dk.FEEDING, RETRACTING: dk.RETRACTING, REVERSING: dk.REVERSING}
_STRAIN = 11            # the canal's outcome array: the file's largest bending strain


#: The last tick's estimate and commands in its row
_Q, _QDOT, _TIP, _WS, _WH = (COL[name] for name in (
    "q_deg", "qdot_cmd_deg_s", "tool_pose", "wrench_s", "wrench_h"))
_TAU, _CUR, _RPM, _DEPTH, _FZ_STAR = (COL[name] for name in (
    "file_torque_mnm", "motor_current_a", "motor_rpm", "depth_mm", "fz_star_n"))

#: What the kernel takes for the strategy and the torque rise outside feeding (unused).
_NO_STRATEGY = make_strategy(StrategyParams(), 1.0, 0.002)
_NO_RISE = TorqueRise()


class DrillLoop:
    """A procedure's drilling ticks over ``world``, many per compiled call (module
    docstring); ``gate`` and ``clock`` are the procedure's."""

    def __init__(self, world, gate, clock: LockStepClock, every: int | None = None,
                 block_ticks: int = CHUNK) -> None:
        self.world = world
        self.gate = gate
        self.clock = clock
        #: a call ends at the first tick that is a multiple of ``every``, if any (the reader
        #: then looks at the world at that tick)
        self.every = every
        #: most ticks per call when the rows are read (a recorder's budget of ticks at risk)
        self.block_ticks = max(2, min(CHUNK, int(block_ticks)))
        # a call that sends its blocks to the recorder's process itself
        self._ctl = np.zeros(rk.CTL_SIZE, dtype=np.int64)
        self.out = np.zeros((CHUNK, len(dk.OUT_FIELDS)))
        self.rows = np.zeros((CHUNK, WIDTH))
        self._phantom_euler = euler_xyz_deg(world.phantom_pose[:3, :3])
        self.last = np.zeros(dk.LAST_SIZE)
        self.frames = np.zeros((6, 4, 3))
        self.jh = np.zeros((6, 6))

    # ------------------------------------------------------------------ eligibility
    def _budget(self, rt) -> int:
        """How many ticks may run here now (0: none)."""
        w, tr, ctx, dev = self.world, rt.treatment, rt.ctx, rt.dev
        state = tr.state
        if ((rt.sink is not None and rt.on_block is None)
                or (rt.on_tick is not None and rt.on_ticks is None)
                or rt.pending or state not in STATES or rt._state != state
                or rt.mode.arm != "admittance" or rt.gravity is None or ctx.depth_ref is None
                or ctx.tooth is not None or rt.admittance.ref_h.any() or self.gate.pending):
            return 0
        if state == FEEDING and (rt.mode.feed != "strategy" or ctx.torque_rise is None
                                 or not isinstance(ctx.strategy, KernelStrategy)):
            return 0
        if state == RETRACTING and rt.mode.feed != "retract":
            return 0
        if state == REVERSING and (rt.mode.feed != "zero" or rt.file_cmd != ("reverse",)):
            return 0
        if not (type(dev.arm) is SimArm and type(dev.ft) is SimForceSensor
                and type(dev.motor) is SimHandpiece and type(dev.aux) is SimAux
                and dev.tracker is None and dev.arm.world is w and dev.ft.world is w
                and dev.motor.world is w and dev.aux.world is w):
            return 0
        clock = self.clock
        if clock is not rt.clock or not clock.ticks_left():
            return 0
        hp = w.handpiece
        if (w.fractured is not None or hasattr(w.motion, "rotation_at") or w.estop
                or hp.fault is not None or w.canal._file_key is not w.file):
            return 0
        fc = rt.file_cmd
        sup = rt.supervisor
        if (fc is None or fc[0] not in ("vel", "reverse") or fc != sup.spindle._cmd
                or sup._joint_bounds is None or sup._joint_bounds[0] is not rt.kin.joint_limits_deg
                or sup._speed_limits is None or sup._speed_limits[0] is not rt.speed_limits):
            return 0
        params = rt.cfg.plan.axis_servo
        servo = ctx.axis_servo
        if params is not None and (servo is None or servo.p is not params):
            return 0
        n = int(min(CHUNK, clock.ticks_left()))
        due = self.gate.ticks_to_next_waiter()
        if due is not None:
            n = min(n, due)
        if self.every:
            n = min(n, -rt.ticks % self.every + 1)
        if rt.sink is not None and not self._wire(rt):
            n = min(n, self.block_ticks)
        k = max(hp.hs[hpk.S["k"]], w.sensor.ss[ftk.S["k"]])
        n = min(n, int(min(HP_NOISE_BLOCK, FT_NOISE_BLOCK) - k))
        return n if n >= 2 else 0

    # ------------------------------------------------------------------ the call
    async def __call__(self, rt) -> int:
        """Run drilling ticks here; how many ran (each as ``Runtime.tick`` would, the world
        stepped after each but the last). Where the compiled ticks stopped before a tick with
        the world already stepped for it, that tick is the control task's, run from here."""
        n_max = self._budget(rt)
        if not n_max:
            return 0
        t_start = time.perf_counter()
        w = self.world
        arm, canal, hp, sensor = w.arm, w.canal, w.handpiece, w.sensor
        steps0, ts = w.steps, w.ts
        times = np.arange(steps0, steps0 + n_max) * ts    # each step's time, as World.step's
        times[0] = w.t
        origins = w.origins_at(times)
        axis_p = np.array(w.from_phantom(canal.t0, point=False))
        ctx, sup, adm = rt.ctx, rt.supervisor, rt.admittance
        filt, lim = adm._filter, adm.limiter
        phase = rt.treatment.state
        strat, rise = ctx.strategy, ctx.torque_rise
        if phase != FEEDING:          # neither decides unless the file is fed
            strat, rise = _NO_STRATEGY, _NO_RISE
        rev_start, rev_tick = rt.behaviours[phase].start if phase == REVERSING else (0.0, 0)
        servo = ctx.axis_servo
        stepping = rt.cfg.plan.axis_servo is not None
        sp, fr, tp = sup.spindle, sup.fracture, sup.tip_speed
        th, plan, hpc = rt.cfg.thresholds, rt.cfg.plan, rt.cfg.handpiece
        fc = rt.file_cmd
        compared = fc[0] != "reverse"          # the spindle observer's comparison
        want = fc[1] if fc[0] == "vel" else 0.0
        forward = max(0.0, want)
        gravity, to_h = rt.gravity, rt._to_h[rt._ref or "B"]
        o, a = ctx.depth_ref
        state = [sup._fresh.reshape(-1), sup._last_force, sp._st, fr._st, fr._ring.reshape(-1),
                 tp._st, tp._ring.reshape(-1), sup._disagree, strat.pd.st, strat.blank,
                 rise.st, filt.v, filt._f_prev, adm._w_prev]
        sv_st = sv_par = np.zeros(1)
        beam = (0.0, 0.0, np.zeros(1), np.zeros(1), np.zeros(1))
        if servo is not None:
            sv_st, sv_par, beam = servo.st, servo.par, servo._beam
            state.append(sv_st)
        saved = np.zeros((len(state), max(x.shape[0] for x in state)))
        b0, b1, b2 = canal._beam
        world_arrays = (w.ws, w.wp, w._F, w.kin._dh_arr, arm.ast, arm.ap, arm.lims, arm._q,
                        arm._qd, arm._vel_cmd, arm._target, arm._queue_t, arm._queue_v,
                        canal.st, canal.cp, canal.R, canal._h, canal.s, canal.kappa, b0, b1,
                        b2, canal._out, hp.hs, hp.hp, hp.noise, sensor.ss, sensor.sp,
                        sensor.noise)
        reads = (arm.p.encoder_res_deg, wk.S["origin_x"], wk.S["tip_x"], hpk.S["omega_rpm"],
                 hpk.S["pos_deg"], hpk.S["current_a"], hpk.S["torque_mnm"], hpk.S["stalled"],
                 ftk.S["last0"], ftk.S["status"], _STRAIN, bool(hp.enabled))
        sups = (sup._fresh, sup.bounds, sup._last_force, sup.lim.ft_jump_n, sup._in_out,
                sp._st, sp._lim, compared, float(want), fr._st, fr._ring, fr._lim,
                fr.n_recent,
                float(forward), fr.lim.speed_tolerance_share, fr._out, tp._st, tp._ring,
                tp.lim.tip_speed_mm_s, tp.lim.persist_s, sup._disagree, sup._est_lim,
                rt.mode.file in ("forward", "align"), sup._joint_bounds[1],
                sup._joint_bounds[2], sup._est_out, sup._speed_limits[1],
                sup.lim.tip_speed_cap_mm_s, sup._cmd_out)
        ctl = (adm.robot._dh_arr, adm.robot.tool, adm.ref_h, gravity._offset, gravity._gain,
               to_h.matrix, float(hpc.efficiency), float(hpc.friction_current_a),
               np.array(o, dtype=float), np.array(a, dtype=float))
        adms = (filt._a, filt._c, filt.v, filt._f_prev, adm._w_prev, adm._half_ts_deg,
                adm._q_lo, adm._q_hi, adm.singular_sigma, adm.robot.elbow_offset_rad,
                WRIST_CENTRE_FRAME, lim.thresholds, lim.lo_rad, lim.hi_rad, lim.vmax_rad_s,
                lim.margin_rad, lim.ts, float(rt.cfg.file.length_mm),
                float(rt.cfg.plan.lateral_free_ref_mm))
        feed = (STATES[phase], plan.retract_to_mm, plan.retract_fz_n, float(rev_start),
                int(rev_tick), hpc.reversal_deg, hpc.reversal_timeout_s, th.patient_moved_n,
                plan.working_length_mm + th.depth_margin_mm,
                th.axial_force_limit_n, strat.kind, strat.reverse, strat.pd.st, strat.pd.par,
                strat.blank, strat.p.feedrate.reversal_threshold_n, strat.p.constant_fz_n,
                strat.wl, spin_up_rpm(hpc), th.torque_limit_mnm, rise.st, rise._a, rise.ts,
                rise.p.min_slope_mnm_s, rise.p.horizon_s)
        servos = (stepping, servo is not None, sv_st, sv_par, *beam)
        row_on = rt.sink is not None
        truth = (row_on, rt.R_6_H, canal.R0, canal.width0, float(canal.p.stain_mm),
                 canal._red_buf, float(canal.red0), ck.S["version"],
                 float(w.completeness()) if row_on else 0.0)
        k0 = rt.ticks
        wire = rt.block_wire if self._wire(rt) and n_max > self.block_ticks else None
        relay = rk.OFF if wire is None else rk.wire_args(
            self.block_ticks, self._ctl,
            wire.begin(rt.step_name, rt.treatment.state, rt.ts, rt.cfg.plan.working_length_mm,
                       rt.ctx.reversals, self._phantom_euler),
            self.rows, COL["compute_us"], k0)
        n, steps, code = dk.drill_ticks(n_max, k0, steps0, w.t, ts, origins, axis_p,
                                        tuple(state), saved, world_arrays, reads, sups, ctl,
                                        adms, feed, servos,
                                        (arm._p.vel_dead_time_s, sim_arm._ERROR), truth,
                                        relay, self.out, self.rows, self.last, self.frames,
                                        self.jh)
        handed, failed = 0, None
        if wire is not None:
            handed = int(self._ctl[rk.PUB])
            try:
                wire.end(k0 + handed - 1, rt.ts, self.block_ticks)
            except Exception as exc:  # noqa: BLE001 - raised once the ticks are accounted for
                failed = exc
        if not n:
            if failed is not None:
                raise failed
            return 0
        self._after(rt, n, steps, code, k0, steps0, time.perf_counter() - t_start,
                    wire is not None, handed, failed)
        if steps == n:                # the next tick is due: the control task's own
            t0 = time.perf_counter()
            await rt.tick(0.0)
            rt.stats.add(0.0, time.perf_counter() - t0)
            n += 1
        return n

    @staticmethod
    def _wire(rt) -> bool:
        """Whether the calls send their blocks to the recorder's process themselves: rows
        are read, the recorder has a pipe for them (``rt.block_wire``) and the readers of
        the rows besides it take them after the call (``rt.on_block_read``)."""
        return (rt.sink is not None and rt.block_wire is not None
                and rt.on_block_read is not None)

    def _after(self, rt, n: int, steps: int, code: int, k0: int, steps0: int,
               wall_s: float, wired: bool = False, handed: int = 0,
               failed: BaseException | None = None) -> None:
        """The Python side brought up to date after ``n`` ticks ran here; ``wired``: the call
        sent its blocks to the recorder, the first ``handed`` ticks (the wire's failure, if
        any, is raised once the rest is up to date)."""
        w, last, row = self.world, self.last, self.rows[n - 1]
        norm, pos, fz = last[dk.LAST_SCALAR:].tolist()
        tau, cur, rpm, depth, fz_star = row[[_TAU, _CUR, _RPM, _DEPTH, _FZ_STAR]].tolist()
        rt.last = Estimate(row[_Q:_Q + 6].copy(), row[_WS:_WS + 6].copy(),
                           row[_WH:_WH + 6].copy(), norm, tau, rpm, cur, pos,
                           tuple(row[_TIP:_TIP + 3].tolist()),
                           tuple(last[dk.LAST_AXIS:dk.LAST_AXIS + 3].tolist()), depth)
        frames = self.frames.copy()
        rt.chain, rt.r_0_6 = (self.jh.copy(), frames), frames[5, :3].T
        rt.qdot_cmd = row[_QDOT:_QDOT + 6].copy()
        if rt.treatment.state == FEEDING:
            rt.ctx.decision, rt.ctx.decided = Decision(fz, fz_star), k0 + n - 1
        rt.ctx.pedal, rt.treatment.estop_active = bool(w.pedal), bool(w.estop)
        rt.ticks = k0 + n
        rt.stats.add_lockstep(n, wall_s)
        if steps:                     # the steps between the ticks, as the clock takes them
            w.steps = steps0 + steps
            w.t = w.steps * w.ts
            w._interaction = None
            self.clock.stepped(steps)
            self.gate.skip(steps)
        if code:
            w.fracture_from_step(code)
        if rt.on_ticks is not None:
            rt.on_ticks(self.out, n, k0, rt.treatment.state)
        if rt.sink is not None and wired:
            # the recorder has the blocks the call sent; the rows after them go to it from
            # here; the other readers take all the call's rows now
            if handed < n:
                self.rows[handed:n, COL["compute_us"]] = \
                    self._ctl[rk.TAIL_NS] / (n - handed) / 1e3
            block = TickBlock(self.rows[:n].copy(), k0, rt.ts, rt.step_name,
                              rt.treatment.state, rt.cfg.plan.working_length_mm,
                              rt.ctx.reversals, self._phantom_euler)
            rt.last_row = block.row(-1)
            try:
                if failed is not None:
                    raise failed
                if handed < n:
                    rt.block_wire.rec.record_block(block.part(handed, n))
            finally:                              # the rows are read once they are recorded
                rt.on_block_read(block)
            return
        if rt.sink is not None:
            cols = self.rows[:n].copy()
            cols[:, COL["compute_us"]] = wall_s / n * 1e6    # the call's, shared out
            block = TickBlock(cols, k0, rt.ts, rt.step_name, rt.treatment.state,
                              rt.cfg.plan.working_length_mm, rt.ctx.reversals,
                              self._phantom_euler)
            rt.on_block(block)
            rt.last_row = block.row(-1)

