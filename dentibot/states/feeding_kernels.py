"""What the treatment's drilling states decide every tick, compiled (numba): the drilling
guard, the feed decision of the regulated and the constant strategies, the reversal checks of
``treating.drilling.feeding``, the end of a reversal (``treating.drilling.reversing``) and of
``treating.retracting``, and the overload of a turning file.

:class:`~dentibot.states.behaviours.Drilling`, :class:`~dentibot.states.behaviours.Feeding`,
:class:`~dentibot.states.behaviours.Reversing`, :class:`~dentibot.states.behaviours.Retracting`,
the overload check every state runs and the
strategies of :mod:`dentibot.states.strategies` call these with their state arrays and turn
the codes into events and messages; the compiled drilling loop of the built-in simulator calls
the same kernels. Each law has this one implementation.
"""

from __future__ import annotations

from numba import njit

from dentibot.control.feedrate import pd_step
from dentibot.control.torque_rise import rise_step

#: :func:`drilling_guard`'s answers (0: nothing).
GUARD_PATIENT_MOVED, GUARD_DEPTH_LIMIT, GUARD_FORCE_LIMIT = 1, 2, 3
#: A strategy's events (bits of :func:`strategy_decision`).
WL_REACHED, REVERSAL_NEEDED = 1, 2
#: Why feeding reverses the file although the strategy did not ask (:func:`feeding_checks`).
REVERSE_LIMIT, REVERSE_RISE = 1, 2
#: Strategies decided here (:func:`strategy_decision`): a constant feed, the feedrate PD.
CONSTANT, FEEDRATE = 0, 1


@njit(cache=True)
def drilling_guard(force_norm_n: float, patient_moved_n: float, has_depth: bool,
                   depth_mm: float, depth_max_mm: float, fz_h_n: float,
                   axial_force_limit_n: float) -> int:
    """What ends drilling before anything else is looked at (fig 5.6 and the limits): a
    force norm above the patient-moved threshold, the depth beyond ``depth_max_mm`` (the
    working length plus its margin), an axial push (``-fz_H``) above its limit; 0 for none."""
    if force_norm_n > patient_moved_n:
        return GUARD_PATIENT_MOVED
    if has_depth and depth_mm > depth_max_mm:
        return GUARD_DEPTH_LIMIT
    if -fz_h_n > axial_force_limit_n:
        return GUARD_FORCE_LIMIT
    return 0


@njit(cache=True)
def strategy_decision(kind: int, reverse: bool, pd_st, pd_par, blank,
                      reversal_threshold_n: float, constant_fz_n: float,
                      working_length_mm: float, tau_mnm: float,
                      depth_mm: float) -> tuple[float, float, int]:
    """One feeding tick of a strategy (5.3-5.4): ``FEEDRATE`` runs the PD
    (:func:`~dentibot.control.feedrate.pd_step`) and, with ``reverse``, asks for a reversal
    when fz* is below the threshold once the restart blanking (``blank[0]`` ticks, counted
    down here) is over; ``CONSTANT`` feeds ``constant_fz_n``. Both ask to retract at the
    working length (which takes precedence). Returns ``(fz, fz*, events)``."""
    bits = WL_REACHED if depth_mm >= working_length_mm else 0
    if kind == CONSTANT:
        return constant_fz_n, constant_fz_n, bits
    fz_star, fz = pd_step(pd_st, pd_par, tau_mnm)
    blank[0] -= 1.0
    if reverse and fz_star < reversal_threshold_n and bits == 0 and blank[0] < 0.0:
        bits |= REVERSAL_NEEDED
    return fz, fz_star, bits


@njit(cache=True)
def feeding_checks(strategy_events: int, tau_mnm: float, motor_rpm: float,
                   spin_up_rpm: float, torque_limit_mnm: float, rise_st, rise_a: float,
                   ts: float, min_slope_mnm_s: float, horizon_s: float) -> tuple[int, float]:
    """Feeding's own reversal checks after the strategy's decision: the torque above the
    hard limit, or rising so fast that it will be before a reversal takes effect
    (:func:`~dentibot.control.torque_rise.rise_step`; not while the motor spins up below
    ``spin_up_rpm``: the current then accelerates the rotor). Returns ``(REVERSE_* or 0,
    projected torque)``; nothing when the strategy already asked for a reversal."""
    ahead = rise_step(rise_st, rise_a, ts, min_slope_mnm_s, horizon_s, tau_mnm)
    if motor_rpm < spin_up_rpm:
        ahead = tau_mnm
    if strategy_events & REVERSAL_NEEDED:
        return 0, ahead
    if tau_mnm > torque_limit_mnm:
        return REVERSE_LIMIT, ahead
    if ahead > torque_limit_mnm:
        return REVERSE_RISE, ahead
    return 0, ahead


@njit(cache=True)
def overloaded(torque_mnm: float, torque_limit_mnm: float, turning_commanded: bool) -> bool:
    """A file commanded to turn (forward, or aligning) above the hard torque limit."""
    return turning_commanded and torque_mnm > torque_limit_mnm


@njit(cache=True)
def retracted(has_depth: bool, depth_mm: float, retract_to_mm: float) -> bool:
    """The retraction is over: the tip back at ``retract_to_mm`` or shallower."""
    return has_depth and depth_mm <= retract_to_mm


#: :func:`reversal_over`'s answers (0: still turning back).
REVERSAL_DONE, REVERSAL_TIMEOUT = 1, 2


@njit(cache=True)
def reversal_over(start_deg: float, pos_deg: float, reversal_deg: float, motor_rpm: float,
                  ticks: int, start_tick: int, ts: float, timeout_s: float) -> int:
    """A reversal (5.2) is done when the file has turned back ``reversal_deg`` (within 1 deg)
    from ``start_deg`` and stands still (under 2 rpm); it has failed when it takes longer
    than ``timeout_s`` (a bound file)."""
    if start_deg - pos_deg >= reversal_deg - 1.0 and abs(motor_rpm) < 2.0:
        return REVERSAL_DONE
    if (ticks - start_tick) * ts > timeout_s:
        return REVERSAL_TIMEOUT
    return 0


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels for the argument types the states
    pass, before any loop runs. Called once, at import."""
    import numpy as np

    z3 = np.zeros(3)
    drilling_guard(0.0, 1.5, True, 0.0, 16.5, 0.0, 5.0)
    strategy_decision(FEEDRATE, True, z3, np.zeros(7), np.zeros(1), -0.2, 0.3, 16.0, 1.0, 0.0)
    feeding_checks(0, 1.0, 0.0, 270.0, 50.0, z3, 0.3, 0.002, 1000.0, 0.012)
    overloaded(1.0, 50.0, True)
    retracted(True, 1.0, 0.5)
    reversal_over(0.0, -90.0, 90.0, 0.0, 10, 0, 0.002, 1.0)


warm_up()      # at import: before any device streams or loop runs
