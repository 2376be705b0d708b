"""The tracker's anchor calibration: its pose set identifies every anchor, on the built-in
simulator (lock step) it finds the simulated tracker's true anchors when the nominal ones
are off by 1-2 mm, the protocol step applies them, and it is refused without a tracker."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dentibot.app.procedure import Procedure
from dentibot.app.simulated import plan_config
from dentibot.app.steps import StepExecutor
from dentibot.app.tracker_calibration import identify, move_matrix, pose_set
from dentibot.app.tracking import sim_tooth_config
from dentibot.control.strings import StringGeometry, lengths, ring_geometry
from dentibot.errors import ConfigError, IdentificationError
from dentibot.protocol.loader import ProtocolFileError, parse_protocol
from dentibot.protocol.schema import CalibrateTrackerStep
from dentibot.sim.tracker_device import TrackerSimParams
from dentibot.sim.world import World, WorldConfig

#: The device file's (the drawing's) anchors: the simulator's default ring.
NOMINAL = ring_geometry(40.0, 15.0, 30.0, -5.0)


def _offsets(rng, n: int = 6) -> np.ndarray:
    """n displacements in random directions, 1 to 2 mm long."""
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1)[:, None] * rng.uniform(1.0, 2.0, (n, 1))


def _rigid_fit_error(found: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``found`` moved by the rigid transform that best fits it to ``true``, minus ``true``
    (the tooth anchors are defined up to the clamp frame's choice)."""
    cf, ct = found.mean(axis=0), true.mean(axis=0)
    rot, _ = Rotation.align_vectors(true - ct, found - cf)
    return rot.apply(found - cf) + ct - true


def _flange_poses(world: World, moves) -> list[np.ndarray]:
    """0T_6 of each move of the tool frame about the file tip, from the world's home pose."""
    t0h = world.kin.fk_tool(world.config.q0_deg)
    return [t0h @ move_matrix(r, t) @ np.linalg.inv(world.kin.tool) for r, t in moves]


#: The clamp's set-up position in the mount, as a device file gives it (mm): the first guess.
SET_UP = np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 90.0], [0, 0, 0, 1]])


def test_the_pose_set_identifies_every_anchor_and_translations_alone_do_not():
    rng = np.random.default_rng(1)
    true = StringGeometry(NOMINAL.mount_mm + _offsets(rng), NOMINAL.tooth_mm + _offsets(rng))
    w = World()
    moves = pose_set()
    flanges = _flange_poses(w, moves)
    t0t = w.phantom_pose                          # the clamp, static in the base frame
    exact = np.array([lengths(true, np.linalg.inv(f) @ t0t) for f in flanges])
    found = identify(NOMINAL, flanges, exact, start_pose=SET_UP)
    # the mount anchors are absolute in {M}; the tooth anchors up to the clamp frame's choice
    np.testing.assert_allclose(found.geometry.mount_mm, true.mount_mm, atol=1e-6)
    np.testing.assert_allclose(_rigid_fit_error(np.asarray(found.geometry.tooth_mm),
                                                true.tooth_mm), 0.0, atol=1e-6)
    assert found.rms_mm < 1e-8 and found.ok
    assert max(s.condition for s in found.strings) < 1e3
    # the turns are what separate a mount anchor from a tooth anchor
    shifts = [(r, t) for r, t in moves if not np.any(r)]
    flanges = _flange_poses(w, shifts)
    exact = np.array([lengths(true, np.linalg.inv(f) @ t0t) for f in flanges])
    with pytest.raises(IdentificationError, match="same orientation"):
        identify(NOMINAL, flanges, exact, start_pose=SET_UP)


async def test_the_simulated_set_up_gives_the_true_anchors_within_the_noise():
    rng = np.random.default_rng(0)
    da, db = _offsets(rng), _offsets(rng)
    sim = TrackerSimParams(mount_mm=NOMINAL.mount_mm + da, tooth_mm=NOMINAL.tooth_mm + db,
                           seed=0)
    world = World(WorldConfig(seed=0))
    cfg = plan_config(world)
    # the runtime knows the drawing's anchors only
    cfg = dataclasses.replace(cfg, tooth=dataclasses.replace(sim_tooth_config(world, sim),
                                                             geometry=NOMINAL))
    async with Procedure.simulated(world, cfg, tracker=sim) as proc:
        steps = StepExecutor(proc)
        await steps.step("calibrate_tracker", CalibrateTrackerStep())
        rt = proc.runtime
        assert rt.state == "idle", rt.treatment.fault_causes
        q_end = np.array(rt.last.q_deg)
    res = steps.tracker_calibration
    assert res is not None and res.ok
    np.testing.assert_allclose(q_end, world.config.q0_deg, atol=0.01)    # back at the start
    # a reading's noise: the 0.01 mm step's quantisation and 0.003 mm rms, averaged over
    # the hold's 50 readings
    per_read = np.hypot(sim.resolution_mm / np.sqrt(12.0), sim.noise_mm)
    averaged = per_read / np.sqrt(0.1 / world.ts)
    assert 0.3 * averaged < res.rms_mm < 3.0 * averaged
    mount_std = np.array([s.mount_std_mm for s in res.strings])
    tooth_std = np.array([s.tooth_std_mm for s in res.strings])
    assert mount_std.max() < 0.1 and tooth_std.max() < 0.1    # well under the 1-2 mm offsets
    err_a = np.asarray(res.geometry.mount_mm) - sim.mount_mm
    err_b = _rigid_fit_error(np.asarray(res.geometry.tooth_mm), sim.tooth_mm)
    assert np.all(np.abs(err_a) <= 4.0 * mount_std)
    assert np.all(np.abs(err_b) <= 4.0 * tooth_std)
    assert np.abs(err_a).max() < 0.2 and np.abs(err_b).max() < 0.2
    # the nominal anchors were off by the offsets: the calibration took them out
    assert np.linalg.norm(err_a, axis=1).max() < 0.15 * np.linalg.norm(da, axis=1).min()
    # the runtime tracks with the identified anchors from now on
    np.testing.assert_allclose(rt.cfg.tooth.geometry.mount_mm, res.geometry.mount_mm)
    assert rt.ctx.tooth.cfg is rt.cfg.tooth
    # the report and the device file's format
    assert "PASS" in res.report() and res.anchors_yaml().count("  - [") == 12


def test_a_protocol_without_the_tracker_is_refused_at_the_step():
    with pytest.raises(ProtocolFileError) as err:
        parse_protocol("name: t\nsteps:\n  - calibrate_tracker: {}\n")
    (_, field, text), = err.value.problems
    assert field == "steps.0.calibrate_tracker"
    assert "patient.tracker = False" in text and "patient tracker" in text
    # with it, and before the load calibration (position moves: no force law), accepted
    p = parse_protocol("name: t\npatient: {tracker: true}\nsteps:\n"
                       "  - calibrate_tracker: {rotation_deg: 8}\n  - calibrate_load: {}\n")
    assert p.steps[0].kind == "calibrate_tracker" and p.steps[0].spec.rotation_deg == 8


async def test_the_step_on_a_procedure_without_a_tracker_is_refused_before_any_motion():
    async with Procedure.simulated() as proc:
        with pytest.raises(ConfigError, match="patient.tracker"):
            await StepExecutor(proc).step("calibrate_tracker", CalibrateTrackerStep())
        assert proc.runtime.ticks == 0


TRACKER_SECTION = """tracker:   # the encoders
  interface: socketcand
  node_ids: [0x21, 0x22, 0x23, 0x24, 0x25, 0x26]
  mount_anchors_mm:            # a_i in {M}
    - [6.95, 39.39, 30.0]
    - [-6.95, 39.39, 30.0]
    - [-37.59, -13.68, 30.0]
    - [-30.64, -25.71, 30.0]
    - [30.64, -25.71, 30.0]
    - [37.59, -13.68, 30.0]
  # the clamp
  tooth_anchors_mm: [[11.49, 9.64, -5.0], [-11.49, 9.64, -5.0], [-14.10, 5.13, -5.0],
                     [-2.60, -14.77, -5.0], [2.60, -14.77, -5.0], [14.10, 5.13, -5.0]]
  resolution_mm: 0.01
"""


def test_the_anchors_are_written_into_the_device_file_and_the_rest_is_kept(tmp_path):
    import yaml

    from dentibot.cli.tracker import write_anchors
    from dentibot.io.devices import load_devices_config, loopback_config

    base = yaml.safe_dump(loopback_config().model_dump(mode="json", exclude_none=True),
                          sort_keys=False)
    path = tmp_path / "devices.yaml"
    path.write_text(base + TRACKER_SECTION + "# the end\n", encoding="utf-8")
    rng = np.random.default_rng(2)
    mount = NOMINAL.mount_mm + _offsets(rng)
    tooth = NOMINAL.tooth_mm + _offsets(rng)
    write_anchors(path, mount, tooth)
    t = load_devices_config(path).tracker
    np.testing.assert_allclose(t.mount_anchors_mm, mount, atol=5e-4)
    np.testing.assert_allclose(t.tooth_anchors_mm, tooth, atol=5e-4)
    assert t.node_ids == [0x21, 0x22, 0x23, 0x24, 0x25, 0x26] and t.resolution_mm == 0.01
    text = path.read_text(encoding="utf-8")
    assert text.startswith(base) and text.endswith("# the end\n")
    assert "# the encoders" in text and "# a_i in {M}" in text and "# the clamp" in text


async def test_a_clamp_that_moves_during_a_hold_stops_the_calibration_with_a_fault():
    async with Procedure.simulated(WorldConfig(motion="head"),
                                   tracker=TrackerSimParams()) as proc:
        steps = StepExecutor(proc)
        await steps.step("calibrate_tracker", CalibrateTrackerStep())
        rt = proc.runtime
        assert rt.state == "fault" and steps.tracker_calibration is None
        assert "the clamp or the mount moved" in rt.treatment.fault_causes[-1]
        await proc.run_for(ticks=2)
        assert rt.mode.arm == "stop" and not proc.world.arm.moving
