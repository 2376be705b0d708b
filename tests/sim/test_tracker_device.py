"""The in-process simulated patient tracker (lock step) against geometry derived here."""

from __future__ import annotations

import numpy as np
import pytest

from dentibot.control import strings
from dentibot.io.interfaces import (
    STRING_FAULT,
    STRING_OK,
    STRING_OVER_RANGE,
    STRING_SLACK,
    PatientTracker,
)
from dentibot.sim import SimPatientTracker, TrackerSimParams, World, WorldConfig

STEP = 0.01


def world_lengths(world: World, p: TrackerSimParams) -> np.ndarray:
    """Anchors carried to {0} by hand: a_i by the flange pose, b_i by the phantom's."""
    t0m = world.kin.fk(world.arm.q) @ p.mount_in_flange
    a0 = p.mount_mm @ t0m[:3, :3].T + t0m[:3, 3]
    rp = world.phantom_pose[:3, :3]
    t = p.tooth_in_phantom
    b_p = p.tooth_mm @ t[:3, :3].T + t[:3, 3]
    b0 = b_p @ rp.T + np.array(world.phantom_origin_0())
    return np.linalg.norm(a0 - b0, axis=1)


async def test_lock_step_lengths_follow_the_patient():
    w = World(WorldConfig(seed=2, motion="square"))
    p = TrackerSimParams(noise_mm=0.0)
    dev = SimPatientTracker(w, p)
    assert isinstance(dev, PatientTracker)
    s0 = await dev.read()
    assert s0.seq == 0 and s0.ok
    assert np.abs(np.array(s0.lengths_mm) - world_lengths(w, p)).max() <= STEP / 2 + 1e-9
    w.run(3.0)                                   # the square's first edge: +x at 3 mm/s
    s1 = await dev.read()
    assert s1.seq == w.steps == 1500 and s1.t == pytest.approx(3.0)
    assert np.abs(np.array(s1.lengths_mm) - world_lengths(w, p)).max() <= STEP / 2 + 1e-9
    assert np.abs(np.array(s1.lengths_mm) - s0.lengths_mm).max() > 1.0     # it moved
    # the pose from the lengths is the phantom's offset, 9 mm along the base x axis
    geo = strings.StringGeometry(p.mount_mm, p.tooth_mm)
    e0 = strings.forward(geo, s0.lengths_mm, np.eye(4) @ _start(), sigma_mm=STEP / np.sqrt(12))
    e1 = strings.forward(geo, s1.lengths_mm, e0.pose, sigma_mm=STEP / np.sqrt(12))
    r06 = w.flange_rotation
    moved_0 = r06 @ (e1.pose[:3, 3] - e0.pose[:3, 3])        # {M} axes = flange axes
    assert moved_0 == pytest.approx([9.0, 0.0, 0.0], abs=0.05)


def _start() -> np.ndarray:
    t = np.eye(4)
    t[2, 3] = 90.0
    return t


async def test_noise_is_seeded_and_of_the_stated_size():
    p = TrackerSimParams(noise_mm=0.02, seed=4)
    w = World(WorldConfig(seed=1))
    dev = SimPatientTracker(w, p)
    true = world_lengths(w, p)
    errs = []
    for _ in range(400):
        w.step()
        errs.append(np.array((await dev.read()).lengths_mm) - true)
    errs = np.array(errs)
    # quantisation (step^2/12) and noise add in variance
    assert errs.std() == pytest.approx(np.hypot(0.02, STEP / np.sqrt(12)), rel=0.1)
    # the same seed gives the same readings
    a, b = (SimPatientTracker(World(WorldConfig(seed=1)), TrackerSimParams(noise_mm=0.02, seed=4))
            for _ in range(2))
    for dev_ in (a, b):
        dev_.world.run(0.1)
    assert (await a.read()).counts == (await b.read()).counts


async def test_faults_broken_held_and_stopped_strings():
    w = World(WorldConfig(seed=1))
    dev = SimPatientTracker(w, TrackerSimParams(noise_mm=0.0))
    dev.model.broken.add(0)
    dev.model.held_mm[3] = 500.0
    dev.stopped.add(5)
    s = await dev.read()
    assert s.status == (STRING_SLACK, STRING_OK, STRING_OK, STRING_OVER_RANGE, STRING_OK,
                        STRING_FAULT)
    assert s.counts[0] == 0 and s.lengths_mm[0] == 20.0
    assert s.counts[3] == 29_999
    await dev.recover()
    assert (await dev.read()).status[5] == STRING_OK
