"""The hierarchical treatment state machine (transitions' HierarchicalAsyncMachine).

States (nested names joined with "."; our names contain underscores, so the separator is "."):

    idle
    calibrating.{tcp, load}
    dragging                      Table 4.3 dragging parameters, reference point A (the grip)
    self_aligning                 Table 4.3 self-alignment, reference point B, f_d = (0,0,fz)
    treating.drilling.{feeding, reversing}
    treating.patient_moved        fig 5.6: ||f_H|| > 1.5 N, file stopped, fz = 0
    treating.paused               operator pause: file stopped, fz = 0, still compliant
    treating.retracting
    done
    fault                         latched; only ``reset`` leaves it, never by itself

The machine sees events only (pedal, thresholds crossed, reversal finished, working length
reached, stale streams, emergency stop ...), never the 500 Hz stream: the control task detects
them and calls :meth:`Treatment.fire`. What the arm and the file do in each state is data
(:mod:`dentibot.states.modes`), read by the control task every tick.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from transitions import MachineError
from transitions.extensions.asyncio import HierarchicalAsyncMachine, NestedAsyncState


class _State(NestedAsyncState):
    separator = "."


class _Machine(HierarchicalAsyncMachine):
    state_cls = _State


STATES = [
    "idle",
    {"name": "calibrating", "children": ["tcp", "load"], "initial": "tcp"},
    "dragging",
    "self_aligning",
    {"name": "treating", "initial": "drilling", "children": [
        {"name": "drilling", "children": ["feeding", "reversing"], "initial": "feeding"},
        "patient_moved", "paused", "retracting"]},
    "done",
    "fault",
]

#: Every leaf state, dotted.
LEAF_STATES = (
    "idle", "calibrating.tcp", "calibrating.load", "dragging", "self_aligning",
    "treating.drilling.feeding", "treating.drilling.reversing", "treating.patient_moved",
    "treating.paused", "treating.retracting", "done", "fault",
)

_ALL_BUT_FAULT = [s for s in ("idle", "calibrating", "dragging", "self_aligning", "treating",
                              "done")]

#: (trigger, sources, destination, extra keyword arguments). Operator commands and detected
#: events alike; what each needs first is in :data:`NEEDS`.
TRANSITIONS = [
    ("calibrate_tcp", ["idle", "done"], "calibrating.tcp", {}),
    ("calibrate_load", ["idle", "done"], "calibrating.load", {}),
    ("calibration_done", "calibrating", "idle", {}),
    ("drag", ["idle", "self_aligning", "done"], "dragging", {"conditions": "calibrated"}),
    ("align", ["idle", "dragging", "done"], "self_aligning", {"conditions": "calibrated"}),
    ("drill", ["self_aligning", "dragging", "idle", "done"], "treating",
     {"conditions": "calibrated"}),
    ("reversal_needed", "treating.drilling.feeding", "treating.drilling.reversing", {}),
    ("reverse", "treating.drilling.feeding", "treating.drilling.reversing", {}),
    ("reversal_finished", "treating.drilling.reversing", "treating.drilling.feeding", {}),
    ("patient_moved", "treating.drilling", "treating.patient_moved", {}),
    ("patient_released", "treating.patient_moved", "treating.drilling", {}),
    ("pause", ["treating.drilling", "treating.patient_moved", "treating.retracting"],
     "treating.paused", {}),
    ("resume", "treating.paused", "treating.drilling", {}),
    ("section_finished", "treating.drilling.feeding", None, {}),
    ("working_length_reached", "treating.drilling", "treating.retracting", {}),
    ("force_limit", "treating.drilling", "treating.retracting", {}),
    ("depth_limit", "treating.drilling", "treating.retracting", {}),
    ("retract", ["treating.drilling", "treating.patient_moved", "treating.paused"],
     "treating.retracting", {}),
    # a file left in the canal by a stop, a drag or an alignment is withdrawn the same way
    ("retract", ["idle", "dragging", "self_aligning", "done"], "treating.retracting",
     {"conditions": "in_canal"}),
    ("retracted", "treating.retracting", "treating.drilling", {"conditions": "more_passes"}),
    ("retracted", "treating.retracting", "done", {}),
    ("stop", ["calibrating", "dragging", "self_aligning", "treating", "done"], "idle", {}),
    ("fault", _ALL_BUT_FAULT, "fault", {}),
    ("reset", "fault", "idle", {"conditions": "reset_allowed"}),
]

#: Why a trigger may be refused although the state takes it (condition name -> advice).
NEEDS = {
    "calibrated": "a load calibration (calibrate load) or a gravity model given in the config",
    "reset_allowed": "the emergency stop released and the fault's cause cleared",
    "more_passes": "",
    "in_canal": "the file in the canal (a depth reference, set when the file went in), or "
                "further along its axis than where it was last known out",
}

#: Events that cannot be refused by the state (only recorded) when they arrive in ``fault``.
_IDEMPOTENT_IN_FAULT = {"fault"}


@dataclass
class Refusal:
    """A trigger the machine did not take, and why (for the operator and the log)."""

    trigger: str
    state: str
    reason: str

    def __str__(self) -> str:
        return f"'{self.trigger}' refused in state '{self.state}': {self.reason}"


@dataclass
class Treatment:
    """The machine's model. The runtime sets the guard flags; the machine reads them.

    Attributes:
        gravity_known: a gravity/offset model exists (load calibration or configuration).
        estop_active: the emergency stop is pressed (reset is refused while it is).
        passes_left: further drilling passes after this one (protocol rounds).
        depth_known: a depth reference is held: the file went in and has not come out.
        maybe_in: no depth reference, but the tip has gone further along the file's axis than
            where the file was last known out of the canal (dragged in, perhaps).
        fault_causes: why the machine is in ``fault`` (latched, cleared on reset).
    """

    gravity_known: bool = False
    estop_active: bool = False
    passes_left: int = 0
    depth_known: bool = False
    maybe_in: bool = False
    fault_causes: list[str] = field(default_factory=list)
    history: list[tuple[str, str, str]] = field(default_factory=list)  # (trigger, src, dst)
    state: str = "idle"

    def __post_init__(self) -> None:
        self.machine = _Machine(
            model=self, states=STATES, initial="idle", auto_transitions=False,
            send_event=True, after_state_change="_record",
        )
        for trigger, src, dst, kw in TRANSITIONS:
            if dst is None:  # internal: the state's data stays as it is
                self.machine.add_transition(trigger, src, None, **kw)
            else:
                self.machine.add_transition(trigger, src, dst, **kw)

    # -------------------------------------------------------------- conditions
    def calibrated(self, event) -> bool:
        return self.gravity_known

    def reset_allowed(self, event) -> bool:
        return not self.estop_active

    def in_canal(self, event) -> bool:
        return self.depth_known or self.maybe_in

    def more_passes(self, event) -> bool:
        if self.passes_left > 0:
            self.passes_left -= 1
            return True
        return False

    def _record(self, event) -> None:
        self.history.append((event.event.name, event.transition.source, self.state))

    # -------------------------------------------------------------- API
    def allowed(self) -> list[str]:
        """Triggers the current state takes (before conditions)."""
        return sorted(set(self.machine.get_triggers(self.state)))

    async def fire(self, trigger: str, cause: str | None = None) -> Refusal | None:
        """Fire ``trigger``; None when taken, else a :class:`Refusal` naming the reason.

        ``fault`` records ``cause`` (also when already in fault: causes accumulate).
        """
        if trigger == "fault":
            self.fault_causes.append(cause or "unspecified")
            if self.state == "fault":
                return None
        if trigger == "reset" and self.state == "fault" and self.reset_allowed(None):
            self.fault_causes.clear()
        before = self.state
        if trigger not in self.allowed():
            return Refusal(trigger, before, self._needs_state(trigger))
        try:
            ok = await self.trigger(trigger)
        except MachineError as exc:  # pragma: no cover - allowed() checked first
            return Refusal(trigger, before, str(exc))
        if not ok:
            conds = {c.func for t in self.machine.get_transitions(trigger, source=before)
                     for c in t.conditions}
            conds |= {c.func for t in self._parent_transitions(trigger, before)
                      for c in t.conditions}
            reason = "; ".join(NEEDS.get(c, c) for c in sorted(conds) if NEEDS.get(c, c))
            return Refusal(trigger, before, f"needs {reason}" if reason else "condition false")
        return None

    def _parent_transitions(self, trigger: str, state: str):
        parts = state.split(".")
        for i in range(len(parts) - 1, 0, -1):
            yield from self.machine.get_transitions(trigger, source=".".join(parts[:i]))

    def _needs_state(self, trigger: str) -> str:
        sources = sorted({t.source for t in self.machine.get_transitions(trigger)})
        if not sources:
            return "unknown command"
        return "it needs state " + " or ".join(sources)

    def latched(self, cause: str | None) -> bool:
        """In ``fault`` already for a cause of the same kind ("stale_ft: ..." -> "stale_ft")."""
        kind = (cause or "").split(":", 1)[0]
        return self.state == "fault" and kind in {c.split(":", 1)[0] for c in self.fault_causes}

    def in_state(self, prefix: str) -> bool:
        """True in ``prefix`` or any of its sub-states."""
        return self.state == prefix or self.state.startswith(prefix + ".")
