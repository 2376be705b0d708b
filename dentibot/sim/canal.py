"""Root canal in a tooth phantom: centreline, tapered lumen, pulp ("red area"), contact, cutting.

Phantom frame {P}: origin at the canal orifice, z the nominal insertion direction. The canal
starts straight along ``t0 = Rx(tilt) z``; a curved canal continues after ``curve_start_mm``
as a circular arc of radius ``curve_radius_mm`` bending towards ``u = x`` by ``curve_angle_deg``.
Depth ``s`` (mm) is arc length from the orifice.

Discretisation: depth slices of ``slice_mm``. Per slice the lumen radius ``R`` (mm, axisymmetric)
grows as the file cuts.

Completeness (eq 6.1) is measured as the thesis measured it (6.3): the canal of the acrylic
phantom is filled with red pigment, which also stains its wall to a depth ``stain_mm``, and
the "red area" is what a photograph across the canal shows red, in pixels. Here: per slice down
to the working length, the projected width of the stained canal ``2 (R0 + stain)`` times
``slice_mm`` (mm^2), scaled by the fraction of the stain the file has not cut away,
``max(0, 1 - (R - R0) / stain)`` (the pigment inside the lumen goes with the cut wall: a file
that reaches a slice is wider than the initial lumen there). Completeness is
``(red before - red now) / red before``. So it measures how much of the canal's length the
file has cleaned, weighted by width, as the photographs did; how close the lumen has come to
the target preparation (a #25/.06 shape) is :meth:`Canal.shaping`, the removed fraction of the
volume between the initial lumen and that target.

Contact and cutting (per step, vectorised over the slices the file occupies):
- the file is a straight line in the straight part of the canal (its lateral offset ``e(s)``
  from the centreline is linear in depth) and follows the centreline in the curved part (a
  flexible file is guided by the lumen; its bending counts for fatigue only - assumption);
- lateral: per slice the far-side penetration ``|e| + r_f - R`` minus the near-side one pushes
  the file back towards the axis with the wall stiffness, in series with the file's cantilever
  stiffness 3EI/L^3 at the penetration-weighted contact point;
- engagement ``A = sum(max(0, r_f - R)) ds`` (mm^2): the file diameter profile overlapping the
  lumen. The cutting torque ``tau_c = (k_A + k_v feed) A`` grows with it and with the feed;
- the torque the canal resists forward rotation with is ``tau_c`` plus the debris
  (``k_deb`` per mm^3), the wall friction of the lateral force (``mu |F_lat| r``) and the
  flutes rubbing the walls they touch without cutting (``rub`` per mm of contact length);
- cutting (forward rotation only) by energy: a rotation ``dtheta`` removes the volume
  ``tau_c dtheta / u_s`` (``u_s`` the material's specific cutting energy), taken from each
  slice in proportion to its overlap (never more than the overlap). The removed volume
  becomes debris, which reverse rotation (``c_rev`` per reverse revolution), forward augering
  (``c_fwd``), withdrawal beyond a dead band (decay length ``withdraw_mm``) or leaving the
  canal clears;
- screw-in: turning forward, the engaged flutes pull the file into the canal like a screw
  with ``screw`` times the torque on their helical edges (cutting and rubbing) (N); turning
  back pushes it out with the reverse fraction of that.
  Nothing else in the model pulls the file in, so a feed that is not regulated can be drawn
  into a taper lock whose torque breaks the file;
- the canal bottom (``working_length_mm + apex_margin_mm``) is a stiff axial contact.

Materials (:data:`MATERIALS`) set the cutting, rubbing, debris and screw-in constants of a
phantom: ``resin`` (the default: a soft training block) and ``acrylic`` (the thesis's
experiment 2 root phantoms).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import dentibot.sim.canal_kernels as kern
from dentibot.errors import ConfigError
from dentibot.sim.nitifile import NiTiFile
from dentibot.sim.state_view import scalar


@dataclass(frozen=True)
class CanalParams:
    working_length_mm: float = 16.0
    # assumption: the bottom (apical constriction) 0.5 mm beyond the working length.
    apex_margin_mm: float = 0.5
    tilt_deg: float = 0.0
    curve_start_mm: float | None = None
    curve_radius_mm: float = 8.0
    curve_angle_deg: float = 0.0
    # assumption: initial lumen after a #15 hand file (glide path), ISO 15 with 2 % taper.
    initial_apical_mm: float = 0.15
    initial_taper: float = 0.02
    # assumption: target preparation = the shape of a #25/.06 file at working length.
    target_apical_mm: float = 0.25
    target_taper: float = 0.06
    # assumption: the red pigment stains the acrylic wall 20 um deep (a dye in a resin
    # surface); a wall cut deeper than that shows no red.
    stain_mm: float = 0.02
    slice_mm: float = 0.25
    # assumption: wall stiffness 20 N/mm per mm of contact length (acrylic/dentin surface
    # under a ~0.5 mm file; far stiffer than the file, so the file's compliance dominates).
    wall_n_mm_per_mm: float = 20.0
    # Lateral compliance of the tooth's support (mm/N): the tooth moves sideways as a body
    # under the file's loads (a patient's periodontal ligament, a phantom's holder and
    # platform). It softens a file pushed sideways and leaves a couple alone. 0: a rigid
    # holder (the training block's default). ``support_y_mm_per_n``: along the phantom's y
    # axis, where it differs (a holder clamped on one side); None: the same.
    support_mm_per_n: float = 0.0
    support_y_mm_per_n: float | None = None
    # assumption: tip outside the lumen by more than this lands on the chamber floor.
    access_margin_mm: float = 1.0
    # assumption: canal bottom / chamber floor axial stiffness (N/mm).
    bottom_n_mm: float = 20.0
    # Cutting and resistance constants (the ``resin`` material), all assumptions chosen so
    # that a #25/.06 file fully engaged in a #15/.02 canal needs 20-40 mNm (the thesis's
    # tau_d 40-50 mNm range) and shapes a 16 mm canal in one to two minutes at 60 rpm:
    cutting_energy_mj_mm3: float = 180.0  # u_s: energy per removed volume (mJ/mm^3 = N/mm^2)
    torque_mnm_per_mm2: float = 8.0    # k_A: cutting torque per mm^2 of engagement
    torque_mnm_s_per_mm3: float = 20.0  # k_v: per (mm/s of feed * mm^2 of engagement)
    torque_mnm_per_mm3: float = 30.0   # k_deb: torque per mm^3 of debris in the canal
    friction_mu: float = 0.3           # wall friction: torque mu |F_lat| r_file (N*mm = mNm)
    rub_mnm_per_mm: float = 0.0        # flutes rubbing the walls, per mm of contact length
    rub_clearance_mm: float = 0.01     # a slice within this of the file's radius touches it
    screw_n_per_mnm: float = 0.0       # screw-in pull per mNm on the flutes' edges (N/mNm)
    reverse_factor: float = 0.3        # reverse rotation resists this fraction, does not cut
    axial_n_per_mm2: float = 0.1       # axial resistance per mm^2 of engagement
    axial_n_s_per_mm3: float = 0.5     # axial resistance per (mm/s of feed * mm^2 engaged)
    axial_n_per_mm3: float = 0.5       # axial resistance per mm^3 of debris
    c_rev_per_rev: float = 4.0         # debris cleared: exp(-c_rev * reverse revolutions)
    c_fwd_per_rev: float = 0.1         # forward rotation augers debris out along the flutes
    withdraw_mm: float = 0.5           # debris cleared: exp(-withdrawal / withdraw_mm) ...
    # ... counting only withdrawal beyond this dead band from the deepest point since the last
    # flush: the tip's micrometre jitter under admittance control does not flush the canal.
    withdraw_deadband_mm: float = 0.1
    # The feed-rate-dependent resistances act on the feed rate low-passed with this time
    # constant (assumption: the file and the dentin chips are viscoelastic, not a pure
    # dashpot). A pure dashpot closes an algebraic loop with the admittance law (velocity =
    # k/b * force): with several mm^2 engaged its gain exceeds 1 per tick and the axial
    # force rings between the sensor's +-60 N limits at the canal bottom.
    feed_filter_s: float = 0.05
    # Canal drag on the file (all zero by default: no drag). The file slides along the canal
    # at the slip rate ``u`` (mm/s, + deeper; the depth rate low-passed with
    # ``drag_filter_s``; 0 while the tip is pressed into the bottom, where the seat gives
    # and the file does not slide along the walls); the walls resist it with
    # ``drag_n_s_per_mm * u + drag_coulomb_n * tanh(u / drag_v0_mm_s)`` (N). While the root
    # recedes from the file (u < 0) that pulls the file along into the canal: the contact
    # force in {H} turns to tension. A file that does not turn is dragged
    # ``drag_static_factor`` times harder, both parts (its flutes do not work it loose from
    # the walls as a turning file's do), and held by ``drag_still_coulomb_n`` of friction
    # more (N, the Coulomb law above). Laterally the walls damp the file's
    # sliding across the canal with ``drag_lat_n_s_per_mm`` (N per mm/s) while it touches
    # them. The axial drag acts along the file's length in the canal: with
    # ``drag_depth_mm`` set (> 0) it is the values above for a file that deep, in proportion
    # to the depth (a file entering the orifice meets next to none); 0: the same at any
    # depth. The bench preset (:mod:`dentibot.sim.bench_physics`) holds the fitted values.
    drag_n_s_per_mm: float = 0.0
    drag_coulomb_n: float = 0.0
    drag_v0_mm_s: float = 0.5
    drag_static_factor: float = 1.0
    drag_depth_mm: float = 0.0
    drag_still_coulomb_n: float = 0.0
    drag_lat_n_s_per_mm: float = 0.0
    drag_filter_s: float = 0.004
    # Torque (mNm) the canal bottom resists rotation with per N the tip is pressed onto it
    # (the file's tip grinding at the apical stop); 0 by default.
    bottom_torque_mnm_per_n: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 < self.working_length_mm <= 30.0:
            raise ConfigError("canal.working_length_mm", self.working_length_mm, "0 < WL <= 30")
        if not 0.0 < self.stain_mm <= 1.0:
            raise ConfigError("canal.stain_mm", self.stain_mm, "0 < stain <= 1 mm")
        if not 0.0 < self.slice_mm <= 1.0:
            raise ConfigError("canal.slice_mm", self.slice_mm, "0 < slice <= 1 mm")
        if not self.cutting_energy_mj_mm3 > 0.0:
            raise ConfigError("canal.cutting_energy_mj_mm3", self.cutting_energy_mj_mm3, "> 0")
        for name in ("rub_mnm_per_mm", "screw_n_per_mnm", "withdraw_deadband_mm",
                     "support_mm_per_n", "drag_depth_mm", "drag_still_coulomb_n"):
            if not getattr(self, name) >= 0.0:
                raise ConfigError(f"canal.{name}", getattr(self, name), ">= 0")
        if self.support_y_mm_per_n is not None and not self.support_y_mm_per_n >= 0.0:
            raise ConfigError("canal.support_y_mm_per_n", self.support_y_mm_per_n,
                              ">= 0 (or none: the same as support_mm_per_n)")
        if self.curve_start_mm is not None and not (
            0.0 <= self.curve_start_mm < self.working_length_mm and self.curve_radius_mm > 0.0
        ):
            raise ConfigError("canal.curve_start_mm", self.curve_start_mm,
                              "0 <= start < working length, radius > 0")


#: Constants a phantom's material sets, and what each is (units in the CanalParams fields).
MATERIAL_FIELDS = ("cutting_energy_mj_mm3", "torque_mnm_per_mm2", "torque_mnm_s_per_mm3",
                   "torque_mnm_per_mm3", "rub_mnm_per_mm", "screw_n_per_mnm",
                   "axial_n_per_mm2", "axial_n_per_mm3", "c_fwd_per_rev")
#: Phantom materials: overrides of the CanalParams defaults (which are ``resin``).
#:
#: ``acrylic``: the thesis's experiment 2 root phantoms (6.3). assumption: no measured values
#: exist for them; the constants are calibrated against the outcome of Table 6.5 and the
#: thesis's account of file fracture (chapter 5), not against single readings:
#:
#: - harder to cut than the training resin (``u_s`` 3000 mJ/mm^3) and stiffer to wedge
#:   (``k_A`` 40 mNm/mm^2): the file advances only as fast as it cuts;
#: - the flutes rub every wall they touch (2.2 mNm per mm of contact): the torque to turn the
#:   file grows with its depth, so a desired torque caps the depth it can be fed to within the
#:   time (about 14 mm at tau_d = 40 mNm, past 16 mm at 50);
#: - they screw in with 0.007 N per mNm on their edges: less than the feedrate PD's 0.025 N
#:   per mNm (so the PD alone holds the file at ``kp tau_d / (kp - screw)``, 1.4 tau_d,
#:   which is past the 62 mNm strength for tau_d = 50 and past the reversal threshold for
#:   both), and at most 0.43 N at the strength, under the PD's 0.5 N pull-back;
#: - debris hardly holds the file axially (0.1 N per mm^3).
MATERIALS: dict[str, dict[str, float]] = {
    "resin": {},
    "acrylic": {"cutting_energy_mj_mm3": 3000.0, "torque_mnm_per_mm2": 40.0,
                "torque_mnm_s_per_mm3": 100.0, "rub_mnm_per_mm": 2.2,
                "screw_n_per_mnm": 0.007, "axial_n_per_mm3": 0.1},
}


def material_params(name: str, **overrides: float) -> dict[str, float]:
    """CanalParams keyword arguments of material ``name`` with ``overrides`` on top."""
    if name not in MATERIALS:
        raise ConfigError("phantom.material", name, f"one of {', '.join(MATERIALS)}")
    bad = set(overrides) - set(MATERIAL_FIELDS)
    if bad:
        raise ConfigError("phantom.material", min(bad),
                          f"a material constant: {', '.join(MATERIAL_FIELDS)}")
    return {**MATERIALS[name], **overrides}


@dataclass
class Interaction:
    """What the canal does to the file this step (phantom frame {P}, N, mm, mNm)."""

    depth_mm: float = -1.0          # tip depth along the canal (arc length), < 0 outside
    f_lat: tuple = (0.0, 0.0, 0.0)  # lateral force on the file, {P}
    contact_from_tip_mm: float = 0.0
    # sum over the lateral loads of (distance from the tip along the file, mm) x (load, N),
    # {P}: the moment of the lateral loads about the tip is -axis x m_lat (N*mm)
    m_lat: tuple = (0.0, 0.0, 0.0)
    f_axial_n: float = 0.0          # pushes the file out, along -file axis
    resist_mnm: float = 0.0         # torque the canal resists forward rotation with (>= 0)
    engagement_mm2: float = 0.0
    max_strain: float = 0.0


class Canal:
    """Tooth phantom canal state (lumen per slice, debris) and its file interaction.

    The state lives in arrays (:mod:`dentibot.sim.canal_kernels`: ``R``, the slices' ``h``,
    the state ``st`` and the constants ``cp``); the laws are the compiled kernels there, which
    the methods here call."""

    def __init__(self, params: CanalParams = CanalParams()) -> None:
        self.p = p = params
        ds = p.slice_mm
        self.bottom_mm = p.working_length_mm + p.apex_margin_mm
        n = math.ceil(self.bottom_mm / ds)
        self.n = n
        self.s = (np.arange(n) + 0.5) * ds                       # slice centres (mm)
        wl = p.working_length_mm
        dist_wl = np.maximum(wl - self.s, 0.0)
        self.R0 = (p.initial_apical_mm + p.initial_taper * dist_wl) / 2.0
        self.Rt = (p.target_apical_mm + p.target_taper * dist_wl) / 2.0
        self.R = self.R0.copy()
        self.in_wl = self.s <= wl
        self.width0 = 2.0 * (self.R0 + p.stain_mm) * ds * self.in_wl   # red area before
        self._red_buf = np.empty(n)
        self.red0 = kern.red_area(self.R, self.R0, self.width0, p.stain_mm, self._red_buf)
        self.pulp0 = float(self._pulp().sum())
        ct, st = math.cos(math.radians(p.tilt_deg)), math.sin(math.radians(p.tilt_deg))
        self.t0 = (0.0, -st, ct)                                   # Rx(tilt) z
        self.u = (1.0, 0.0, 0.0)                                   # Rx(tilt) x
        self.v = (0.0, ct, st)                                     # t0 x u
        if p.curve_start_mm is None or p.curve_angle_deg == 0.0:
            self.n_straight = n
            self.kappa = np.zeros(n)
        else:
            self.n_straight = int(p.curve_start_mm / ds)
            arc_end = p.curve_start_mm + p.curve_radius_mm * math.radians(p.curve_angle_deg)
            self.kappa = np.where((self.s >= p.curve_start_mm) & (self.s <= arc_end),
                                  1.0 / p.curve_radius_mm, 0.0)
        self.curved = bool(self.kappa.any())
        self._drag = bool(p.drag_n_s_per_mm or p.drag_coulomb_n or p.drag_still_coulomb_n
                          or p.drag_lat_n_s_per_mm
                          or p.bottom_torque_mnm_per_n)
        self.st = np.zeros(len(kern.STATE_FIELDS))
        self.st[kern.S["last_depth"]] = -1.0
        #: whether the file turns (set by the world each step): a still file sticks
        self.st[kern.S["turning"]] = 1.0
        self.cp = _param_array(self)
        self._out = np.zeros(len(kern.OUT_FIELDS))
        self._out[kern.O["depth_mm"]] = -1.0          # no file in the canal yet
        self._h = np.zeros(n)
        self._beam = None
        self._file_key = None

    # the state, by name (the kernels' arrays hold it)
    debris_mm3 = scalar("st", kern.S["debris"], doc="Debris in the canal (mm^3).")
    _last_depth = scalar("st", kern.S["last_depth"])
    _feed = scalar("st", kern.S["feed"])
    _slip = scalar("st", kern.S["slip"])
    _tau_cut = scalar("st", kern.S["tau_cut"])
    _tau_edges = scalar("st", kern.S["tau_edges"])
    _entered = scalar("st", kern.S["entered"], bool)
    turning = scalar("st", kern.S["turning"], bool, "Whether the file turns (set by the world "
                     "each step): a still file sticks.")
    version = scalar("st", kern.S["version"], int, """Counts the changes of the lumen ``R``
        (each :meth:`cut` that removes material; code that writes ``R`` itself adds one
        too): what is derived from the lumen alone (completeness, shaping) is the same while
        it is unchanged, so a caller may keep it keyed on this
        (:meth:`dentibot.sim.world.World.completeness`).""")

    # ------------------------------------------------------------------ pulp
    def red_area_mm2(self) -> np.ndarray:
        """Red area per slice to the working length (mm^2) as photographed: the projected
        stained canal, scaled by the stain left on its wall."""
        return self._red()[self.in_wl]

    def _red(self) -> np.ndarray:
        out = np.empty(self.n)
        kern.red_area(self.R, self.R0, self.width0, self.p.stain_mm, out)
        return out

    def completeness(self) -> float:
        """Eq 6.1: (red area before - red area now) / red area before, in [0, 1]
        (:func:`dentibot.sim.canal_kernels.red_area`)."""
        red = kern.red_area(self.R, self.R0, self.width0, self.p.stain_mm, self._red_buf)
        return (self.red0 - red) / self.red0

    def _pulp(self) -> np.ndarray:
        return np.where(self.in_wl, np.pi * np.maximum(self.Rt**2 - self.R**2, 0.0), 0.0)

    def pulp_mm3(self) -> float:
        """Volume (mm^3) between the lumen and the target preparation, to the working length."""
        return float(self._pulp().sum()) * self.p.slice_mm

    def shaping(self) -> float:
        """Removed fraction of the volume between the initial lumen and the target
        preparation, in [0, 1]; 1 for a canal that already had the target's shape."""
        if self.pulp0 <= 0.0:
            return 1.0
        return (self.pulp0 - float(self._pulp().sum())) / self.pulp0

    def centreline_point(self, depth_mm: float) -> tuple[float, float, float]:
        """Centreline point at arc length ``depth_mm`` in {P} (mm)."""
        p = self.p
        t0, u = self.t0, self.u
        if not self.curved or depth_mm <= p.curve_start_mm:
            return tuple(depth_mm * a for a in t0)
        rho = p.curve_radius_mm
        phi = min(depth_mm - p.curve_start_mm, rho * math.radians(p.curve_angle_deg)) / rho
        rest = depth_mm - p.curve_start_mm - rho * phi
        along = p.curve_start_mm + rho * math.sin(phi) + rest * math.cos(phi)
        side = rho * (1.0 - math.cos(phi)) + rest * math.sin(phi)
        return tuple(along * a + side * b for a, b in zip(t0, u))

    # ------------------------------------------------------------------ interaction
    def _prepare(self, f: NiTiFile) -> None:
        # h_i = -(taper/2) s_i - R_i, so that r_f - R = h_i + (d_tip + taper s_tip)/2.
        self._h = -(f.taper / 2.0) * self.s - self.R
        beam = f.beam
        step, b0, b1, b2 = beam.integrals
        self._beam = (b0, b1, b2)
        cp, P = self.cp, kern.P
        cp[P["file_tip_mm"]] = f.tip_diameter_mm
        cp[P["file_taper"]] = f.taper
        cp[P["file_length_mm"]] = beam.length_mm
        cp[P["beam_step_mm"]] = step
        self._file_key = f

    def interact(self, tip, axis, f: NiTiFile, dt: float) -> Interaction:
        """Geometry and resistances for the file at ``tip`` (mm) along unit ``axis`` in {P}
        (:func:`dentibot.sim.canal_kernels.interact`).

        ``axis`` points from the handpiece to the tip (into the tooth). ``dt`` (s) is the
        period, used for the feed rate.

        The file is a straight line in the straight part of the canal: the walls' lateral
        loads act at the ends of its part in the canal (the orifice and the tip: a straight
        line in a tapered lumen, bent by end loads, meets the walls there first), each with
        the wall stiffness of the slices that penetrate in its half. The file is a tapered
        cantilever clamped at the shank (:meth:`NiTiFile.compliance_mm_n`), on a tooth whose
        support adds the same compliance to every pair (``support_mm_per_n``): the loads
        ``lambda_j`` (along the inward normal ``-n_j``) bend it, and where it touches the
        wall's penetration is what the bending leaves,
        ``lambda_j / k_j = pen_j - sum_k c(j, k) (n_j . n_k) lambda_k``, with ``lambda >= 0``
        and no penetration where there is no load (a two-contact linear complementarity
        problem, solved by active sets: a contact the bending presses into the wall joins, one
        that would pull leaves; :func:`dentibot.sim.canal_walls.wall_loads`). A file crossing
        the canal's axis (a handpiece tilted from a tilted canal) is pushed one way near the
        orifice and the other way at the tip: a couple, whose moment about the tip turns the
        handpiece towards the canal's direction under admittance control (thesis 4.4), and
        which a single resultant force would lose.
        """
        if self._file_key is not f:
            self._prepare(f)
        b0, b1, b2 = self._beam
        kern.interact(self.st, self.cp, self.R, self._h, self.s, self.kappa, b0, b1, b2,
                      tip[0], tip[1], tip[2], axis[0], axis[1], axis[2], dt, self._out)
        return interaction_of(self)

    def cut(self, revolutions: float) -> float:
        """Apply ``revolutions`` of file rotation (signed, + cutting) after ``interact``.

        Forward rotation removes ``tau_c * 2 pi revolutions / u_s`` (mm^3) from the engaged
        slices in proportion to their overlap, at most the overlap itself. Returns the removed
        volume (mm^3) (:func:`dentibot.sim.canal_kernels.cut`).
        """
        return kern.cut(self.st, self.cp, self.R, self._h, float(revolutions))

    def screw_in_n(self, revolutions: float) -> float:
        """Axial pull (N, into the canal) of the engaged flutes for this step's rotation:
        ``screw`` times the torque on their helical edges (cutting and rubbing, not debris)
        turning forward, ``-reverse_factor`` times that turning back
        (:func:`dentibot.sim.canal_kernels.screw_in_n`)."""
        return kern.screw_in_n(self.st, self.cp, float(revolutions))


def interaction_of(canal: Canal) -> Interaction:
    """The canal's last outcome (the kernels' ``out`` array) as an :class:`Interaction`."""
    o = canal._out.tolist()
    return Interaction(o[0], (o[1], o[2], o[3]), o[4], (o[5], o[6], o[7]), o[8], o[9], o[10],
                       o[11])


def _param_array(canal: Canal) -> np.ndarray:
    """The canal's constants as :data:`dentibot.sim.canal_kernels.PARAM_FIELDS` lists them
    (the file's are filled in when a file enters: ``Canal._prepare``)."""
    p = canal.p
    sup_y = p.support_mm_per_n if p.support_y_mm_per_n is None else p.support_y_mm_per_n
    derived = {
        "n": canal.n, "n_straight": canal.n_straight, "curved": canal.curved,
        "bottom_mm": canal.bottom_mm, "drag": canal._drag,
        **{f"t0{a}": x for a, x in zip("xyz", canal.t0)},
        **{f"u{a}": x for a, x in zip("xyz", canal.u)},
        **{f"v{a}": x for a, x in zip("xyz", canal.v)},
        "support_extra_y_mm_per_n": sup_y - p.support_mm_per_n,
        "file_tip_mm": 0.0, "file_taper": 0.0, "file_length_mm": 0.0, "beam_step_mm": 0.0,
    }
    return np.array([float(derived[k] if k in derived else getattr(p, k))
                     for k in kern.PARAM_FIELDS])
