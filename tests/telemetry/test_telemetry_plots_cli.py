"""Figures (valid PNG files, skipped when their data are absent) and the report/plot commands."""

from __future__ import annotations

import json
import struct

import pytest
from telemetry_helpers import ramp_row

from dentibot.cli import main
from dentibot.telemetry import McapRecorder
from dentibot.telemetry.plots import FIGURES, plot_recording

pytestmark = pytest.mark.timeout(60)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE
    assert data[12:16] == b"IHDR"                      # first chunk: the image header
    width, height = struct.unpack(">II", data[16:24])
    assert data.rstrip(b"\x00")[-8:-4] == b"IEND"      # complete file
    return width, height


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("runs") / "run.mcap"
    with McapRecorder(path, {"protocol": "demo", "rate_hz": 500, "tau_d_mnm": 40.0}) as rec:
        for i in range(300):
            rec.record(ramp_row(i))
        rec.event("transition", "approach -> drilling", t=0.2, tick=100)
    return path


@pytest.fixture(scope="module")
def hardware_recording(tmp_path_factory):
    """As recorded on hardware: no phantom pose, no depth."""
    path = tmp_path_factory.mktemp("runs") / "hw.mcap"
    with McapRecorder(path, {"rate_hz": 500}) as rec:
        for i in range(100):
            rec.record(ramp_row(i, phantom_pose=None, depth_mm=None, completeness=None))
    return path


def test_plot_writes_every_figure_as_a_valid_png(recording, tmp_path):
    written = plot_recording(recording, tmp_path / "figs")
    assert written.skipped == {}
    assert [p.name for p in written] == [f"run-{name}.png" for name in FIGURES]
    for path in written:
        width, height = _png_size(path)
        assert width > 100 and height > 100


def test_figures_without_data_are_skipped_with_a_reason(hardware_recording, tmp_path):
    written = plot_recording(hardware_recording, tmp_path)
    assert set(written.skipped) == {"position_vs_root"}
    assert "phantom" in written.skipped["position_vs_root"]
    assert len(written) == len(FIGURES) - 1           # force vs position: along the file axis
    for path in written:
        _png_size(path)


def test_cli_report_table_and_json(recording, capsys):
    assert main(["report", str(recording)]) == 0
    out = capsys.readouterr().out
    assert "DentiBot run: ok" in out and "whole run" in out
    assert main(["report", str(recording), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["status"] == "ok" and d["duration_s"] == 300 / 500
    assert [s["name"] for s in d["steps"]] == ["approach", "drilling"]
    assert d["events"] == {"transition": 1}


def test_cli_plot(hardware_recording, tmp_path, capsys):
    out_dir = tmp_path / "out"
    assert main(["plot", str(hardware_recording), "--out", str(out_dir)]) == 0
    out = capsys.readouterr().out
    assert out.count("wrote ") == len(FIGURES) - 1 and "skipped position_vs_root" in out
    assert len(list(out_dir.glob("*.png"))) == len(FIGURES) - 1


@pytest.mark.parametrize("command", ["report", "plot"])
def test_cli_errors_exit_2_with_a_message(command, tmp_path, capsys):
    extra = ["--out", str(tmp_path)] if command == "plot" else []
    assert main([command, str(tmp_path / "missing.mcap"), *extra]) == 2
    assert "no such file" in capsys.readouterr().err
    junk = tmp_path / "junk.mcap"
    junk.write_text("not a recording")
    assert main([command, str(junk), *extra]) == 2
    assert "not an MCAP file" in capsys.readouterr().err


def test_the_torque_figure_shows_the_limit_in_force_beside_the_files_strength(tmp_path):
    from matplotlib.figure import Figure

    from dentibot.telemetry.plots import _fig_torque_feed
    from dentibot.telemetry.reader import read_recording

    path = tmp_path / "limits.mcap"
    meta = {"protocol": "demo", "rate_hz": 500, "file_torque_limit_mnm": 62.0,
            "torque_limit_mnm": 55.8, "tau_d_mnm": 40.0}
    with McapRecorder(path, meta) as rec:
        for i in range(50):
            rec.record(ramp_row(i))
    fig = Figure()
    assert _fig_torque_feed(read_recording(path), fig) is None
    lines = {ln.get_label(): ln.get_ydata()[0] for ln in fig.axes[0].get_lines()}
    assert lines["file strength 62 mNm"] == 62.0
    assert lines["limit in force 55.8 mNm"] == 55.8
    assert lines["tau_d 40 mNm"] == 40.0
