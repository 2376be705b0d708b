"""The Python API (dentibot.api): a protocol run from plain code and from inside a running
event loop (as in Jupyter), its recording as typed tables, quiet logging by default, and an
experiment's result, in this process, as ``dentibot experiment --json`` gives it."""

from __future__ import annotations

import asyncio
import json
import sys
import threading
import time

import numpy as np
import pyarrow as pa
import pytest
import structlog

from dentibot.api import (
    configure_logging,
    open_recording,
    run_experiment,
    run_experiment_async,
    run_protocol,
    run_protocol_async,
)
from dentibot.cli import main
from dentibot.errors import ConfigError
from dentibot.telemetry.reader import read_recording
from dentibot.telemetry.schema import EVENT_FIELDS, TICK_FIELDS

RATE_HZ = 500.0
#: load calibration, then 0.6 s of planned motion: about 7 s simulated, under 1 s of wall time
SHORT = """\
name: api-short
seed: 3
phantom: {working_length_mm: 8.0, orifice_gap_mm: 2.0}
steps:
  - calibrate_load: {}
  - drag: {duration_s: 0.4, hand_force_n: [0.0, 0.2, 0.0]}
  - align: {duration_s: 0.2, fz_n: 1.0}
"""


@pytest.fixture(autouse=True)
def _fresh_logging():
    """structlog as in a fresh interpreter (its default prints everything to stdout)."""
    structlog.reset_defaults()
    yield
    structlog.reset_defaults()


@pytest.fixture
def protocol_file(tmp_path):
    path = tmp_path / "short.yaml"
    path.write_text(SHORT)
    return path


def test_a_run_from_plain_code_records_every_tick_and_prints_nothing(protocol_file, tmp_path,
                                                                     capsys):
    out = tmp_path / "run.mcap"
    result = run_protocol(protocol_file, out=out)
    assert result.summary.status == "ok" and result.exit_code == 0
    assert result.recording == out and out.is_file()
    assert capsys.readouterr().out == ""

    rec = open_recording(out)
    assert rec.complete and rec.status == "ok" and rec.problems == []
    assert rec.metadata["protocol"] == "api-short" and rec.metadata["rate_hz"] == RATE_HZ
    ticks = rec.ticks
    assert isinstance(ticks, pa.Table)
    assert ticks.column_names == [f.name for f in TICK_FIELDS]
    assert ticks.schema.field("t").type == pa.float64()
    assert ticks.schema.field("tick").type == pa.int64()
    assert ticks.schema.field("state").type == pa.string()
    assert ticks.schema.field("overrun").type == pa.bool_()
    assert ticks.schema.field("q_deg").type == pa.list_(pa.float64(), 6)
    assert ticks.schema.field("file_torque_mnm").metadata[b"unit"] == b"mNm"
    # one row per control tick: the run's duration at 500 Hz, within one tick
    n = ticks.num_rows
    assert abs(n - rec.end["duration_s"] * RATE_HZ) <= 1
    assert abs(n - result.summary.duration_s * RATE_HZ) <= 1
    assert ticks.column("tick").to_pylist() == list(range(n))
    t = ticks.column("t").to_numpy()
    assert t[0] == 0.0 and np.allclose(np.diff(t), 1.0 / RATE_HZ)
    steps = set(ticks.column("step").to_pylist())
    assert steps == {"1:calibrate_load", "2:drag", "3:align"}
    # the same values as the row reader gives
    rows = read_recording(out).rows
    assert ticks.slice(n - 1).to_pylist()[0] == rows[-1]
    assert rec.events.column_names == [f.name for f in EVENT_FIELDS]
    assert "calibration_done" in rec.events.column("kind").to_pylist()

    df = rec.to_pandas()
    assert df.shape == (n, len(TICK_FIELDS))
    assert np.array_equal(df["t"].to_numpy(), t)
    assert np.stack(df["q_deg"].to_numpy()).shape == (n, 6)
    assert capsys.readouterr().out == ""


async def test_the_sync_call_works_inside_a_running_event_loop(protocol_file, tmp_path,
                                                               capsys):
    threads = set()
    result = run_protocol(protocol_file, out=tmp_path / "in-loop.mcap",
                          progress=lambda f: threads.add(threading.current_thread()))
    assert result.summary.status == "ok"
    # the run had its own thread and loop; this loop is still usable
    assert threads and threading.current_thread() not in threads
    await asyncio.sleep(0)
    assert open_recording(result.recording).ticks.num_rows == \
        round(result.summary.duration_s * RATE_HZ)
    # and the coroutine, awaited here
    again = await run_protocol_async(protocol_file, record=False)
    assert again.summary.status == "ok" and again.recording is None
    assert again.summary.to_dict() == result.summary.to_dict()    # same seed, same run
    assert capsys.readouterr().out == ""


def test_logging_is_quiet_by_default_and_configurable(protocol_file, tmp_path, capsys):
    run_protocol(protocol_file, record=False)
    log = structlog.get_logger("dentibot.test")
    log.info("hidden")
    log.warning("shown")
    out, err = capsys.readouterr()
    assert out == "" and "hidden" not in err and "shown" in err
    configure_logging(level="info")
    log.info("now shown")
    out, err = capsys.readouterr()
    assert out == "" and "now shown" in err
    with pytest.raises(ValueError, match="level"):
        configure_logging(level="loud")


def test_to_pandas_names_the_extra_when_pandas_is_missing(protocol_file, tmp_path,
                                                          monkeypatch):
    result = run_protocol(protocol_file, out=tmp_path / "r.mcap")
    rec = open_recording(result.recording)
    monkeypatch.setitem(sys.modules, "pandas", None)
    with pytest.raises(ImportError, match=r"dentibot\[notebook\]"):
        rec.to_pandas()


def _without_wall_s(obj):
    """The result without its wall times (the only figures two identical runs differ in)."""
    if isinstance(obj, dict):
        return {k: _without_wall_s(v) for k, v in obj.items() if k != "wall_s"}
    if isinstance(obj, list):
        return [_without_wall_s(v) for v in obj]
    return obj


def test_an_experiment_gives_what_the_command_prints_as_json(tmp_path, capsys):
    lines = []
    result = run_experiment("alignment", config="A", speeds=(6,), workers=1,
                            no_figures=True, out=tmp_path, progress=lines.append)
    assert result["experiment"] == "alignment" and list(result["configs"]) == ["A"]
    assert result["configs"]["A"]["status"] == "ok"
    assert [s["speed_mm_s"] for s in result["configs"]["A"]["speeds"]] == [6.0]
    assert result["checks"] and result["figures"] == []
    assert len(lines) == 1 and lines[0].startswith("config A seed 1: ok, max |x|")
    assert capsys.readouterr().out == ""
    # in this process, no child: the same dict as the command's JSON (lock-step, seeded)
    code = main(["experiment", "alignment", "--config", "A", "--speeds", "6", "--workers", "1",
                 "--no-figures", "--out", str(tmp_path), "--json", "--quiet"])
    printed = json.loads(capsys.readouterr().out)
    assert code == (0 if all(c["passed"] for c in result["checks"]) else 1)
    assert _without_wall_s(result) == _without_wall_s(printed)
    assert result["wall_s"] > 0.0


def test_bad_experiment_input_raises_before_anything_runs():
    with pytest.raises(ValueError, match="one of alignment, preclinical"):
        run_experiment("nonsense")
    with pytest.raises(ConfigError, match="config = 'Z'.*one of A, B, C, all"):
        run_experiment("alignment", config="Z")
    with pytest.raises(ConfigError, match="option = 'strategy'"):
        run_experiment("alignment", strategy="all")
    with pytest.raises(ConfigError, match="each 0 < mm/s <= 20"):
        run_experiment("alignment", speeds=(0,))
    with pytest.raises(ConfigError, match="phantom = 'X'"):
        run_experiment("preclinical", phantom="AX")


async def test_an_experiment_inside_a_running_event_loop_stops_when_cancelled():
    """Awaited in a loop, the experiment runs in a worker thread; cancelling it (the
    notebook's interrupt) stops the run in progress safely instead of waiting for its end."""
    lines = []
    task = asyncio.create_task(run_experiment_async("alignment", config="A", workers=1,
                                                    no_figures=True, progress=lines.append))
    await asyncio.sleep(0.5)
    assert not task.done()
    started = time.perf_counter()
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert time.perf_counter() - started < 5.0       # the whole run: about ten times that
    assert lines == []
    for thread in threading.enumerate():          # its thread ends with it
        if thread.name == "dentibot-experiment":
            thread.join(2.0)
            assert not thread.is_alive()
