"""``dentibot recover``: a recording cut short becomes a finished MCAP file holding exactly its
complete messages; an intact one is left alone; bad input and existing outputs are refused.

The expected counts come from the finished recording's own index (chunk offsets and the
messages inside each chunk), not from the recovery code.
"""

from __future__ import annotations

import functools
import io
import tempfile
import time
from pathlib import Path

import orjson
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk
from telemetry_helpers import real_row

from dentibot.cli import main
from dentibot.telemetry import McapRecorder, read_recording
from dentibot.telemetry.cdr import TICK_CODEC

pytestmark = pytest.mark.timeout(60)

RATE_HZ = 500
N_ROWS = 400


@functools.cache
def _finished() -> tuple[bytes, list[tuple[int, int, int]]]:
    """A finished recording and, per chunk in file order: (end offset, messages, /tick
    messages) in the chunks up to and including it. Its chunks are small (a flush finishes
    the chunk once it holds 20 kB), so that it has many."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "run.mcap"
        with McapRecorder(path, {"rate_hz": RATE_HZ}, chunk_size=40_000) as rec:
            for i in range(N_ROWS):
                rec.record(real_row(i))
                if i % 100 == 50:
                    rec.event("note", f"tick {i}")
        raw = path.read_bytes()
    summary = make_reader(io.BytesIO(raw)).get_summary()
    tick_channel = next(c.id for c in summary.channels.values() if c.topic == "/tick")
    index = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    chunks = [r for r in StreamReader(io.BytesIO(raw), emit_chunks=True).records
              if isinstance(r, Chunk)]
    assert len(chunks) == len(index)
    ends, messages, ticks = [], 0, 0
    for c, chunk in zip(index, chunks, strict=True):
        inside = [m for m in breakup_chunk(chunk) if isinstance(m, Message)]
        messages += len(inside)
        ticks += sum(1 for m in inside if m.channel_id == tick_channel)
        ends.append((c.chunk_start_offset + c.chunk_length, messages, ticks))
    return raw, ends


def _standard_read(path: Path) -> tuple[int, list[int], bool]:
    """(messages, /tick tick numbers, has a summary) by the mcap library's reader."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        has_summary = reader.get_summary() is not None
        messages = list(reader.iter_messages())
    ticks = [TICK_CODEC.decode(m.data)["tick"] for _s, c, m in messages if c.topic == "/tick"]
    return len(messages), ticks, has_summary


def test_the_test_recording_has_many_chunks():
    _raw, ends = _finished()
    assert len(ends) >= 10 and ends[-1][2] == N_ROWS


@pytest.mark.parametrize("where", ["mid-chunk", "after-chunk", "one-byte-short", "last-chunk"])
def test_a_cut_file_is_rewritten_with_exactly_its_complete_messages(tmp_path, capsys, where):
    raw, ends = _finished()
    k = len(ends) // 2
    cut = {"mid-chunk": (ends[k - 1][0] + ends[k][0]) // 2,
           "after-chunk": ends[k][0] + 3,                  # inside the chunk's message index
           "one-byte-short": ends[k][0] - 1,
           "last-chunk": ends[-1][0] + 1}[where]
    expected = max(((m, t) for end, m, t in ends if end <= cut), default=(0, 0))
    src = tmp_path / "cut.mcap"
    src.write_bytes(raw[:cut])
    out = tmp_path / "out.mcap"
    assert main(["recover", str(src), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"recovered {expected[1]} ticks" in text and "INCOMPLETE" in text
    messages, ticks, has_summary = _standard_read(out)
    assert has_summary                                     # a finished file: summary, footer
    assert messages == expected[0]
    assert ticks == list(range(expected[1]))
    with open(out, "rb") as f:
        assert make_reader(f).get_summary().statistics.message_count == expected[0]
    got = read_recording(out)                              # DentiBot's view: incomplete
    assert not got.complete and got.recovered["ticks"] == str(expected[1])
    assert got.recovered["source"] == "cut.mcap"


def test_a_crashed_file_as_written_is_rewritten_message_for_message(tmp_path, capsys):
    """A copy of a file being recorded (provisional end): recover keeps every message the
    standard reader sees in it, and says it has no /run/end."""
    live = tmp_path / "live.mcap"
    crash = tmp_path / "crash.mcap"
    rec = McapRecorder(live, {"rate_hz": RATE_HZ})
    try:
        for i in range(333):
            rec.record(real_row(i))
        deadline = time.monotonic() + 10
        while len(read_recording(live).rows) < 333:       # wall-time flush of the tail
            assert time.monotonic() < deadline, "not flushed in time"
            time.sleep(0.01)
        crash.write_bytes(live.read_bytes())
    finally:
        rec.close("ok")
    before, before_ticks, before_summary = _standard_read(crash)
    assert not before_summary and before_ticks == list(range(333))
    out = tmp_path / "crash.recovered.mcap"                # the default name
    assert main(["recover", str(crash)]) == 0
    text = capsys.readouterr().out
    assert "recovered 333 ticks (0.666 s of procedure at 500 Hz; ticks 0-332)" in text
    assert "no /run/end" in text
    after, after_ticks, has_summary = _standard_read(out)
    assert has_summary and after == before and after_ticks == before_ticks
    assert main(["report", str(out)]) == 0
    text = capsys.readouterr().out
    assert "DentiBot run: incomplete" in text and "recovered by 'dentibot recover'" in text
    assert main(["report", str(out), "--json"]) == 0
    d = orjson.loads(capsys.readouterr().out)
    assert d["status"] == "incomplete" and d["ticks"] == 333
    assert d["recording"]["recovered"]["ticks"] == "333"
    # a recovered file is itself intact: nothing more to recover
    assert main(["recover", str(out)]) == 0
    assert "nothing to recover" in capsys.readouterr().out


def test_an_intact_file_is_left_alone_unless_asked(tmp_path, capsys):
    raw, ends = _finished()
    src = tmp_path / "run.mcap"
    src.write_bytes(raw)
    assert main(["recover", str(src)]) == 0
    assert "intact" in (text := capsys.readouterr().out) and "nothing to recover" in text
    assert not (tmp_path / "run.recovered.mcap").exists()
    assert src.read_bytes() == raw
    out = tmp_path / "copy.mcap"
    assert main(["recover", str(src), "--out", str(out), "--rewrite"]) == 0
    capsys.readouterr()
    messages, ticks, has_summary = _standard_read(out)
    assert has_summary and messages == ends[-1][1] and ticks == list(range(N_ROWS))
    got = read_recording(out)
    assert got.complete and got.recovered is None and got.status == "ok"


def test_an_existing_output_is_refused_without_force(tmp_path, capsys):
    raw, ends = _finished()
    src = tmp_path / "cut.mcap"
    src.write_bytes(raw[:ends[3][0]])
    out = tmp_path / "out.mcap"
    out.write_bytes(b"precious")
    assert main(["recover", str(src), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(out) in err and "exists" in err and "--force" in err
    assert out.read_bytes() == b"precious"
    assert main(["recover", str(src), "--out", str(out), "--force"]) == 0
    capsys.readouterr()
    messages, _ticks, _summary = _standard_read(out)
    assert messages == ends[3][1]
    assert not list(tmp_path.glob(".*tmp"))               # no temporary file left behind


def test_bad_input_exits_2_naming_the_file(tmp_path, capsys):
    missing = tmp_path / "missing.mcap"
    assert main(["recover", str(missing)]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "no such file" in err
    junk = tmp_path / "junk.mcap"
    junk.write_text("not a recording")
    assert main(["recover", str(junk)]) == 2
    err = capsys.readouterr().err
    assert str(junk) in err and "not an MCAP file" in err
    stub = tmp_path / "stub.mcap"
    stub.write_bytes(_finished()[0][:12])                  # the magic, then a cut header
    assert main(["recover", str(stub)]) == 2
    err = capsys.readouterr().err
    assert str(stub) in err and "no complete header" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.mcap", "stub.mcap"]


def test_recover_json_reports_what_was_saved(tmp_path, capsys):
    import json

    raw, ends = _finished()
    k = len(ends) // 2
    src = tmp_path / "cut.mcap"
    src.write_bytes(raw[:ends[k][0]])                      # cut right after a chunk
    out = tmp_path / "out.mcap"
    assert main(["recover", str(src), "--out", str(out), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["source"] == str(src) and d["out"] == str(out)
    assert d["intact"] is False and d["has_end"] is False
    assert (d["messages"], d["ticks"]) == (ends[k][1], ends[k][2])
    assert d["first_tick"] == 0 and d["last_tick"] == ends[k][2] - 1
    assert d["seconds"] == pytest.approx(d["ticks"] / d["rate_hz"])
