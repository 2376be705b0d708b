"""Rows in blocks: a block gives the rows the control task builds, and the summary, the
recorder and the recorder process take it whole with the same result as row by row, within
the same budget of ticks at risk."""

from __future__ import annotations

import io
import math
import pickle
import random

import numpy as np
import pytest
import zstandard
from mcap.reader import make_reader
from mcap.writer import Writer
from telemetry_helpers import GatedStream

from dentibot.telemetry import McapRecorder, mcap_messages, record_kernels
from dentibot.telemetry.blocks import COL, COLUMNS, WIDTH, TickBlock, tick_row
from dentibot.telemetry.cdr import TICK_CODEC
from dentibot.telemetry.recorder import ZSTD_LEVEL, TelemetryOverflow
from dentibot.telemetry.recorder_process import RecorderProcess
from dentibot.telemetry.schema import TICK_FIELDS
from dentibot.telemetry.summary import SummaryAccumulator

pytestmark = pytest.mark.timeout(60)

RATE_HZ = 500.0
META = {"protocol": "blocks", "seed": 1, "rate_hz": RATE_HZ}


def _block(k0: int, n: int, seed: int = 0, reversals: int = 0, step: str = "4:drill",
           state: str = "treating.drilling.feeding") -> TickBlock:
    """A block of ``n`` ticks from ``k0`` whose every number is known: column ``c`` of tick
    ``k0 + i`` holds ``k0 + i + c / 100`` (plus a seeded offset), the motor turning at odd
    ticks only."""
    rng = np.random.default_rng(seed)
    k = np.arange(k0, k0 + n)[:, None]
    cols = k + np.arange(WIDTH)[None, :] / 100.0 + rng.normal(0.0, 0.01, (n, WIDTH))
    cols[:, COL["motor_rpm"]] = np.where(k[:, 0] % 2 == 1, 60.0, 0.0)
    return TickBlock(cols, k0, 1.0 / RATE_HZ, step, state, 16.0, reversals, (180.0, 0.0, 90.0))


def test_the_columns_cover_the_rows_numbers_once():
    starts = [COL[name] for name, _ in COLUMNS]
    assert starts == sorted(starts) and starts[0] == 0
    assert WIDTH == sum(width for _, width in COLUMNS) == 42
    assert set(tick_row(*([0] * 27)).keys()) == {f.name for f in TICK_FIELDS}


def test_a_block_gives_each_tick_its_row():
    b = _block(1000, 7)
    rows = b.rows()
    assert len(rows) == len(b) == 7 and list(b.ticks) == [r["tick"] for r in rows]
    for i, row in enumerate(rows):
        c = b.cols[i]
        assert row["tick"] == 1000 + i and row["t"] == (1000 + i) * (1.0 / RATE_HZ)
        assert row["q_deg"] == c[0:6].tolist()
        assert row["qdot_cmd_deg_s"] == c[6:12].tolist()
        assert row["tool_pose"] == c[12:18].tolist()
        assert row["phantom_pose"] == [*c[18:21].tolist(), 180.0, 0.0, 90.0]
        assert row["wrench_s"] == c[21:27].tolist() and row["wrench_h"] == c[27:33].tolist()
        assert row["f_d"] == [0.0, 0.0, c[33], 0.0, 0.0, 0.0] and row["fz_n"] == c[33]
        assert row["fz_star_n"] == c[34] and row["file_torque_mnm"] == c[35]
        assert (row["motor_current_a"], row["motor_rpm"]) == (c[36], c[37])
        assert (row["depth_mm"], row["true_depth_mm"], row["completeness"]) == \
            (c[38], c[39], c[40])
        assert row["compute_us"] == c[41]
        assert row["tooth_pose"] is None and row["events"] == [] and row["lateness_us"] == 0.0
        assert (row["fractured"], row["patient_moved"], row["overrun"]) == (False,) * 3
        assert (row["step"], row["state"], row["working_length_mm"], row["reversals"]) == \
            ("4:drill", "treating.drilling.feeding", 16.0, 0)
    assert b.row(-1) == rows[-1] and b.row(2) == rows[2]
    part = b.part(2, 5)
    assert part.k0 == 1002 and part.rows() == rows[2:5]


def test_a_block_s_wire_form_gives_the_same_block_back():
    """What the recorder process receives: every number bit for bit, the names (not ASCII
    too), the shared values; a pickle or a cut block is refused, not misread."""
    b = _block(123456, 9, 5, reversals=4, step="3:drill — élargir", state="treating.retracting")
    b.cols[2, COL["depth_mm"]] = math.nan
    data = b"".join(b.packed())
    assert data[:1] == b"B"
    back = TickBlock.unpack(data)
    assert back.cols.tobytes() == b.cols.tobytes() and back.cols.flags.writeable
    assert (back.k0, back.ts, back.step, back.state, back.working_length_mm, back.reversals,
            back.phantom_euler) == (123456, 1.0 / RATE_HZ, "3:drill — élargir",
                                    "treating.retracting", 16.0, 4, (180.0, 0.0, 90.0))
    assert [r["tick"] for r in back.rows()] == list(range(123456, 123465))
    with pytest.raises(ValueError, match="not a packed tick block"):
        TickBlock.unpack(pickle.dumps([("block", b)], pickle.HIGHEST_PROTOCOL))
    with pytest.raises(ValueError, match="9 x 42 values has 3016 bytes"):
        TickBlock.unpack(data[:-8])


def _by_rows(blocks: list[TickBlock], rate_hz: float | None) -> SummaryAccumulator:
    acc = SummaryAccumulator(rate_hz=rate_hz)
    for b in blocks:
        for row in b.rows():
            acc.add(row)
    return acc


@pytest.mark.parametrize("rate_hz", [RATE_HZ, None])
def test_the_summary_takes_a_block_as_its_rows(rate_hz):
    """Maxima, sums over turning ticks, durations, step figures and reversals: the same
    numbers, exactly, as row by row; a block with an unknown (NaN) value too."""
    blocks = [_block(0, 25, 1), _block(25, 25, 2, reversals=2),
              _block(50, 10, 3, reversals=3, step="5:drill"), _block(60, 25, 4, reversals=3)]
    blocks[2].cols[4, COL["file_torque_mnm"]] = math.nan
    acc = SummaryAccumulator(rate_hz=rate_hz)
    for b in blocks:
        acc.add_block(b)
    want = _by_rows(blocks, rate_hz)
    got, expected = acc.finish("ok"), want.finish("ok")
    assert got == expected
    assert got.reversals == 3 and got.ticks == 85 and len(got.steps) == 2
    # the numbers themselves, from the columns: torque magnitudes while turning (odd ticks)
    torque = np.concatenate([b.cols[:, COL["file_torque_mnm"]] for b in blocks])
    odd = np.arange(85) % 2 == 1
    assert got.peak_file_torque_mNm == np.nanmax(np.abs(torque))
    assert got.mean_file_torque_mNm == pytest.approx(np.nanmean(np.abs(torque[odd])), rel=1e-12)


def _ticks_of(data: bytes) -> list[dict]:
    return [TICK_CODEC.decode(m.data) for _s, c, m in
            make_reader(io.BytesIO(data)).iter_messages() if c.topic == "/tick"]


@pytest.mark.parametrize(("chunk_size", "view"), [(1 << 20, True), (2000, True),
                                                   (1 << 20, False), (30_000, True)])
def test_the_recorder_writes_a_block_as_its_rows(chunk_size, view):
    """The same /tick, /tf and /scene messages as record() of each row, byte for byte; a block
    larger than the budget goes in parts, and never more than the budget is at risk; also
    where a block's messages fill 2 kB chunks on the way (a flush then finds its chunk
    empty), without the 3D view, and with chunks that flushes finish on the way (half of
    30 kB)."""
    blocks = [_block(0, 25), _block(25, 140, 1), _block(165, 3, 2)]
    files = []
    for whole in (True, False):
        stream = io.BytesIO()
        rec = McapRecorder(stream, {**META, "start_wall_ns": 10**18}, chunk_size=chunk_size,
                           view=view)
        for b in blocks:
            if whole:
                rec.record_block(b)
            else:
                for row in b.rows():
                    rec.record(row)
        assert rec.at_risk_max <= rec.budget == 50
        rec.close("ok")
        assert rec.ticks_written == 168 and rec.transforms_written == 168 * view
        assert rec.scenes_written == 17 * view          # 50 Hz of 0.336 s: ticks 0, 10, ...
        files.append(stream.getvalue())
    assert _ticks_of(files[0]) == _ticks_of(files[1])
    assert [r["tick"] for r in _ticks_of(files[0])] == list(range(168))
    assert files[0] == files[1]                         # byte for byte


def test_the_record_kernel_is_ready_at_import_and_blocks_compile_nothing_more():
    """The recorder's process imports the kernel before it forks: its first block must not
    wait for a compilation (the producer waits for room at most max_wait_s)."""
    before = list(record_kernels.message_records.signatures)
    assert len(before) == 1
    for view in (True, False):
        rec = McapRecorder(io.BytesIO(), META, view=view)
        for k0 in range(0, 100, 25):
            rec.record_block(_block(k0, 25, k0))
        rec.close("ok")
        assert rec.ticks_written == 100 and rec.scenes_written == 10 * view
    assert list(record_kernels.message_records.signatures) == before


def test_a_block_that_finds_no_room_is_dropped_loudly():
    stream = GatedStream()
    rec = McapRecorder(stream, META, flush_interval_s=0.02, max_wait_s=0.1)
    stream.hold()
    rec.record_block(_block(0, 1))
    stream.entered.wait(5.0)
    assert stream.entered.is_set()                     # the writer is stuck in a write
    rec.record_block(_block(1, 40))                    # 41 of 50 at risk
    with pytest.raises(TelemetryOverflow, match="ticks 41 to 50 dropped") as info:
        rec.record_block(_block(41, 10))
    assert info.value.rows_dropped == 10 and rec.at_risk_max == 41
    stream.release()
    rec.close("fault", "telemetry overflow")
    assert rec.ticks_written == 41


def test_the_recorder_process_takes_blocks(tmp_path):
    path = tmp_path / "blocks.mcap"
    rec = RecorderProcess(path, META, max_queue=50)
    for k0 in range(0, 400, 25):
        rec.record_block(_block(k0, 25, k0))
    rec.record_block(_block(400, 120, 9))               # larger than the budget: in parts
    rec.close("ok")
    assert rec.rows_queued == rec.ticks_written == 520 and rec.at_risk_max <= 50
    with open(path, "rb") as f:
        ticks = [TICK_CODEC.decode(m.data) for _s, c, m in make_reader(f).iter_messages()
                 if c.topic == "/tick"]
    assert [r["tick"] for r in ticks] == list(range(520))
    assert ticks[0]["q_deg"] == _block(0, 25, 0).cols[0, 0:6].tolist()


def _messages_file(fast: bool, chunk_size: int, level: int | None = None) -> bytes:
    """A file of 3000 messages on three channels, flushed every 370 messages: through the
    library's calls, or (``fast``) through add_messages and, with a zstd ``level``,
    finish_chunk with a compressor of that level."""
    compress = None if level is None else zstandard.ZstdCompressor(level=level).compress
    out = io.BytesIO()
    w = Writer(out, chunk_size=chunk_size)
    w.start(profile="", library="test")
    schema = w.register_schema(name="s", encoding="jsonschema", data=b"{}")
    channels = [w.register_channel(topic=f"/c{i}", message_encoding="json", schema_id=schema)
                for i in range(3)]
    rng = random.Random(1)
    messages = [(rng.choice(channels), 10**18 + 1000 * i + rng.randint(-5, 5),
                 bytes(rng.randint(1, 300)), i) for i in range(3000)]
    for start in range(0, len(messages), 37):
        batch = messages[start:start + 37]
        if fast:
            mcap_messages.add_messages(w, batch)
        else:
            for channel, log_ns, data, seq in batch:
                w.add_message(channel, log_ns, data, log_ns, sequence=seq)
        if start % 370 == 0:
            if fast and compress is not None:
                mcap_messages.finish_chunk(w, compress)
            else:
                w.flush()
    w.finish()
    return out.getvalue()


@pytest.mark.parametrize("chunk_size", [1 << 20, 4096])
def test_many_messages_at_once_make_the_librarys_file(chunk_size, monkeypatch):
    """Byte for byte the file of the library's add_message, chunks filling up mid-batch too
    (4 kB chunks); and through add_message itself where the version is not the checked one."""
    assert mcap_messages.FAST                           # the pinned version
    want = _messages_file(False, chunk_size)
    assert _messages_file(True, chunk_size) == want
    monkeypatch.setattr(mcap_messages, "FAST", False)
    assert _messages_file(True, chunk_size) == want


def test_a_chunk_finished_with_a_compressor_made_once_is_the_library_s_chunk(monkeypatch):
    """finish_chunk with a level-3 compressor writes the library's file byte for byte (its
    chunks, their message indexes, the summary that indexes them); at the recorder's level
    (a fast one) the same messages read back from a file of its own; elsewhere it is
    writer.flush()."""
    want = _messages_file(False, 1 << 20)
    assert _messages_file(True, 1 << 20, level=3) == want
    fast1 = _messages_file(True, 1 << 20, level=ZSTD_LEVEL)
    assert fast1 != want

    def read(data):
        reader = make_reader(io.BytesIO(data))
        return [(c.topic, m.log_time, m.sequence, m.data) for _s, c, m in
                reader.iter_messages(log_time_order=False)], reader.get_summary().statistics
    assert read(fast1) == read(want)
    monkeypatch.setattr(mcap_messages, "FAST", False)
    assert _messages_file(True, 1 << 20, level=ZSTD_LEVEL) == want
