"""Runtime configuration: tool geometry, thresholds, drilling plan (units in the names).

Defaults are the thesis's numbers where it gives them, else marked assumptions. The protocol
files (YAML) fill these; every value is range-checked here so that a bad value is refused with
its field, value and limit before anything moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from dentibot.control.admittance import AdmittanceParams
from dentibot.control.canal_axis import AxisServoParams
from dentibot.control.feedrate import FILE_STRENGTH_MNM, FeedrateParams, file_torque_from_current
from dentibot.control.filebeam import FileBeam
from dentibot.errors import ConfigError
from dentibot.protocol.schema import StalePeriods
from dentibot.runtime.clock import check_cpus
from dentibot.runtime.supervisor import SupervisorLimits
from dentibot.runtime.tooth import ToothConfig
from dentibot.states.strategies import StrategyParams


def _check(name: str, value: float, lo: float, hi: float, unit: str = "") -> None:
    if not (isinstance(value, int | float) and math.isfinite(value) and lo <= value <= hi):
        raise ConfigError(name, value, f"{lo}..{hi} {unit}".strip())


@dataclass(frozen=True)
class ToolGeometry:
    """Where the file tip, the sensor and the grip are (section 3.4, fig 4.7).

    - ``tip_6_mm``: 6p_H, the file tip in the flange frame (TCP calibration).
    - ``R_6_H``: 6R_H as 9 numbers row-major (tool-axis calibration); identity by default.
    - ``sensor_origin_6_mm``: the F/T sensor's origin in the flange frame (mechanical design).
    - ``grip_h_mm``: reference point A (where the operator holds the handpiece) in {H}.
    """

    tip_6_mm: tuple[float, float, float] = (0.0, 0.0, 90.0)
    R_6_H: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    sensor_origin_6_mm: tuple[float, float, float] = (0.0, 0.0, 10.0)
    # assumption: the grip is 50 mm behind the file tip along the file axis.
    grip_h_mm: tuple[float, float, float] = (0.0, 0.0, -50.0)


@dataclass(frozen=True)
class HandpieceConfig:
    """Current -> file torque (eq 5.4-5.5 with efficiency and no-load current)."""

    efficiency: float = 0.7            # assumption, matches the simulator's gearhead
    friction_current_a: float = 0.005  # assumption, matches the simulator's no-load current
    drilling_rpm: float = 60.0         # thesis 5.3: spindle speed constant 60 rpm
    reversal_deg: float = 90.0         # thesis 5.2: turn back 90 deg
    reversal_timeout_s: float = 2.0    # assumption: a reversal that takes longer is a fault

    def current_for(self, torque_mnm: float) -> float:
        """The motor current (A) that gives the file ``torque_mnm`` (eq 5.4-5.5 inverted, plus
        the no-load current the motor spends on itself)."""
        return torque_mnm / file_torque_from_current(1.0, self.efficiency) + \
            self.friction_current_a

    def __post_init__(self) -> None:
        _check("handpiece.efficiency", self.efficiency, 0.3, 1.0)
        _check("handpiece.friction_current_a", self.friction_current_a, 0.0, 0.2, "A")
        _check("handpiece.drilling_rpm", self.drilling_rpm, 1.0, 200.0, "rpm")
        _check("handpiece.reversal_deg", self.reversal_deg, 10.0, 360.0, "deg")
        _check("handpiece.reversal_timeout_s", self.reversal_timeout_s, 0.1, 10.0, "s")


@dataclass(frozen=True)
class Thresholds:
    """Event thresholds and safety limits."""

    patient_moved_n: float = 1.5        # thesis fig 5.6: ||{H}f|| > 1.5 N
    # assumption: released below 1.0 N held for 0.1 s (hysteresis against chattering).
    patient_release_n: float = 1.0
    patient_release_s: float = 0.1
    # assumption: a real patient movement is followed within 2 s (the arm yields at
    # 6.25 mm/s per N: a patient still pushing after 2 s would have moved the tooth 12 mm);
    # a force not released by then is sensor drift, a collision or a ringing contact -> fault.
    patient_persist_s: float = 2.0
    # assumption: following a real movement relieves the force: after 0.3 s of following and
    # 2 mm of measured tip travel the force is below what triggered the following (the arm
    # has caught up with the tooth). A force that is not relieved while the arm travels is
    # not a contact force (an F/T offset drift): fault, before the tip sweeps the canal.
    drift_window_s: float = 0.3
    drift_travel_mm: float = 2.0
    # the file's torsional strength (thesis eq 5.5: 62 mNm), from the protocol's file
    file_strength_mnm: float = FILE_STRENGTH_MNM
    # assumption: hard file-torque limit 90 % of the 62 mNm strength: stop and reverse.
    torque_limit_mnm: float = 0.9 * FILE_STRENGTH_MNM
    # assumption: apical force cap 3 N along the file (retract above it).
    axial_force_limit_n: float = 3.0
    # assumption: past the working length by more than this (depth estimate) -> retract.
    depth_margin_mm: float = 0.5
    # assumption: alignment may rest the file on the canal bottom (the phantoms' apical
    # constriction is 0.5 mm past the working length; thesis experiment 1 inserts until the
    # file meets it), so its bound is 1.0 mm past the working length -> fault.
    align_depth_margin_mm: float = 1.0
    supervisor: SupervisorLimits = field(default_factory=SupervisorLimits)
    # Freshness bound per stream, in control periods (stale -> fault); defaults: the schema's.
    stale_periods: dict = field(default_factory=lambda: StalePeriods().model_dump())

    def __post_init__(self) -> None:
        _check("limits.patient_moved_n", self.patient_moved_n, 0.2, 10.0, "N")
        _check("limits.patient_release_n", self.patient_release_n, 0.05, self.patient_moved_n,
               "N")
        _check("limits.file_strength_mnm", self.file_strength_mnm, 1.0, 200.0, "mNm")
        _check("limits.torque_limit_mnm", self.torque_limit_mnm, 1.0, self.file_strength_mnm,
               "mNm")
        _check("limits.axial_force_limit_n", self.axial_force_limit_n, 0.5, 20.0, "N")


    @property
    def drive_limit_mnm(self) -> float | None:
        """The torque the drive's own current limit is set to (:attr:`file_safe_mnm`): the
        hardware bounds the file's torque even if the software stalls. None when the runtime's
        limit is the file's strength itself (a study without the runtime's net)."""
        return self.file_safe_mnm if self.torque_limit_mnm < self.file_strength_mnm else None

    @property
    def file_safe_mnm(self) -> float:
        """Halfway between the runtime's torque limit and the file's strength: what the file
        may see while the runtime's reaction (a reversal: about 10 ms for the drive to turn the
        file round) takes effect."""
        return 0.5 * (self.torque_limit_mnm + self.file_strength_mnm)


@dataclass(frozen=True)
class TreatmentPlan:
    """The drilling part of a procedure."""

    working_length_mm: float = 16.0
    strategy: StrategyParams = field(default_factory=StrategyParams)
    passes: int = 1                    # drill to working length and retract this many times
    align_fz_n: float = 1.0            # Table 6.4: fz = 1 N during alignment
    align_rpm: float = 0.0             # file turning during alignment (Table 6.4 B, C: yes)
    # Table 6.4: the alignment's admittance (None: Table 4.3 self-alignment) and, for config
    # C, feedrate control of fz during alignment (None: the constant align_fz_n).
    align_params: AdmittanceParams | None = None
    align_feedrate: FeedrateParams | None = None
    retract_fz_n: float = 0.5          # assumption: withdraw with -0.5 N (about 3 mm/s)
    retract_to_mm: float = -0.5        # assumption: retracted when the tip is 0.5 mm out
    # Distance (mm) from the file tip to the canal orifice along the file when alignment or
    # drilling starts (the operator dragged the tip there): depth = -gap at that moment.
    orifice_gap_mm: float = 0.0
    # Self-alignment's orientation loop (control.canal_axis): the handpiece turns to the
    # canal's direction read from the file's bending. None: the thesis's admittance alone.
    axis_servo: AxisServoParams | None = field(default_factory=AxisServoParams)
    # The lateral admittance's damping and mass rise as (L_ref / L)^3 once the file's free
    # part L (its length less the depth) is shorter than this (mm; 0, the default: never):
    # the stiffness the handpiece feels sideways grows so. For an arm that answers late, with
    # a rigidly held tooth: control.admittance.LATERAL_FREE_REF_MM.
    lateral_free_ref_mm: float = 0.0
    # The self-alignment and drilling admittance's time constant along the file (s, m_z/b_z;
    # None: Table 4.3's 1 ms). For an arm that answers late in a canal that drags the file:
    # control.admittance.AXIAL_LAG_S.
    axial_lag_s: float | None = None

    def __post_init__(self) -> None:
        _check("treatment.working_length_mm", self.working_length_mm, 1.0, 30.0, "mm")
        _check("treatment.passes", self.passes, 1, 1000)
        _check("treatment.align_fz_n", self.align_fz_n, -2.0, 2.0, "N")
        _check("treatment.align_rpm", self.align_rpm, 0.0, 200.0, "rpm")
        _check("treatment.retract_fz_n", self.retract_fz_n, 0.05, 2.0, "N")
        _check("treatment.retract_to_mm", self.retract_to_mm, -10.0, 0.0, "mm")
        _check("treatment.orifice_gap_mm", self.orifice_gap_mm, 0.0, 20.0, "mm")
        _check("treatment.lateral_free_ref_mm", self.lateral_free_ref_mm, 0.0, 60.0, "mm")
        if self.axial_lag_s is not None:
            _check("treatment.axial_lag_s", self.axial_lag_s, 0.0005, 0.2, "s")


@dataclass(frozen=True)
class RuntimeConfig:
    period_s: float = 0.002            # thesis: ts = 2 ms (500 Hz)
    tool: ToolGeometry = field(default_factory=ToolGeometry)
    handpiece: HandpieceConfig = field(default_factory=HandpieceConfig)
    thresholds: Thresholds = field(default_factory=Thresholds)
    plan: TreatmentPlan = field(default_factory=TreatmentPlan)
    #: the file in the handpiece (its bending model reads the canal's direction)
    file: FileBeam = field(default_factory=FileBeam)
    tcp_points: int = 4                # thesis 3.4: four-point TCP (more when available)
    #: the patient tracker's geometry: depth in the tooth's frame (None: the base frame)
    tooth: ToothConfig | None = None
    #: CPUs the control process is kept to in real time (None: wherever the kernel puts it)
    cpus: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        _check("control.period_s", self.period_s, 0.0002, 0.1, "s")
        object.__setattr__(self, "cpus", check_cpus("control.cpus", self.cpus))
        _check("calibration.tcp_points", self.tcp_points, 4, 12, "poses (eq 3.23 needs >= 4)")
