"""A protocol's patient tracker: depth in the tooth's frame on the built-in simulator, a
warning without it, and a device file that must have a tracker when the protocol asks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dentibot.app.runner import ProtocolRunner
from dentibot.app.tracking import tooth_config_from_devices
from dentibot.errors import ConfigError
from dentibot.io.devices import TrackerConfig, loopback_config
from dentibot.protocol.loader import parse_protocol
from dentibot.telemetry.reader import read_recording

SHORT = "name: t\n{patient}steps:\n  - align: {{duration_s: 0.3}}\n  - drill: {{}}\n"


@pytest.mark.slow
async def test_a_tracked_protocol_measures_depth_in_the_tooth(tmp_path):
    p = parse_protocol(SHORT.format(patient="patient: {tracker: true}\n"
                                            "phantom: {working_length_mm: 8}\n"))
    runner = ProtocolRunner(p, recording=tmp_path / "t.mcap")
    result = await runner.run()
    assert result.summary.status == "ok"
    assert result.summary.depth_reached_mm == pytest.approx(8.0, abs=0.05)
    rec = read_recording(tmp_path / "t.mcap")
    assert rec.metadata["depth_frame"] == "tooth"
    true = [r["true_depth_mm"] for r in rec.rows if r["true_depth_mm"] is not None]
    assert max(true) <= 8.0 + 0.2                        # the working length, in the tooth
    assert all(r["tooth_pose"] is not None for r in rec.rows)


async def test_without_a_tracker_the_run_says_the_working_length_is_unprotected(capsys):
    from dentibot.logs import configure_logging

    configure_logging("warning")
    p = parse_protocol("name: t\nsteps:\n  - align: {duration_s: 0.3}\n"
                       "  - drill: {rounds: [{duration_s: 0.2}]}\n")
    result = await ProtocolRunner(p, no_record=True).run()
    assert result.summary.status == "ok"
    assert "not protected against the patient moving along the canal" in capsys.readouterr().err


def test_a_tracked_protocol_on_devices_needs_the_tracker_section():
    p = parse_protocol(SHORT.format(patient="patient: {tracker: true}\n")
                       .replace("steps:\n", "steps:\n  - calibrate_load: {}\n"))
    with pytest.raises(ConfigError, match="tracker section"):
        ProtocolRunner(p, devices=loopback_config(), no_record=True)


def test_the_device_files_tracker_gives_the_runtime_its_geometry():
    ring = [(40 * np.cos(a), 40 * np.sin(a), 30.0) for a in np.radians(range(0, 360, 60))]
    clamp = [(15 * np.cos(a), 15 * np.sin(a), -5.0) for a in np.radians(range(30, 390, 60))]
    t = TrackerConfig(interface="virtual", mount_anchors_mm=ring, tooth_anchors_mm=clamp,
                      mount_in_flange_mm=(0.0, 0.0, 12.0), mount_in_flange_deg=(0.0, 0.0, 90.0))
    c = tooth_config_from_devices(t)
    np.testing.assert_allclose(c.geometry.mount_mm, ring)
    np.testing.assert_allclose(c.mount_in_flange[:3, :3],
                               Rotation.from_euler("z", 90, degrees=True).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(c.mount_in_flange[:3, 3], (0.0, 0.0, 12.0))
    np.testing.assert_allclose(c.start_pose[:3, 3], (0.0, 0.0, 90.0))
    with pytest.raises(ConfigError, match="six strings"):
        tooth_config_from_devices(TrackerConfig(interface="virtual", mount_anchors_mm=ring[:3],
                                                tooth_anchors_mm=clamp[:3],
                                                node_ids=[0x21, 0x22, 0x23]))
