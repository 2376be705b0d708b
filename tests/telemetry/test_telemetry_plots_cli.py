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


def test_cli_plot_json(hardware_recording, tmp_path, capsys):
    out_dir = tmp_path / "out"
    assert main(["plot", str(hardware_recording), "--out", str(out_dir), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert sorted(d["written"]) == sorted(str(p) for p in out_dir.glob("*.png"))
    assert len(d["written"]) == len(FIGURES) - 1
    assert list(d["skipped"]) == ["position_vs_root"] and "phantom" in d["skipped"][
        "position_vs_root"]


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
    meta = {"protocol": "demo", "rate_hz": 500, "file_strength_mnm": 62.0,
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


@pytest.fixture(scope="module")
def calibrated_recording(tmp_path_factory):
    """100 calibration rows that swing the tool 60 mm sideways, then 200 treatment rows that
    move it 2 mm: the treatment's 2 mm must fill the position figure."""
    path = tmp_path_factory.mktemp("runs") / "cal.mcap"
    with McapRecorder(path, {"rate_hz": 500}) as rec:
        for i in range(300):
            over = {}
            if i < 100:
                over = dict(step="1:calibrate_load", state="calibrating.load",
                            tool_pose=[190.0 + 0.6 * i, 0.0, 308.0, 0.0, 90.0, 0.0])
            rec.record(ramp_row(i, **over))
    return path


def test_calibration_moves_are_left_out_of_the_spatial_figures(calibrated_recording):
    from matplotlib.figure import Figure

    from dentibot.telemetry.plots import _fig_force_vs_position, _fig_position_vs_root
    from dentibot.telemetry.reader import read_recording

    rec = read_recording(calibrated_recording)
    fig = Figure()
    assert _fig_position_vs_root(rec, fig) is None
    x_tool = fig.axes[0].get_lines()[0].get_xydata()
    assert len(x_tool) == 200                              # the treatment rows only
    assert x_tool[0, 0] == pytest.approx(100 / 500)        # first row after calibration
    z_tool = fig.axes[2].get_lines()[0].get_ydata()
    assert z_tool.min() == pytest.approx(-0.01 * 199)      # 2 mm of treatment, from 0
    fig = Figure()
    assert _fig_force_vs_position(rec, fig) is None
    names = [ln.get_label() for ln in fig.axes[0].get_lines()]
    assert "calibrating.load" not in names


def test_force_scatters_get_one_colour_per_phase(recording):
    from matplotlib.figure import Figure

    from dentibot.telemetry.plots import _fig_force_vs_position, _fig_force_vs_velocity
    from dentibot.telemetry.reader import read_recording

    rec = read_recording(recording)
    for draw in (_fig_force_vs_position, _fig_force_vs_velocity):
        fig = Figure()
        assert draw(rec, fig) is None
        lines = fig.axes[0].get_lines()
        # ramp_row alternates feeding / pausing every 25 rows: both are treating.drilling
        assert [ln.get_label() for ln in lines] == ["treating.drilling"]
        assert len(lines[0].get_xdata()) == 300


def test_state_labels_never_overlap(tmp_path):
    """Bands of 1, 3 and 60 ticks with long names: the labels written do not overlap."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from dentibot.telemetry.plots import FIGURES, _fig_state_timeline
    from dentibot.telemetry.reader import read_recording

    path = tmp_path / "bands.mcap"
    lengths = [1, 3, 60, 2, 1, 40, 5, 1, 200] * 3
    states = ["treating.drilling.feeding", "treating.drilling.reversing",
              "treating.retracting", "self_aligning"]
    with McapRecorder(path, {"rate_hz": 500}) as rec:
        i = 0
        for k, n in enumerate(lengths):
            for _ in range(n):
                rec.record(ramp_row(i, state=states[k % len(states)], step=f"{k % 3}:step"))
                i += 1
    size, _draw = FIGURES["state_timeline"]
    fig = Figure(figsize=size)
    canvas = FigureCanvasAgg(fig)
    assert _fig_state_timeline(read_recording(path), fig) is None
    fig.tight_layout()
    canvas.draw()
    renderer = canvas.get_renderer()
    ax = fig.axes[0]
    texts = [t for t in ax.texts if t.get_visible()]
    assert texts                                           # the wide bands are labelled
    boxes = {0: [], 1: []}
    for t in texts:
        boxes[round(t.get_position()[1])].append(t.get_window_extent(renderer))
    for row in boxes.values():
        row.sort(key=lambda b: b.x0)
        for a, b in zip(row, row[1:]):
            assert a.x1 <= b.x0, "two state labels overlap"
