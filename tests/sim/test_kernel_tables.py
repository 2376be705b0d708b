"""The compiled kernels (the simulator's, the control tick's, the supervisor's) index their
state, parameter and output arrays by constants: each constant must be the position of its
field in the module's table (a field added in the middle shifts them all)."""

from __future__ import annotations

import numpy as np
import pytest

from dentibot.control import canal_axis_kernels
from dentibot.runtime import supervisor_kernels
from dentibot.sim import canal_kernels, ftsensor_kernels, handpiece_kernels, world_kernels

# (module, table, {constant: field})
TABLES = [
    (canal_kernels, "STATE_FIELDS", {
        "_FEED": "feed", "_LAST": "last_depth", "_SLIP": "slip", "_FLUSH": "flush_ref",
        "_DEBRIS": "debris", "_ENTERED": "entered", "_HAS_E": "has_last_e", "_EU": "last_eu",
        "_EV": "last_ev", "_TAU_CUT": "tau_cut", "_TAU_EDGES": "tau_edges", "_WIN0": "win_i0",
        "_WIN1": "win_i1", "_WINC": "win_c", "_TURNING": "turning", "_VERSION": "version",
        "S_TURNING": "turning"}),
    (canal_kernels, "PARAM_FIELDS", {
        "_DS": "slice_mm", "_N": "n", "_DRAG": "drag", "_T0X": "t0x", "_UX": "ux", "_VX": "vx",
        "_FEED_TAU": "feed_filter_s", "_MU": "friction_mu", "_SUPPORT_Y":
        "support_extra_y_mm_per_n", "_U_S": "cutting_energy_mj_mm3", "_REVERSE":
        "reverse_factor", "_F_TIP": "file_tip_mm", "_B_STEP": "beam_step_mm",
        "P_DRAG": "drag", "P_REVERSE": "reverse_factor"}),
    (canal_kernels, "OUT_FIELDS", {
        "OUT_DEPTH": "depth_mm", "OUT_FX": "f_lat_x", "OUT_CONTACT": "contact_from_tip_mm",
        "OUT_MX": "m_lat_x", "OUT_AXIAL": "f_axial_n", "OUT_RESIST": "resist_mnm",
        "OUT_ENGAGE": "engagement_mm2", "OUT_STRAIN": "max_strain"}),
    (handpiece_kernels, "STATE_FIELDS", {
        "_W": "omega_rpm", "_POS_MODE": "pos_mode", "_TORQUE": "torque_mnm",
        "_LIMIT": "current_limit_a", "_K": "k", "_T": "t", "S_OMEGA": "omega_rpm",
        "S_TORQUE": "torque_mnm"}),
    (handpiece_kernels, "PARAM_FIELDS", {"_TAU": "tau_s", "_WANDER_PHASE": "wander_phase"}),
    (ftsensor_kernels, "STATE_FIELDS", {
        "_LAST": "last0", "_RAW": "raw0", "_TARE": "tare0", "_STATUS": "status", "_K": "k"}),
    (ftsensor_kernels, "PARAM_FIELDS", {
        "_WEIGHT": "weight_n", "_RX": "rx_m", "_OFFSET": "offset0", "_RES": "res0",
        "_INV_RES": "inv_res0", "_RANGE": "range0", "_OFFSET_MM": "offset_mm",
        "_SATURATED": "saturated", "P_OFFSET_MM": "offset_mm"}),
    (world_kernels, "STATE_FIELDS", {
        "_TIP": "tip_x", "_AXIS": "axis_x", "_ORIGIN": "origin_x", "_RP": "rp00",
        "_CONTACT": "contact_x", "_EXT_TAU": "ext_tau_x", "_HAND": "hand_x", "_GRIP": "grip_x",
        "_FRACTURED": "fractured", "_FATIGUE": "fatigue_damage",
        "_FR_TORQUE": "fracture_torque", "_FR_DEPTH": "fracture_depth"}),
    (world_kernels, "PARAM_FIELDS", {
        "_TOOL_P": "tool_px", "_TOOL_Z": "tool_zx", "_FAT_C": "fatigue_c",
        "_FAT_B": "fatigue_b", "_STRENGTH": "torsional_strength_mnm"}),
    (canal_axis_kernels, "STATE_FIELDS", {
        "S_TARE": "tare_fx", "S_TARED": "tared", "S_LOAD": "load_fx", "S_LOADED": "loaded",
        "S_TILT": "tilt_x"}),
    (canal_axis_kernels, "PARAM_FIELDS", {
        "P_A_TARE": "a_tare", "P_A_LOAD": "a_load", "P_MAX_RATE": "max_rate", "P_HOLD": "hold",
        "P_STOP": "stop", "P_GAIN": "gain", "P_MIN_DEPTH": "min_depth"}),
    (supervisor_kernels, "INPUT_OUT_FIELDS", {
        "O_STALE": "stale_arm", "O_BAD_GROUP": "bad_group", "O_BAD_INDEX": "bad_index",
        "O_BAD_VALUE": "bad_value", "O_SATURATED": "saturated", "O_JUMP": "jump"}),
    (supervisor_kernels, "ESTIMATE_OUT_FIELDS", {
        "E_TAU_FT": "tau_ft", "E_DIFF": "tau_diff", "E_LATERAL": "lateral",
        "E_AXIAL": "axial", "E_SHOULDER": "shoulder", "E_ELBOW": "elbow", "E_WRIST": "wrist"}),
    (supervisor_kernels, "FRACTURE_FIELDS", {
        "F_FREE": "free_mnm", "F_FREE_N": "free_n", "F_HEAD": "head", "F_COUNT": "count"}),
    (supervisor_kernels, "TIP_FIELDS", {"T_HEAD": "head", "T_COUNT": "count", "T_BAD": "bad"}),
    (supervisor_kernels, "SPINDLE_FIELDS", {"SP_SINCE": "since", "SP_BAD": "bad",
                                            "SP_TOL": "tol"}),
]


@pytest.mark.parametrize("module, table, constants", TABLES,
                         ids=[f"{m.__name__.rsplit('.', 1)[1]}.{t}" for m, t, _ in TABLES])
def test_each_index_is_its_fields_position(module, table, constants):
    fields = getattr(module, table)
    assert len(set(fields)) == len(fields)
    for const, field in constants.items():
        assert getattr(module, const) == fields.index(field), (const, field)


def test_the_vectors_fields_are_consecutive():
    """Three components (and the rotation's nine) follow each other, as the kernels read
    them."""
    for fields in (world_kernels.STATE_FIELDS, ftsensor_kernels.STATE_FIELDS,
                   ftsensor_kernels.PARAM_FIELDS, canal_kernels.PARAM_FIELDS):
        for i, name in enumerate(fields):
            if name.endswith("_x") or (name.endswith("0x") and len(name) == 3):
                stem = name[:-1]
                assert fields[i + 1:i + 3] == (stem + "y", stem + "z"), name
    rp = world_kernels.STATE_FIELDS.index("rp00")
    assert world_kernels.STATE_FIELDS[rp:rp + 9] == tuple(
        f"rp{i}{j}" for i in range(3) for j in range(3))
    assert np.all(np.diff([ftsensor_kernels.PARAM_FIELDS.index(f"res{i}")
                           for i in range(6)]) == 1)
