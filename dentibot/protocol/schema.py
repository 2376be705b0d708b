"""The treatment protocol file (YAML), validated with pydantic.

Every section is optional; thesis defaults apply where the file is silent. Unknown keys are
errors (a typo must not pass silently). Units are in the field names and descriptions:
lengths mm, angles deg, forces N, file torque mNm, speeds rpm (file) or mm/s, time s.

A protocol::

    name: root-canal
    seed: 1
    file: {size: 25, taper: 0.06, length_mm: 25}
    phantom: {working_length_mm: 16, tilt_deg: 0}
    patient: {motion: static}
    steps:
      - calibrate_load: {}
      - drag: {duration_s: 2, hand_force_n: [0, 0, -1.0]}
      - align: {duration_s: 1, fz_n: 1.0}
      - drill: {strategy: automated, tau_d_mnm: 40, rounds: [{duration_s: 300}, {duration_s: 200}]}
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import AfterValidator, Field, model_validator

from dentibot.control.admittance import AXIAL_LAG_S, LATERAL_FREE_REF_MM
from dentibot.control.feedrate import FILE_STRENGTH_MNM
from dentibot.yamlfile import StrictModel

#: A tool point in the flange or handpiece frame (mm): beyond 250 mm it is not a handpiece
#: on a Meca500 (whose reach is 330 mm) but a unit or sign mistake.
MAX_TOOL_MM = 250.0
#: File length that must stay out of the canal at the working length (mm): the shank and the
#: handpiece head between the reference point and the chuck.
FILE_CLEARANCE_MM = 2.0
#: The hard torque limit may be at most this share of the file's torsional strength.
LIMIT_SHARE_OF_STRENGTH = 0.9
#: Longest planned procedure (s): the sum of the steps' durations.
MAX_PROCEDURE_S = 2 * 3600.0
#: Longest a stream may go without a new sample before it is a fault (s): the arm, the F/T
#: sensor and the handpiece drive at 500 Hz, the aux I/O polled at 50-100 Hz.
STALE_MAX_S = {"arm": 0.1, "ft": 0.1, "motor": 0.1, "aux": 0.5}


def _plausible_mnm(value: float) -> float:
    """A file torque below 1 mNm is a unit mistake (N m for mNm), not a setting."""
    if 0.0 < value < 1.0:
        raise ValueError(f"{value!r} mNm is implausibly small: was it given in N m? "
                         f"({value!r} N m = {value * 1000:g} mNm)")
    return value


ToolMm = Annotated[float, Field(ge=-MAX_TOOL_MM, le=MAX_TOOL_MM)]
ToolVec = tuple[ToolMm, ToolMm, ToolMm]
HandN = Annotated[float, Field(ge=-20.0, le=20.0)]
MilliNm = Annotated[float, AfterValidator(_plausible_mnm)]

#: The simulated phantom materials a protocol may name (the simulator's table of their
#: constants has exactly these names; a test holds the two together).
MATERIAL_NAMES = ("resin", "acrylic")


class Strict(StrictModel):
    """A section of a protocol (see :class:`~dentibot.yamlfile.StrictModel`)."""


class ControlSpec(Strict):
    rate_hz: float = Field(500.0, ge=10.0, le=5000.0,
                           description="control rate (Hz); thesis 500 Hz (ts = 2 ms)")
    lateral_free_ref_mm: float = Field(
        LATERAL_FREE_REF_MM, ge=0.0, le=60.0,
        description="the file's free length (mm, its length less the depth) below which the "
                    "lateral admittance's damping rises as (this / free length)^3, the "
                    "stiffness the handpiece feels sideways: keeps the lateral loop from "
                    "ringing deep in a rigidly held tooth through a real arm's delay "
                    "(the Meca500's, fitted on the bench); 0: never (the thesis)")
    axial_lag_ms: float | None = Field(
        round(1e3 * AXIAL_LAG_S, 6), ge=0.5, le=200.0,
        description="time constant (ms) of the self-alignment and drilling admittance along "
                    "the file (m_z/b_z): keeps the axial loop from running away through a "
                    "real arm's delay in a canal that drags the file; null: Table 4.3's "
                    "1 ms (the thesis)")
    cpus: list[int] | None = Field(
        None, min_length=1,
        description="CPUs the control process is kept to in real time, e.g. [3] for a core "
                    "the kernel keeps other jobs off (isolcpus); each must be one this "
                    "process may use; null: wherever the kernel puts it")


class ToolSpec(Strict):
    tip_mm: ToolVec = Field((0.0, 0.0, 90.0),
                         description="file tip in the flange frame, 6p_H (mm), from TCP calibration")
    sensor_offset_mm: float = Field(10.0, ge=0.0, le=100.0,
                                    description="F/T sensor origin along the flange z (mm)")
    grip_mm: ToolVec = Field((0.0, 0.0, -50.0),
                          description="reference point A (the grip) in {H} (mm)")


class FileSpec(Strict):
    size: int = Field(25, ge=6, le=140, description="ISO size: tip diameter in 1/100 mm")
    taper: float = Field(0.06, gt=0.0, le=0.12, description="taper (mm per mm)")
    length_mm: Literal[21, 25, 28, 31] = Field(25, description="total length (mm)")
    torsional_strength_mnm: MilliNm = Field(
        FILE_STRENGTH_MNM, gt=0.0, le=200.0,
        description="torque at which the file fractures (mNm); thesis 62 mNm")


class CurveSpec(Strict):
    start_mm: float = Field(ge=0.0, le=30.0, description="depth where the curve starts (mm)")
    radius_mm: float = Field(8.0, gt=1.0, le=100.0, description="curve radius (mm)")
    angle_deg: float = Field(25.0, ge=0.0, le=60.0, description="curve angle (deg)")


class MaterialSpec(Strict):
    """The phantom's material (simulator): a named one, optionally with constants changed.

    ``material: acrylic`` is short for ``material: {name: acrylic}``."""

    name: Literal[MATERIAL_NAMES] = Field(  # type: ignore[valid-type]
        "resin", description="resin: soft training block; acrylic: thesis experiment 2 phantoms")
    cutting_energy_mj_mm3: float | None = Field(
        None, gt=0.0, le=100_000.0, description="specific cutting energy (mJ/mm^3)")
    torque_mnm_per_mm2: float | None = Field(
        None, ge=0.0, le=1000.0, description="cutting torque per mm^2 of engagement (mNm)")
    torque_mnm_s_per_mm3: float | None = Field(
        None, ge=0.0, le=10_000.0,
        description="cutting torque per mm^2 of engagement and mm/s of feed (mNm s/mm^3)")
    torque_mnm_per_mm3: float | None = Field(
        None, ge=0.0, le=1000.0, description="torque of debris in the canal (mNm per mm^3)")
    rub_mnm_per_mm: float | None = Field(
        None, ge=0.0, le=10.0, description="flutes rubbing the walls (mNm per mm of contact)")
    screw_n_per_mnm: float | None = Field(
        None, ge=0.0, le=1.0, description="screw-in pull per mNm on the flutes (N/mNm)")
    axial_n_per_mm2: float | None = Field(
        None, ge=0.0, le=100.0, description="axial resistance of engagement (N per mm^2)")
    axial_n_per_mm3: float | None = Field(
        None, ge=0.0, le=100.0, description="axial resistance of debris (N per mm^3)")
    c_fwd_per_rev: float | None = Field(
        None, ge=0.0, le=10.0, description="debris augered out per forward revolution")

    @model_validator(mode="before")
    @classmethod
    def _named(cls, data):
        return {"name": data} if isinstance(data, str) else data

    def overrides(self) -> dict[str, float]:
        """The constants set here (CanalParams names)."""
        return {k: v for k, v in self.model_dump(exclude={"name"}).items() if v is not None}


class PhantomSpec(Strict):
    """The tooth phantom and its canal (simulator only)."""

    working_length_mm: float = Field(16.0, gt=1.0, le=30.0, description="working length (mm)")
    tilt_deg: float = Field(0.0, ge=-30.0, le=30.0,
                            description="canal tilt from the insertion direction (deg)")
    curve: CurveSpec | None = None
    orifice_gap_mm: float = Field(2.0, ge=0.0, le=20.0,
                                  description="file tip to orifice at the start (mm)")
    material: MaterialSpec = Field(MaterialSpec(), description="phantom material")
    preshaped: bool = Field(False, description="canal already shaped to the target (thesis "
                                               "experiment 1: 'drilled thoroughly in advance')")

    @model_validator(mode="after")
    def _curve_inside(self):
        if self.curve is not None and self.curve.start_mm >= self.working_length_mm:
            raise ValueError(f"curve.start_mm = {self.curve.start_mm} must be below "
                             f"working_length_mm = {self.working_length_mm}")
        return self


class PatientSpec(Strict):
    motion: Literal["static", "square", "head", "tremor", "swallowing", "patient"] = Field(
        "static", description="phantom motion: none, thesis experiment 1 square, head sway, "
        "tremor (8-12 Hz), swallowing (a 3 mm, 3 deg bump towards the robot about once a "
        "minute), or patient (head sway, tremor and swallows together)")
    tracker: bool = Field(
        False, description="measure depth in the tooth's frame with the patient tracker (the "
                           "built-in simulator adds a simulated one; on devices the device "
                           "file's tracker section is required); without it depth is taken "
                           "in the robot's base frame, as in the thesis, and the working "
                           "length is not protected against the patient moving along the "
                           "canal")
    tracking: Literal["force", "hybrid"] = Field(
        "force", description="how the arm follows the patient: force (the thesis: by the "
                             "admittance law alone) or hybrid (the tracked tooth's motion fed "
                             "forward, the force law correcting the rest; needs tracker)")


class SimulatorSpec(Strict):
    """The built-in simulator's physics, where it can be the ideal one or the one fitted to the
    thesis bench's recordings (simulator only; see the sim-to-real page)."""

    arm: Literal["ideal", "bench"] = Field(
        "bench", description="the arm's response to velocity commands: bench (fitted to the "
                             "bench's recordings: 16 ms dead time, a 6.3 ms lag, 0.80 of the "
                             "command realised) or ideal (an 8 ms lag, the command realised "
                             "in full: the world the thesis's tables were tuned on)")
    canal_drag: Literal["none", "bench"] = Field(
        "bench", description="the canal walls' drag on the file: none, or bench (fitted to the "
                             "bench's recordings: 0.21 N per mm/s along the canal while the "
                             "file slides off its seat 16.5 mm deep, in proportion to the "
                             "depth, a still file held by 1.2 N of friction more; 0.10 N per "
                             "mm/s across it)")


class StalePeriods(Strict):
    """Control periods a stream may go without a new sample before it is a fault.

    The device streams (arm, F/T, drive) come every period on the bench (Meca500 monitoring
    interval 2 ms, Net F/T RDT at the control rate, TPDOs on the 500 Hz SYNC): four periods
    without a sample is a fault on the fifth, 10 ms after the last one. The aux I/O is polled
    at 100 Hz in the background, hence its longer bound."""

    arm: int = Field(4, ge=1, le=500)
    ft: int = Field(4, ge=1, le=500)
    motor: int = Field(4, ge=1, le=500)
    aux: int = Field(50, ge=1, le=5000)


class LimitsSpec(Strict):
    torque_limit_mnm: MilliNm = Field(
        LIMIT_SHARE_OF_STRENGTH * FILE_STRENGTH_MNM, gt=0.0, le=200.0,
        description="hard file-torque limit (mNm); at most 90 % of the file's strength")
    patient_moved_n: float = Field(1.5, ge=0.2, le=10.0,
                                   description="||f_H|| above which the patient moved (N)")
    axial_force_limit_n: float = Field(3.0, ge=0.5, le=20.0,
                                       description="apical force cap (N)")
    stale_periods: StalePeriods = StalePeriods()


class RecordingSpec(Strict):
    enabled: bool = True
    path: str | None = Field(None, min_length=1, max_length=1024,
                             description="MCAP file; default runs/<name>-<seed>.mcap")


class CalibrateLoadStep(Strict):
    pass


class CalibrateTrackerStep(Strict):
    """Identify the patient tracker's anchors on the set-up
    (:mod:`dentibot.app.tracker_calibration`): with the file out of the canal and the clamp
    held still, the arm turns the handpiece about the file tip and moves it away and sideways
    through fourteen poses; the anchors found replace the device file's for the rest of the
    run, and are recorded (event ``tracker_calibration``) in the device file's format. Needs
    ``patient.tracker``."""

    rotation_deg: float = Field(10.0, ge=2.0, le=15.0,
                                description="turn about each of two axes at the file tip (deg)")
    translation_mm: float = Field(5.0, ge=1.0, le=10.0,
                                  description="move away from the tooth and sideways (mm)")


class DragStep(Strict):
    duration_s: float = Field(2.0, gt=0.0, le=600.0, description="how long (s)")
    hand_force_n: tuple[HandN, HandN, HandN] = Field((0.0, 0.0, 0.0),
                               description="scripted operator hand force at the grip, base "
                                           "frame (N; simulator only)")


class AlignStep(Strict):
    """Self-alignment (4.4). ``config`` A/B/C takes Table 6.4's column (admittance b6, file
    rotation at 60 rpm for B and C, constant fz = 1 N for A and B, feedrate control of fz in
    -0.2..0.5 N for C) instead of ``fz_n`` and ``rpm``."""

    duration_s: float = Field(1.0, gt=0.0, le=600.0, description="how long (s)")
    fz_n: float = Field(1.0, ge=-2.0, le=2.0, description="insertion force f_d z (N)")
    rpm: float = Field(0.0, ge=0.0, le=200.0, description="file speed while aligning (rpm)")
    config: Literal["A", "B", "C"] | None = Field(
        None, description="thesis Table 6.4 configuration (experiment 1)")
    tau_d_mnm: MilliNm = Field(40.0, gt=0.0, le=200.0,
                               description="desired file torque for config C (mNm)")
    axis_servo: bool | None = Field(
        None, description="turn the handpiece to the canal's direction read from the file's "
        "bending (default: on, except for the Table 6.4 configurations, which ran the "
        "admittance alone)")


class RoundSpec(Strict):
    duration_s: float = Field(gt=0.0, le=3600.0, description="round length (s)")


class DrillStep(Strict):
    strategy: Literal["automated", "feedrate", "reversal", "none"] = "automated"
    tau_d_mnm: MilliNm = Field(40.0, gt=0.0, le=200.0,
                               description="desired file torque (mNm); thesis 40 or 50")
    fz_min_n: float = Field(-0.5, ge=-2.0, le=0.0, description="feed force lower bound (N)")
    fz_max_n: float = Field(0.5, gt=0.0, le=2.0, description="feed force upper bound (N)")
    rpm: float = Field(60.0, gt=0.0, le=200.0, description="file speed (rpm); thesis 60")
    rounds: list[RoundSpec] | None = Field(
        None, min_length=1, max_length=100,
        description="rounds of continued passes, each until its duration; none: one pass")
    section_mm: float = Field(2.0, ge=0.2, le=10.0, description="reversal strategy section")
    min_rounds: int = Field(10, ge=1, le=100, description="reversal strategy rounds/section")


StepName = Literal["calibrate_load", "calibrate_tracker", "drag", "align", "drill"]
STEP_MODELS = {"calibrate_load": CalibrateLoadStep, "calibrate_tracker": CalibrateTrackerStep,
               "drag": DragStep, "align": AlignStep, "drill": DrillStep}


class Step(Strict):
    """One step: exactly one of the keys below."""

    calibrate_load: CalibrateLoadStep | None = None
    calibrate_tracker: CalibrateTrackerStep | None = None
    drag: DragStep | None = None
    align: AlignStep | None = None
    drill: DrillStep | None = None

    @model_validator(mode="before")
    @classmethod
    def _one_key(cls, data):
        if isinstance(data, dict):
            data = {k: ({} if v is None else v) for k, v in data.items()}
            if len(data) != 1:
                raise ValueError(f"a step has exactly one of {', '.join(STEP_MODELS)}; "
                                 f"got {sorted(data) or 'none'}")
        return data

    @property
    def kind(self) -> str:
        return next(k for k in STEP_MODELS if getattr(self, k) is not None)

    @property
    def spec(self):
        return getattr(self, self.kind)


#: A world's defaults for the protocol's ``simulator`` and ``control`` sections, by name
#: (``Protocol.world``); a key the protocol gives itself wins. ``bench`` is the sections' own
#: defaults: the simulator fitted to the bench's recordings, the controller as for a real
#: Meca500. ``thesis``: the ideal arm, no canal drag and Table 4.3's admittance alone, the
#: world the thesis's tables were tuned on (its reproductions run on it).
WORLDS: dict[str, dict[str, dict]] = {
    "bench": {},
    "thesis": {"simulator": {"arm": "ideal", "canal_drag": "none"},
               "control": {"lateral_free_ref_mm": 0.0, "axial_lag_ms": None}},
}
#: The world of a protocol that names none (``dentibot run``, the session): the bench-fitted
#: one, where a controller tuned in simulation meets what the real bench does
#: (docs/sim-to-real.md).
DEFAULT_WORLD = "bench"


class Protocol(Strict):
    name: str = Field(min_length=1, max_length=80)
    description: str = Field("", max_length=4000)
    seed: int = Field(0, ge=0, le=2**32 - 1, description="simulator seed")
    world: Literal["bench", "thesis"] = Field(
        DEFAULT_WORLD,
        description="the defaults of the simulator and control sections: bench (the simulator "
                    "fitted to the thesis bench's recordings, the controller as for a real "
                    "Meca500) or thesis (the ideal arm, no canal drag, Table 4.3's admittance: "
                    "the world the thesis's tables were tuned on); keys given in those sections "
                    "win")
    control: ControlSpec = ControlSpec()
    tool: ToolSpec = ToolSpec()
    file: FileSpec = FileSpec()
    phantom: PhantomSpec = PhantomSpec()
    patient: PatientSpec = PatientSpec()
    simulator: SimulatorSpec = SimulatorSpec()
    limits: LimitsSpec = LimitsSpec()
    recording: RecordingSpec = RecordingSpec()
    steps: Annotated[list[Step], Field(min_length=1, max_length=200)]

    @model_validator(mode="before")
    @classmethod
    def _world_defaults(cls, data):
        world = data.get("world", DEFAULT_WORLD) if isinstance(data, dict) else None
        if not isinstance(world, str) or world not in WORLDS:
            return data                   # not a mapping, or a world the field refuses
        data = dict(data)
        for section, defaults in WORLDS[world].items():
            given = data.get(section)
            if given is None:
                data[section] = dict(defaults)
            elif isinstance(given, dict):
                data[section] = {**defaults, **given}
        return data

    def planned_s(self) -> float:
        """The steps' planned durations added up (s); a single drilling pass counts 0."""
        total = 0.0
        for step in self.steps:
            spec = step.spec
            if step.kind in ("drag", "align"):
                total += spec.duration_s
            elif step.kind == "drill" and spec.rounds:
                total += sum(r.duration_s for r in spec.rounds)
        return total

    def cross_checks(self, limit_share: float = LIMIT_SHARE_OF_STRENGTH
                     ) -> list[tuple[tuple, str]]:
        """What no single field can say: each problem at the field it names. ``limit_share``:
        the largest share of the file's strength the hard torque limit may be (only a study on
        the built-in simulator, without the runtime's net, raises it)."""
        out: list[tuple[tuple, str]] = []
        if self.patient.tracking == "hybrid" and not self.patient.tracker:
            out.append((("patient", "tracking"), "hybrid needs the patient tracker (set "
                        "patient.tracker: true): the tooth's motion comes from it"))
        wl, length = self.phantom.working_length_mm, self.file.length_mm
        if wl + FILE_CLEARANCE_MM > length:
            out.append((("phantom", "working_length_mm"),
                        f"{wl:g} mm does not fit the {length} mm file: at most "
                        f"{length - FILE_CLEARANCE_MM:g} mm ({FILE_CLEARANCE_MM:g} mm of the "
                        "file stays out of the canal); use a longer file"))
        reach = math.hypot(*self.tool.tip_mm)
        if reach > MAX_TOOL_MM:
            out.append((("tool", "tip_mm"), f"{reach:.0f} mm from the flange: at most "
                                            f"{MAX_TOOL_MM:g} mm (check the unit: mm)"))
        strength = self.file.torsional_strength_mnm
        limit = self.limits.torque_limit_mnm
        if limit > limit_share * strength + 1e-9:
            out.append((("limits", "torque_limit_mnm"),
                        f"{limit:g} mNm is too close to the file's strength ({strength:g} "
                        f"mNm): at most {limit_share * strength:.1f} mNm "
                        f"({100 * limit_share:.0f} %)"))
        rate = self.control.rate_hz
        for name, max_s in STALE_MAX_S.items():
            n = getattr(self.limits.stale_periods, name)
            if n / rate > max_s + 1e-12:
                out.append((("limits", "stale_periods", name),
                            f"{n} periods = {1000 * n / rate:.0f} ms at {rate:g} Hz: at most "
                            f"{1000 * max_s:.0f} ms ({math.floor(max_s * rate + 1e-9)} "
                            "periods)"))
        calibrated_at = next((i for i, s in enumerate(self.steps)
                              if s.kind == "calibrate_load"), None)
        for i, step in enumerate(self.steps):
            spec = step.spec
            if step.kind == "calibrate_tracker" and not self.patient.tracker:
                out.append((("steps", i, step.kind),
                            "patient.tracker = False: the tracker calibration needs the "
                            "patient tracker (set patient.tracker: true)"))
            if calibrated_at is not None and i < calibrated_at and step.kind not in (
                    "calibrate_load", "calibrate_tracker"):   # position moves, no force law
                out.append((("steps", i, step.kind),
                            f"comes before the load calibration (step {calibrated_at + 1}): "
                            "force control needs the load identified first"))
            tau = getattr(spec, "tau_d_mnm", None)
            if tau is not None and (step.kind == "drill" or spec.config == "C") \
                    and tau >= limit:
                out.append((("steps", i, step.kind, "tau_d_mnm"),
                            f"{tau:g} mNm is not below the torque limit "
                            f"(limits.torque_limit_mnm = {limit:g} mNm)"))
        total = self.planned_s()
        if total > MAX_PROCEDURE_S:
            out.append((("steps",), f"{total:g} s planned in all: at most "
                                    f"{MAX_PROCEDURE_S:g} s ({MAX_PROCEDURE_S / 3600:g} h)"))
        return out
