"""The recorder in a process of its own: the same file as the in-process recorder, its errors
raised where the caller is, and no row it was sent lost when its parent dies."""

from __future__ import annotations

import gc
import io
import os
import pickle
import signal
import time

import pytest
from mcap.reader import make_reader
from telemetry_helpers import real_row

from dentibot.errors import ConfigError
from dentibot.telemetry import McapRecorder, TelemetryError, read_recording
from dentibot.telemetry.foxglove import FoxgloveView
from dentibot.telemetry.journal import journal_path
from dentibot.telemetry.recorder_process import RecorderProcess, open_recorder

pytestmark = pytest.mark.timeout(120)

META = {"protocol": "process-test", "rate_hz": 500.0, "start_wall_ns": 1_700_000_000 * 10**9}


def _gone(pid: int, timeout_s: float = 30.0) -> bool:
    """True once process ``pid`` (the fork server's child, not ours) has ended."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            state = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            return True
        if state == "Z":
            return True
        time.sleep(0.02)
    return False


def test_the_same_rows_make_the_same_recording_as_in_process(tmp_path):
    rows = [real_row(i) for i in range(1200)]
    recs = {}
    for cls in (McapRecorder, RecorderProcess):
        rec = cls(tmp_path / f"{cls.__name__}.mcap", dict(META), validate=False)
        for i, row in enumerate(rows):
            rec.record(row)
            if i == 400:
                rec.event("note", "after tick 400")
        end = rec.close("ok", "done")
        assert end == {"status": "ok", "reason": "done", "duration_s": 1200 / 500.0}
        recs[cls] = rec
    a = read_recording(tmp_path / "McapRecorder.mcap")
    b = read_recording(tmp_path / "RecorderProcess.mcap")
    assert b.complete and b.rows == a.rows == rows
    assert b.events == a.events and b.events[0]["tick"] == 400
    assert b.end == a.end and b.metadata == a.metadata
    # the writer's counters come back from the child: one /tf per tick, /scene at 50 Hz
    local, child = recs[McapRecorder], recs[RecorderProcess]
    for name in ("ticks_written", "events_written", "transforms_written", "scenes_written"):
        assert getattr(child, name) == getattr(local, name), name
    assert child.ticks_written == 1200 and child.scenes_written == 1200 // 10
    # the same messages, byte for byte (the chunks are cut elsewhere: the process writes its
    # file in larger steps)
    assert _messages(tmp_path / "RecorderProcess.mcap") == \
        _messages(tmp_path / "McapRecorder.mcap")
    assert _gone(child.pid)
    assert not journal_path(tmp_path / "RecorderProcess.mcap").exists()   # closed: deleted


def _messages(path) -> list[tuple[str, int, int, bytes]]:
    with open(path, "rb") as f:
        return [(ch.topic, m.log_time, m.sequence, m.data)
                for _, ch, m in make_reader(f).iter_messages(log_time_order=False)]


def test_argument_errors_are_raised_by_the_constructor(tmp_path):
    path = tmp_path / "x.mcap"
    path.write_bytes(b"taken")
    with pytest.raises(TelemetryError, match="file exists"):
        RecorderProcess(path, dict(META))
    assert path.read_bytes() == b"taken"                  # not touched
    with pytest.raises(ConfigError) as err:
        RecorderProcess(tmp_path / "y.mcap", dict(META), compression="brotli")
    assert err.value.field == "telemetry.compression" and err.value.value == "brotli"
    with pytest.raises(ConfigError) as err:
        RecorderProcess(tmp_path / "z.mcap", {"rate_hz": -5.0})
    assert err.value.field == "metadata.rate_hz"
    assert not (tmp_path / "y.mcap").exists() and not (tmp_path / "z.mcap").exists()


def test_open_recorder_keeps_what_cannot_cross_processes_here(tmp_path):
    rec = open_recorder(io.BytesIO(), dict(META))
    assert isinstance(rec, McapRecorder)
    rec.close()
    drawn = FoxgloveView(frames=lambda row: [])          # a lambda does not pickle
    rec = open_recorder(tmp_path / "a.mcap", dict(META), view=drawn)
    assert isinstance(rec, McapRecorder)
    rec.close()
    rec = open_recorder(tmp_path / "b.mcap", dict(META), view=FoxgloveView())
    assert isinstance(rec, RecorderProcess)
    rec.close()


def test_ctrl_c_belongs_to_the_control_process(tmp_path):
    """SIGINT (a Ctrl-C reaches the whole process group) does not stop the recorder: the
    control process stops the procedure safely and then closes the recording."""
    rec = RecorderProcess(tmp_path / "a.mcap", dict(META), validate=False)
    for i in range(100):
        rec.record(real_row(i))
    os.kill(rec.pid, signal.SIGINT)
    time.sleep(0.2)
    for i in range(100, 200):
        rec.record(real_row(i))
    rec.close("aborted", "Ctrl-C")
    got = read_recording(tmp_path / "a.mcap")
    assert got.complete and len(got.rows) == 200 and got.end["status"] == "aborted"


def test_a_dead_recorder_process_is_reported_on_the_next_record_and_close_returns(tmp_path):
    rec = RecorderProcess(tmp_path / "a.mcap", dict(META), validate=False)
    for i in range(100):
        rec.record(real_row(i))
    os.kill(rec.pid, signal.SIGKILL)
    assert _gone(rec.pid)
    with pytest.raises(TelemetryError, match="recorder process"):
        for i in range(100, 200):                       # a batch is sent every 10 rows
            rec.record(real_row(i))
    with pytest.raises(TelemetryError, match="recorder is closed|recorder process"):
        rec.record(real_row(200))
    rec.close("fault", "recorder died")                 # already reported: no second raise
    got = read_recording(tmp_path / "a.mcap")
    assert not got.complete and len(got.rows) <= 100


def test_a_recorder_dropped_without_close_writes_out_what_it_was_sent(tmp_path):
    """The parent forgets it (or dies): the child writes every row it received and leaves
    the file flagged incomplete, as a crash would, with nothing it was sent lost."""
    path = tmp_path / "a.mcap"
    rec = RecorderProcess(path, dict(META), validate=False)
    for i in range(95):
        rec.record(real_row(i))
    sent = rec.rows_queued - len(rec._pending)           # rows that left this process
    assert 85 <= sent <= 95
    pid = rec.pid
    del rec
    gc.collect()
    assert _gone(pid)
    got = read_recording(path)
    assert not got.complete and got.end is None
    assert [r["tick"] for r in got.rows] == list(range(sent))
    assert not journal_path(path).exists()        # all it held is in the file


def test_the_budget_holds_with_back_pressure(tmp_path):
    """max_queue 5: never more than 5 ticks at risk (here or in the child); all rows land."""
    rec = RecorderProcess(tmp_path / "a.mcap", dict(META), validate=False, max_queue=5)
    assert rec.send_ticks == 1
    for i in range(600):
        rec.record(real_row(i))
        assert rec.rows_queued - rec._settled <= 5
    rec.close()
    assert rec.at_risk_max <= 5 and rec.backpressure_waits > 0 and rec.rows_dropped == 0
    assert len(read_recording(tmp_path / "a.mcap").rows) == 600


def test_a_stopped_recorder_process_overflows_loudly_and_drops_nothing_silently(tmp_path):
    """The child frozen (SIGSTOP): the parent waits max_wait_s at the budget, then drops the
    row and raises; the process resumed, the recording goes on and says what it lost."""
    from dentibot.telemetry.recorder import TelemetryOverflow

    rec = RecorderProcess(tmp_path / "a.mcap", dict(META), validate=False, max_queue=5,
                          max_wait_s=0.2)
    os.kill(rec.pid, signal.SIGSTOP)
    try:
        with pytest.raises(TelemetryOverflow, match="the recorder process made no room in "
                                                    "0.2 s") as err:
            for i in range(6):
                rec.record(real_row(i))
        assert err.value.rows_dropped == 1 and rec.overflowed and rec.rows_queued == 5
    finally:
        os.kill(rec.pid, signal.SIGCONT)
    rec.record(real_row(6))
    rec.close()
    assert [r["tick"] for r in read_recording(tmp_path / "a.mcap").rows] == [0, 1, 2, 3, 4, 6]
