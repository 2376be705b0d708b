"""read_recording: cut files read up to their last complete chunk; garbage is a typed error."""

from __future__ import annotations

import functools
import io
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk
from telemetry_helpers import ramp_row

from dentibot.telemetry import McapRecorder, TelemetryError, read_recording

pytestmark = pytest.mark.timeout(60)

N_ROWS = 600
RATE_HZ = 500


@functools.cache
def _recording() -> tuple[bytes, list[dict], list[tuple[int, int]]]:
    """A finished recording with small chunks: (bytes, rows, [(chunk end offset, ticks in
    chunks up to and including it)])."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "run.mcap"
        rows = [ramp_row(i, RATE_HZ) for i in range(N_ROWS)]
        with McapRecorder(path, {"rate_hz": RATE_HZ}, chunk_size=32768) as rec:
            for row in rows:
                rec.record(row)
        raw = path.read_bytes()
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    # the chunks in file order, from the index (offsets) and from the stream (contents)
    tick_channel = next(c.id for c in summary.channels.values() if c.topic == "/tick")
    index = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    chunks = [r for r in StreamReader(io.BytesIO(raw), emit_chunks=True).records
              if isinstance(r, Chunk)]
    assert len(chunks) == len(index)
    ends, n = [], 0
    for c, chunk in zip(index, chunks, strict=True):
        n += sum(1 for m in breakup_chunk(chunk)
                 if isinstance(m, Message) and m.channel_id == tick_channel)
        ends.append((c.chunk_start_offset + c.chunk_length, n))
    return raw, rows, ends


def _read_bytes(raw: bytes):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "cut.mcap"
        p.write_bytes(raw)
        return read_recording(p)


def test_the_test_recording_has_many_chunks():
    _raw, _rows, ends = _recording()
    assert len(ends) >= 5
    assert ends[-1][1] == N_ROWS


def test_cut_at_each_chunk_end_gives_exactly_the_rows_of_the_complete_chunks():
    raw, rows, ends = _recording()
    before = 0
    for end, n in ends:
        for cut in (end, end + 1):           # + 1: a record begun after the chunk
            got = _read_bytes(raw[:cut])
            assert got.rows == rows[:n]
            assert not got.complete
            assert (got.end is None) == (end < ends[-1][0])   # /run/end is in the last chunk
        got = _read_bytes(raw[:end - 1])     # one byte short: that chunk is lost whole
        assert got.rows == rows[:before]
        before = n


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_any_cut_reads_a_prefix_without_raising(data):
    raw, rows, ends = _recording()
    cut = data.draw(st.integers(min_value=8, max_value=len(raw) - 1))
    got = _read_bytes(raw[:cut])
    expected = max((n for end, n in ends if end <= cut), default=0)
    assert got.rows == rows[:expected]
    assert not got.complete


@settings(max_examples=40, deadline=None)
@given(st.binary(max_size=400), st.integers(min_value=0, max_value=2000))
def test_garbage_after_valid_data_is_survived(garbage, keep):
    """Bytes damaged after any point: never an exception, only complete rows come back."""
    raw, rows, _ends = _recording()
    keep = min(keep, len(raw))
    got = _read_bytes(raw[:8 + keep] + garbage)
    assert got.rows == rows[:len(got.rows)]
    assert isinstance(got.problems, list)


@settings(max_examples=40, deadline=None)
@given(st.binary(max_size=200))
def test_not_an_mcap_file_is_a_typed_error(garbage):
    if garbage.startswith(b"\x89MCAP0\r\n"):
        return
    with pytest.raises(TelemetryError, match="not an MCAP file"):
        _read_bytes(garbage)


def test_missing_file_is_a_typed_error(tmp_path):
    with pytest.raises(TelemetryError, match="no such file"):
        read_recording(tmp_path / "nope.mcap")


def test_finished_file_is_complete():
    raw, rows, _ends = _recording()
    got = _read_bytes(raw)
    assert got.complete and got.rows == rows and got.end["status"] == "ok"
    assert got.problems == []


def test_a_recording_with_json_ticks_reads_back_as_before(tmp_path):
    """Recordings made before /tick was CDR hold it as JSON with a JSON schema: they read
    back the same way, an absent field as None, and recover and report as before."""
    import orjson
    from mcap.writer import Writer

    from dentibot.cli import main
    from dentibot.telemetry.schema import json_schema, none_fields

    path = tmp_path / "old.mcap"
    rows = [{k: v for k, v in ramp_row(i, RATE_HZ).items() if v is not None} for i in range(30)]
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="dentibot 0 (older)")
        channels = {}
        for topic in ("/run", "/tick"):
            sid = w.register_schema(name=json_schema(topic)["title"], encoding="jsonschema",
                                    data=orjson.dumps(json_schema(topic)))
            channels[topic] = w.register_channel(topic=topic, message_encoding="json",
                                                 schema_id=sid)
        w.add_message(channels["/run"], 0, orjson.dumps({"rate_hz": RATE_HZ}), 0)
        for row in rows:
            ns = round(row["t"] * 1e9)
            w.add_message(channels["/tick"], ns, orjson.dumps(row), ns, sequence=row["tick"])
        w.finish()
    got = read_recording(path)
    assert got.rows == [none_fields("/tick") | row for row in rows]
    assert got.metadata["rate_hz"] == RATE_HZ
    out = tmp_path / "old-recovered.mcap"
    assert main(["recover", str(path), "--out", str(out), "--rewrite"]) == 0
    assert read_recording(out).rows == got.rows
