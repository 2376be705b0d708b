"""Drilling strategies of chapter 5, selectable so that experiments can compare them.

Each strategy decides, every tick in ``treating.drilling.feeding``, the insertion force fz (N)
of f_d = (0, 0, fz, 0, 0, 0) and which events to raise; the state machine does the rest
(reversal, retraction). Depth is the file tip's depth along the canal (mm, 0 at the orifice).

- ``automated`` (5.4, fig 5.8): feedrate PD (fig 5.5) with bounds -0.5..0.5 N; fz* below the
  reversal threshold (-0.2 N) -> reversal; working length -> retract.
- ``feedrate`` (5.3, fig 5.5-5.6): the PD alone (no reversal).
- ``reversal`` (5.2, fig 5.4): sectioned drilling with a constant feed force: each section
  (``section_mm``) is drilled back and forth at least ``min_rounds`` times and until a whole
  round passes with the torque under the threshold; over the threshold -> 90 deg reversal.
- ``none``: constant feed force, no regulation, no reversal (ablation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dentibot.control.feedrate import FeedrateController, FeedrateParams
from dentibot.errors import ConfigError
from dentibot.states import feeding_kernels as fk

STRATEGIES = ("automated", "feedrate", "reversal", "none")


@dataclass(frozen=True)
class StrategyParams:
    name: str = "automated"
    feedrate: FeedrateParams = field(default_factory=FeedrateParams)
    # Fig 5.4 (inverse rotation control): the thesis gives no section length or feed force.
    # assumption: 2 mm sections, 0.3 N feed (about 1.9 mm/s with k/b = 6.25 mm/s per N).
    section_mm: float = 2.0
    min_rounds: int = 10
    constant_fz_n: float = 0.3
    # Current threshold of fig 5.4, as a file torque (mNm); default: the feedrate reversal
    # torque (tau_d - threshold/kp), so the strategies are compared at the same torque.
    reversal_torque_mnm: float | None = None
    # assumption: for 0.1 s after the file (re)starts, fz* does not trigger a reversal: the
    # spin-up (0 -> load torque in a few ms) makes the D term kick far below -0.2 N although
    # the torque is under tau_d. The hard torque limit still applies.
    restart_blanking_s: float = 0.1

    def __post_init__(self) -> None:
        if self.name not in STRATEGIES:
            raise ConfigError("drilling.strategy", self.name, f"one of {', '.join(STRATEGIES)}")
        if not 0.2 <= self.section_mm <= 10.0:
            raise ConfigError("drilling.section_mm", self.section_mm, "0.2..10 mm")
        if not 1 <= self.min_rounds <= 100:
            raise ConfigError("drilling.min_rounds", self.min_rounds, "1..100")
        if not 0.0 <= self.restart_blanking_s <= 1.0:
            raise ConfigError("drilling.restart_blanking_s", self.restart_blanking_s, "0..1 s")
        if not 0.0 < self.constant_fz_n <= 1.0:
            raise ConfigError("drilling.constant_fz_n", self.constant_fz_n, "0 < fz <= 1 N")

    @property
    def torque_threshold_mnm(self) -> float:
        if self.reversal_torque_mnm is not None:
            return self.reversal_torque_mnm
        return self.feedrate.reversal_torque_mnm


@dataclass(frozen=True)
class Decision:
    fz_n: float
    fz_star_n: float
    events: tuple[str, ...] = ()


class DrillingStrategy:
    """Base: ``start_pass`` when drilling (re)starts, ``step`` every feeding tick."""

    def __init__(self, params: StrategyParams, working_length_mm: float, ts: float) -> None:
        self.p = params
        self.wl = working_length_mm
        self.ts = ts

    def start_pass(self, depth_mm: float) -> None:
        """A pass (or a resumption after reversal / patient motion) begins at ``depth_mm``."""

    def reversed(self) -> None:
        """A reversal just finished."""

    def step(self, tau_mnm: float, depth_mm: float) -> Decision:
        raise NotImplementedError


class KernelStrategy(DrillingStrategy):
    """A strategy decided by the compiled :func:`~dentibot.states.feeding_kernels.strategy_decision`
    (state: the PD's ``pd.st`` and the restart blanking's ``blank``)."""

    kind = fk.CONSTANT
    reverse = False

    def __init__(self, params, working_length_mm, ts) -> None:
        super().__init__(params, working_length_mm, ts)
        self.pd = FeedrateController(params.feedrate, ts)
        self.blank = np.zeros(1)        # ticks left of the restart blanking (counted down)

    def step(self, tau_mnm: float, depth_mm: float) -> Decision:
        p = self.p
        if self.kind == fk.FEEDRATE and not math.isfinite(tau_mnm):
            raise ValueError(f"file torque is not finite: {tau_mnm}")
        fz, fz_star, bits = fk.strategy_decision(
            int(self.kind), bool(self.reverse), self.pd.st, self.pd.par, self.blank,
            float(p.feedrate.reversal_threshold_n), float(p.constant_fz_n), float(self.wl),
            float(tau_mnm), float(depth_mm))
        return Decision(fz, fz_star, _EVENTS[bits])


class FeedrateStrategy(KernelStrategy):
    """PD on the file torque (fig 5.5); ``reverse`` adds the 5.4 reversal trigger."""

    kind = fk.FEEDRATE

    def __init__(self, params, working_length_mm, ts, reverse: bool) -> None:
        super().__init__(params, working_length_mm, ts)
        self.reverse = reverse

    def start_pass(self, depth_mm: float) -> None:
        self.pd.reset()
        self.blank[0] = round(self.p.restart_blanking_s / self.ts)


class ConstantFeed(KernelStrategy):
    """Constant feed force, no regulation (the ``none`` ablation)."""


#: A strategy's event bits as the machine's triggers.
_EVENTS = {0: (), fk.WL_REACHED: ("working_length_reached",),
           fk.REVERSAL_NEEDED: ("reversal_needed",)}


class SectionedReversal(DrillingStrategy):
    """Fig 5.4: section by section, back and forth, reversal over the torque threshold."""

    def __init__(self, params, working_length_mm, ts) -> None:
        super().__init__(params, working_length_mm, ts)
        self.section = 0
        self.rounds = 0
        self.direction = 1
        self.clean_round = True
        self.sections = max(1, round(working_length_mm / params.section_mm + 0.4999))

    def bounds(self) -> tuple[float, float]:
        """Depth range (mm) of the current section: from the previous section's end."""
        end = min(self.wl, (self.section + 1) * self.p.section_mm)
        return max(0.0, end - self.p.section_mm), end

    def start_pass(self, depth_mm: float) -> None:
        if depth_mm < 0.5 * self.p.section_mm:   # a new pass from the orifice
            self.section, self.rounds, self.direction, self.clean_round = 0, 0, 1, True

    def reversed(self) -> None:
        self.clean_round = False

    def step(self, tau_mnm: float, depth_mm: float) -> Decision:
        p = self.p
        events: tuple[str, ...] = ()
        if tau_mnm > p.torque_threshold_mnm:
            self.clean_round = False
            events = ("reversal_needed",)
        lo, hi = self.bounds()
        if self.direction > 0 and depth_mm >= hi:
            self.direction = -1
        elif self.direction < 0 and depth_mm <= lo:
            self.direction = 1
            self.rounds += 1
            if self.rounds >= p.min_rounds and self.clean_round:
                if self.section + 1 >= self.sections:
                    events = ("working_length_reached",)
                else:
                    self.section += 1
                    self.rounds = 0
                    events = ("section_finished",)
            self.clean_round = True
        fz = p.constant_fz_n * self.direction
        return Decision(fz, fz, events)


def make_strategy(params: StrategyParams, working_length_mm: float, ts: float) -> DrillingStrategy:
    if params.name == "automated":
        return FeedrateStrategy(params, working_length_mm, ts, reverse=True)
    if params.name == "feedrate":
        return FeedrateStrategy(params, working_length_mm, ts, reverse=False)
    if params.name == "reversal":
        return SectionedReversal(params, working_length_mm, ts)
    return ConstantFeed(params, working_length_mm, ts)
