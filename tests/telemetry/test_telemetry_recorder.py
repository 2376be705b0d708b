"""McapRecorder: rows in = rows out, bounded risk (back-pressure, loud overflow), no lost error."""

from __future__ import annotations

import errno
import io
import json
import math
import shutil
import threading
import time

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from telemetry_helpers import GatedStream, decoded_messages, ramp_row

from dentibot.errors import ConfigError
from dentibot.telemetry import McapRecorder, TelemetryError, json_schema, read_recording
from dentibot.telemetry.cdr import TICK_CODEC, definition
from dentibot.telemetry.foxglove import FOXGLOVE_TOPICS
from dentibot.telemetry.recorder import PROVISIONAL_END, TelemetryOverflow
from dentibot.telemetry.schema import TICK_FIELDS
from dentibot.telemetry.tf_cdr import TF_DEFINITION, TF_SCHEMA_NAME

pytestmark = pytest.mark.timeout(30)

RATE_HZ = 500
META = {"protocol": "demo", "seed": 7, "rate_hz": RATE_HZ,
        "devices": {"arm": "sim", "ft": "sim", "handpiece": "sim", "aux": "sim"}}


def _wait_for(condition, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.005)


def test_5000_rows_read_back_identical(tmp_path):
    path = tmp_path / "run.mcap"
    duration_s = 10.0
    n = round(duration_s * RATE_HZ)
    rows = [ramp_row(i, RATE_HZ) for i in range(n)]
    with McapRecorder(path, META) as rec:
        for row in rows:
            rec.record(row)
        rec.event("transition", "approach -> drilling", t=0.2, tick=100)
    assert rec.ticks_written == rec.rows_queued == n == 5000
    assert rec.rows_invalid == rec.rows_rejected == rec.rows_dropped == 0
    got = read_recording(path)
    assert got.complete and got.problems == []
    assert len(got.rows) == n
    assert got.rows == rows                          # every value, exactly (JSON float repr)
    assert got.events == [{"t": 0.2, "tick": 100, "kind": "transition",
                           "detail": "approach -> drilling"}]
    assert got.end == {"status": "ok", "reason": "", "duration_s": duration_s}
    assert {k: got.metadata[k] for k in META} == META
    assert got.metadata["dentibot_version"]
    np.testing.assert_array_equal(got.column("tick"), np.arange(n))
    assert got.column("q_deg").shape == (n, 6)


# 2023-11-14 22:13:20 UTC is 1 700 000 000 s after the Unix epoch
START_NS = 1_700_000_000_123_456_789
START_ISO = "2023-11-14T22:13:20.123456789Z"


def test_file_is_an_indexed_foxglove_ready_mcap(tmp_path):
    """The mcap library's indexed reader (as Foxglove reads it): json messages, jsonschema
    schemas identical to the derived ones (and Foxglove's for the 3D topics), /tick in CDR
    with its ROS 2 definition, decoded by Foxglove's own codec; log_time = publish_time =
    wall-clock start + t, message counts per channel."""
    path = tmp_path / "run.mcap"
    with McapRecorder(path, {**META, "start_wall_ns": START_NS}) as rec:
        for i in range(300):
            rec.record(ramp_row(i, RATE_HZ))
        rec.event("note", "hello")
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {"/run", "/tick", "/events", "/run/end", "/tf", "/scene"}
        for topic, channel in topics.items():
            schema = summary.schemas[channel.schema_id]
            if topic in ("/tick", "/tf"):
                assert (channel.message_encoding, schema.encoding) == ("cdr", "ros2msg")
                assert (schema.name, schema.data.decode()) == (
                    ("dentibot_msgs/msg/Tick", definition(TICK_FIELDS)) if topic == "/tick"
                    else (TF_SCHEMA_NAME, TF_DEFINITION))
                continue
            assert channel.message_encoding == "json"
            assert schema.encoding == "jsonschema"
            expected = FOXGLOVE_TOPICS[topic] if topic in FOXGLOVE_TOPICS else json_schema(topic)
            assert json.loads(schema.data) == expected
            assert schema.name == expected["title"]
        counts = summary.statistics.channel_message_counts
        assert counts[topics["/tick"].id] == 300 and counts[topics["/events"].id] == 1
        assert counts[topics["/tf"].id] == 300
        assert counts[topics["/scene"].id] == 300 // 10      # 50 Hz of 500 Hz ticks
        ticks = [(m.log_time, m.publish_time, {"tick": d.tick, "t": d.t}) for _s, _c, m, d in
                 make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                     topics=["/tick"])]
        (_s, _c, run), = reader.iter_messages(topics=["/run"])
        events = [m.log_time for _s, _c, m in reader.iter_messages(topics=["/events"])]
        assert summary.statistics.message_start_time == START_NS
    expected_ns = [START_NS + round(i / RATE_HZ * 1e9) for i in range(300)]
    assert [lt for lt, _pt, _row in ticks] == expected_ns
    assert [pt for _lt, pt, _row in ticks] == expected_ns
    assert [row["tick"] for _lt, _pt, row in ticks] == list(range(300))
    assert [row["t"] for _lt, _pt, row in ticks] == [i / RATE_HZ for i in range(300)]
    assert run.log_time == run.publish_time == START_NS
    assert events == [expected_ns[-1]]                   # at the last row's t
    meta = json.loads(run.data)
    assert meta["start_wall_ns"] == START_NS and meta["start_time"] == START_ISO
    got = read_recording(path)                           # the reader still works from t
    assert got.metadata["start_wall_ns"] == START_NS
    assert [r["t"] for r in got.rows] == [i / RATE_HZ for i in range(300)]


def test_the_start_defaults_to_the_wall_clock_now(tmp_path):
    before = time.time_ns()
    with McapRecorder(tmp_path / "run.mcap", META) as rec:
        rec.record(ramp_row(0))
    after = time.time_ns()
    assert before <= rec.start_wall_ns <= after
    meta = read_recording(tmp_path / "run.mcap").metadata
    assert meta["start_wall_ns"] == rec.start_wall_ns
    assert meta["start_time"].endswith("Z") and meta["start_time"][:4] >= "2024"
    with pytest.raises(ConfigError, match="start_wall_ns"):
        McapRecorder(tmp_path / "bad.mcap", {"start_wall_ns": -1})


def test_unknown_values_are_left_out_of_the_file_and_read_back_as_none(tmp_path):
    """The JSON messages hold no null at the top (Foxglove's parser takes one type per
    field): an unknown field is left out; in /tick (CDR) an unknown number is NaN and an
    unknown pose an empty sequence, as Foxglove's codec reads them. The reader gives the row
    back as it was handed over, None values included."""
    path = tmp_path / "run.mcap"
    row = ramp_row(0, phantom_pose=None, depth_mm=None, completeness=None)
    assert row["true_depth_mm"] is None
    with McapRecorder(path, {**META, "seed": None}) as rec:
        rec.record(row)
    msgs = dict(decoded_messages(path, ["/run", "/tick"]))
    tick = msgs["/tick"]
    assert list(tick.phantom_pose) == [] and list(tick.tooth_pose) == []
    for name in ("depth_mm", "completeness", "true_depth_mm"):
        assert math.isnan(getattr(tick, name))
    assert list(tick.q_deg) == row["q_deg"] and tick.tick == 0
    assert "seed" not in msgs["/run"]
    got = read_recording(path)
    assert got.rows == [row]
    assert got.metadata["seed"] is None


def _stuck_writer(max_wait_s: float) -> tuple[GatedStream, McapRecorder]:
    """A recorder whose writer is provably stuck in a write (disk stall) after row 0."""
    stream = GatedStream()
    rec = McapRecorder(stream, META, flush_interval_s=0.02, max_wait_s=max_wait_s)
    stream.hold()
    rec.record(ramp_row(0))
    stream.entered.wait(5.0)
    assert stream.entered.is_set()                 # the writer is now blocked in write()
    return stream, rec


def test_a_stuck_writer_holds_the_producer_at_the_budget_then_overflows_loudly():
    """The writer is stuck in I/O: record() keeps returning until 100 ms of ticks are at
    risk, then waits for room, and after max_wait_s drops the row and raises; nothing grows
    without bound, and everything accepted reaches the file once the disk is back."""
    stream, rec = _stuck_writer(max_wait_s=0.1)
    budget = round(0.1 * RATE_HZ)                  # 100 ms of ticks at 500 Hz
    assert rec.budget == budget == 50
    accepted = 1                                   # row 0
    for i in range(1, budget):
        rec.record(ramp_row(i))
        accepted += 1
    assert rec.rows_dropped == 0 and not rec.overflowed
    raised = 0
    for i in range(budget, budget + 3):
        with pytest.raises(TelemetryOverflow, match=f"tick {i} dropped") as info:
            rec.record(ramp_row(i))
        raised += 1
        assert info.value.rows_dropped == raised
    assert accepted == budget and raised == 3
    assert rec.rows_dropped == raised and rec.overflowed
    assert rec.queue_depth <= budget and rec.queue_depth_max <= budget
    assert rec.at_risk_max == budget
    stream.release()
    rec.close("fault", "telemetry overflow")
    assert rec.ticks_written == accepted
    got = _read_bytes(stream.getvalue())
    assert [r["tick"] for r in got] == list(range(accepted))


def test_back_pressure_waits_for_the_writer_instead_of_dropping():
    """A writer stuck for a while (shorter than max_wait_s): the producer's record() of the
    tick past the budget returns only after the disk is back, and nothing is lost."""
    stream, rec = _stuck_writer(max_wait_s=30.0)
    for i in range(1, rec.budget):
        rec.record(ramp_row(i))
    released = threading.Event()

    def release() -> None:
        released.set()
        stream.release()

    timer = threading.Timer(0.2, release)
    timer.start()
    try:
        rec.record(ramp_row(rec.budget))           # waits for room
        assert released.is_set()                   # ...which came only with the release
    finally:
        timer.join()
    n = 2000
    for i in range(rec.budget + 1, n):
        rec.record(ramp_row(i))
    rec.close("ok")
    assert rec.backpressure_waits >= 1 and rec.rows_dropped == 0
    assert [r["tick"] for r in _read_bytes(stream.getvalue())] == list(range(n))


def _read_bytes(raw: bytes) -> list[dict]:
    import tempfile
    from pathlib import Path
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "x.mcap"
        p.write_bytes(raw)
        return read_recording(p).rows


def test_writer_death_is_reported_on_the_next_record():
    stream = GatedStream()
    rec = McapRecorder(stream, META, flush_interval_s=0.02)
    stream.fail_with = OSError(errno.ENOSPC, "No space left on device")
    rec.record(ramp_row(0))
    _wait_for(lambda: rec.error is not None)
    with pytest.raises(TelemetryError, match="writer thread died") as info:
        rec.record(ramp_row(1))
    assert isinstance(info.value.__cause__, OSError)
    with pytest.raises(TelemetryError):
        rec.event("note")
    rec.close("fault", "disk full")                # already reported: close does not raise
    rec.close("fault", "disk full")                # idempotent


def test_close_reports_a_writer_death_not_seen_yet():
    stream = GatedStream()
    rec = McapRecorder(stream, META, flush_interval_s=0.02)
    stream.fail_with = OSError(errno.EIO, "Input/output error")
    rec.record(ramp_row(0))
    _wait_for(lambda: rec.error is not None)
    with pytest.raises(TelemetryError, match="Input/output error"):
        rec.close("ok")
    assert rec.close("ok") == {"status": "ok", "reason": "", "duration_s": 1 / RATE_HZ}


def test_everything_up_to_the_last_flush_is_readable_from_an_open_recording(tmp_path):
    """Copy the file of a recorder that is still running (as after a crash): every row
    flushed so far reads back, the file is flagged incomplete, no end record."""
    path = tmp_path / "run.mcap"
    rec = McapRecorder(path, META, flush_interval_s=0.05)
    try:
        rows = [ramp_row(i) for i in range(1000)]
        for row in rows:
            rec.record(row)
        _wait_for(lambda: rec.rows_flushed == 1000)
        crash = tmp_path / "crash.mcap"
        shutil.copyfile(path, crash)
        got = read_recording(crash)
        assert got.rows == rows
        assert got.end is None and not got.complete
        assert got.metadata["protocol"] == "demo"
    finally:
        rec.close("ok")
    assert read_recording(path).complete


def test_flushes_write_pieces_of_the_chunk_which_the_finished_chunk_replaces(tmp_path):
    """Between two finished chunks each flush writes the chunk's new records as an
    uncompressed chunk of their own after the data, then the provisional end; the finished
    chunk (compressed, once it holds half of chunk_size) is written over the pieces and the
    file cut after its new end. After every flush a copy of the file is a valid MCAP file
    with exactly the flushed rows, and the finished file holds compressed chunks only."""
    path = tmp_path / "run.mcap"
    rows = [ramp_row(i) for i in range(600)]
    rec = McapRecorder(path, META, chunk_size=120_000, writer_thread=False)
    seen, pieces_seen, finished_seen = 0, 0, 0
    for row in rows:
        rec.record(row)
        if rec.flushes == seen:
            continue
        seen = rec.flushes
        raw = path.read_bytes()
        assert raw.endswith(PROVISIONAL_END) and len(raw) == rec.bytes_flushed + len(
            PROVISIONAL_END)
        kinds = [c.compression for c in StreamReader(io.BytesIO(raw), emit_chunks=True).records
                 if isinstance(c, Chunk)]
        assert kinds == sorted(kinds, key=lambda k: k == "")     # pieces after the chunks
        pieces_seen = max(pieces_seen, kinds.count(""))
        finished_seen = max(finished_seen, kinds.count("zstd"))
        ticks = [TICK_CODEC.decode(m.data)["tick"] for _s, c, m in
                 make_reader(io.BytesIO(raw)).iter_messages() if c.topic == "/tick"]
        assert ticks == list(range(rec.rows_flushed))
    assert pieces_seen >= 2 and finished_seen >= 2 and rec.flushes >= 20
    rec.close("ok")
    raw = path.read_bytes()
    kinds = {c.compression for c in StreamReader(io.BytesIO(raw), emit_chunks=True).records
             if isinstance(c, Chunk)}
    assert kinds == {"zstd"}
    assert read_recording(path).rows == rows


def test_nan_becomes_null_numpy_is_accepted_bad_rows_are_counted(tmp_path):
    path = tmp_path / "run.mcap"
    with McapRecorder(path, META) as rec:
        rec.record(ramp_row(0, fz_n=math.nan, q_deg=np.arange(6.0), tick=np.int64(0)))
        rec.record({**ramp_row(1), "oops": object()})    # a field the table has not: left
        rec.record({"t": 0.004, "tick": 2})              # no step, no state: nothing to write
        rec.record({**ramp_row(3), "q_deg": [1.0, 2.0]})  # two joints of six
        rec.record(ramp_row(4))
    assert rec.nonfinite_rows == 1
    assert rec.rows_rejected == 2
    assert rec.rows_invalid == 4           # the NaN row, the object row, the sparse ones
    assert rec.ticks_written == 3
    rows = read_recording(path).rows
    assert rows[0]["fz_n"] is None and rows[0]["q_deg"] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    assert rows[1] == ramp_row(1) and rows[2] == ramp_row(4)
    first = decoded_messages(path, ["/tick"])[0][1]
    assert math.isnan(first.fz_n)                     # NaN is a number in CDR


def test_event_defaults_to_the_last_row_and_exit_on_exception_aborts(tmp_path):
    path = tmp_path / "run.mcap"
    with pytest.raises(RuntimeError), McapRecorder(path, META) as rec:
        rec.record(ramp_row(41))
        rec.event("fault", "ft: stale sample")
        raise RuntimeError("operator pressed stop")
    got = read_recording(path)
    assert got.events == [{"t": ramp_row(41)["t"], "tick": 41, "kind": "fault",
                           "detail": "ft: stale sample"}]
    assert got.end["status"] == "aborted" and "operator pressed stop" in got.end["reason"]
    with pytest.raises(TelemetryError, match="closed"):
        rec.record(ramp_row(42))


def test_configuration_errors(tmp_path):
    path = tmp_path / "run.mcap"
    path.write_bytes(b"")
    with pytest.raises(TelemetryError, match="exists"):
        McapRecorder(path, META)
    with pytest.raises(TelemetryError, match="cannot create"):
        McapRecorder(tmp_path / "no" / "dir.mcap", META)
    with pytest.raises(ConfigError, match="rate_hz"):
        McapRecorder(tmp_path / "r.mcap", {"rate_hz": 0})
    with pytest.raises(ConfigError, match="compression"):
        McapRecorder(tmp_path / "r.mcap", META, compression="gzip")
    with McapRecorder(path, META, overwrite=True) as rec, \
            pytest.raises(ConfigError, match="status"):
        rec.close("great")
    assert read_recording(path).end["status"] == "ok"


def test_duration_without_rate_is_the_last_t(tmp_path):
    path = tmp_path / "run.mcap"
    with McapRecorder(path, {"protocol": "x"}, compression="none") as rec:
        for i in range(10):
            rec.record(ramp_row(i, rate_hz=100.0))
    assert read_recording(path).end["duration_s"] == 0.09


def test_bad_metadata_is_refused_before_a_file_is_created(tmp_path):
    path = tmp_path / "run.mcap"
    with pytest.raises(ConfigError, match="metadata"):
        McapRecorder(path, {"rate_hz": 500, "operator": object()})
    assert not path.exists()


def test_non_finite_numbers_of_a_tick_are_counted_nan_reads_back_as_none_inf_as_inf(tmp_path):
    """/tick is CDR: a string holding "null" is a string, a NaN inside an array is a NaN
    (read back as None, as an unknown value), an infinity is kept; the rows holding either
    are counted."""
    path = tmp_path / "null.mcap"
    with McapRecorder(path, {"rate_hz": 500.0}, validate=False, view=False) as rec:
        rec.record(ramp_row(0, step="null step"))
        rec.record(ramp_row(1, q_deg=[0.0, math.nan, 0.0, 0.0, 0.0, 0.0]))
        rec.record(ramp_row(2, fz_n=math.inf))
    assert rec.nonfinite_rows == 2
    ticks = [m for _topic, m in decoded_messages(path, ["/tick"])]
    assert ticks[0].step == "null step"
    assert math.isnan(ticks[1].q_deg[1]) and ticks[2].fz_n == math.inf
    rows = read_recording(path).rows
    assert rows[1]["q_deg"][1] is None and rows[2]["fz_n"] == math.inf
