"""The /tick messages in CDR, held to Foxglove's own ROS 2 codec (``mcap_ros2``): the same
bytes as its encoder, read back by its decoder, and by ours to the row recorded."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic
from telemetry_helpers import ramp_row

from dentibot.telemetry.blocks import COL, WIDTH, TickBlock
from dentibot.telemetry.cdr import (
    CDR_LE,
    TICK_CODEC,
    TICK_SCHEMA_NAME,
    BlockEncoder,
    CdrError,
    definition,
)
from dentibot.telemetry.schema import TICK_FIELDS, Field

TEXT = definition(TICK_FIELDS)
THEIR_ENCODE = serialize_dynamic(TICK_SCHEMA_NAME, TEXT)[TICK_SCHEMA_NAME]
THEIR_DECODE = generate_dynamic(TICK_SCHEMA_NAME, TEXT)[TICK_SCHEMA_NAME]


def _theirs(row: dict) -> dict:
    """The row as mcap_ros2's encoder takes it: an unknown number NaN, an unknown pose an
    empty sequence."""
    out = {}
    for f in TICK_FIELDS:
        v = row.get(f.name)
        out[f.name] = ([] if f.length else math.nan) if v is None else v
    return out


def test_the_definition_is_one_line_per_field_with_its_ros_2_type():
    lines = TEXT.splitlines()
    assert len(lines) == len(TICK_FIELDS)
    assert lines[0].startswith("float64 t  # s: ")
    assert lines[1].startswith("int64 tick  #")
    assert "string step  #" in TEXT and "bool overrun  #" in TEXT
    assert "float64[6] q_deg  #" in TEXT and "float64[] phantom_pose  #" in TEXT
    assert "string[] events  #" in TEXT


def test_a_row_is_the_bytes_of_foxglove_s_encoder_and_reads_back_equal():
    row = ramp_row(7, phantom_pose=None, depth_mm=None, events=["fault", "reversal"],
                   step="4:drill", state="treating.drilling.feeding", fractured=True)
    data = TICK_CODEC.encode(row)
    assert data[:4] == CDR_LE
    assert data == bytes(THEIR_ENCODE(_theirs(row)))
    msg = THEIR_DECODE(data)
    assert (msg.t, msg.tick, msg.step, msg.events) == (row["t"], 7, "4:drill",
                                                       ["fault", "reversal"])
    assert list(msg.phantom_pose) == [] and math.isnan(msg.depth_mm) and msg.fractured
    assert TICK_CODEC.decode(data) == {f.name: row.get(f.name) for f in TICK_FIELDS}


def test_the_layout_by_hand():
    """t at byte 4 (after the header), tick at 12, then step's length (with its NUL) and
    text; state after it, its length aligned to 4; q_deg's first number aligned to 8 past
    the header."""
    row = ramp_row(3, step="ab", state="xyz")
    data = TICK_CODEC.encode(row)
    assert struct.unpack_from("<d", data, 4)[0] == row["t"]
    assert struct.unpack_from("<q", data, 12)[0] == 3
    assert struct.unpack_from("<I", data, 20)[0] == 3 and data[24:27] == b"ab\0"
    assert struct.unpack_from("<I", data, 28)[0] == 4 and data[32:36] == b"xyz\0"
    # 36 bytes in, 32 past the header: a multiple of 8, q_deg starts there
    assert list(struct.unpack_from("<6d", data, 36)) == row["q_deg"]


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=60, deadline=None)
@given(t=finite, tick=st.integers(0, 2**40), step=st.text(max_size=12),
       state=st.text(max_size=30), q=st.lists(finite, min_size=6, max_size=6),
       phantom=st.none() | st.lists(finite, min_size=6, max_size=6),
       depth=st.none() | finite, events=st.lists(st.text(max_size=8), max_size=3),
       flags=st.tuples(st.booleans(), st.booleans(), st.booleans()))
def test_any_row_matches_foxglove_s_codec_both_ways(t, tick, step, state, q, phantom, depth,
                                                    events, flags):
    row = ramp_row(0, t=t, tick=tick, step=step, state=state, q_deg=q, phantom_pose=phantom,
                   depth_mm=depth, events=events, patient_moved=flags[0],
                   fractured=flags[1], overrun=flags[2])
    data = TICK_CODEC.encode(row)
    assert data == bytes(THEIR_ENCODE(_theirs(row)))
    assert TICK_CODEC.decode(data) == {f.name: row.get(f.name) for f in TICK_FIELDS}
    assert TICK_CODEC.decode(bytes(THEIR_ENCODE(_theirs(row)))) == TICK_CODEC.decode(data)


def test_a_row_that_does_not_fit_names_its_field():
    with pytest.raises(CdrError, match="q_deg: 2 items, expected 6"):
        TICK_CODEC.encode(ramp_row(0, q_deg=[1.0, 2.0]))
    with pytest.raises(CdrError, match="step: None is not a string"):
        TICK_CODEC.encode(ramp_row(0, step=None))
    with pytest.raises(CdrError, match="tick: 1.5 is not an integer"):
        TICK_CODEC.encode(ramp_row(0, tick=1.5))
    with pytest.raises(CdrError, match="header"):
        TICK_CODEC.decode(b"\x00\x00\x00\x00" + bytes(8))
    with pytest.raises(CdrError, match="does not fit"):
        TICK_CODEC.decode(TICK_CODEC.encode(ramp_row(0))[:40])


def test_types_without_an_unknown_value_in_cdr_are_refused():
    with pytest.raises(CdrError, match="nullable integer"):
        definition((Field("n", "integer", "", "", nullable=True),))
    with pytest.raises(CdrError, match="object"):
        definition((Field("o", "string", "", "", length=-1),))


def test_a_block_s_messages_are_its_rows_messages():
    """TickBlock.tick_cdr writes, by copying columns into a template, the bytes of each row
    encoded alone, a NaN (an unknown depth) included."""
    rng = np.random.default_rng(4)
    cols = rng.normal(size=(30, WIDTH))
    cols[5, COL["depth_mm"]] = math.nan
    block = TickBlock(cols, 1000, 0.002, "4:drill", "treating.drilling.feeding", 16.0, 3,
                      (-180.0, 2.0, 180.0))
    rows = block.rows()
    assert block.tick_cdr() == [TICK_CODEC.encode(r) for r in rows]
    assert block.tick_cdr(10, 14) == [TICK_CODEC.encode(r) for r in rows[10:14]]
    assert TICK_CODEC.decode(block.tick_cdr(5, 6)[0])["depth_mm"] is None


def test_the_block_encoder_puts_every_number_in_a_word():
    row = ramp_row(0, step="odd", state="lengths!")
    enc = BlockEncoder(TICK_FIELDS, row)
    buf = enc.buffer(2)
    buf[1, enc.slot("q_deg", 4)] = 123.5
    buf.view(np.int64)[1, enc.slot("tick")] = 77
    one, two = enc.messages(buf)
    assert one == TICK_CODEC.encode(row)
    assert TICK_CODEC.decode(two) == {**TICK_CODEC.decode(one), "tick": 77,
                                      "q_deg": [*row["q_deg"][:4], 123.5, row["q_deg"][5]]}


def test_text_that_is_not_utf_8_names_its_field():
    with pytest.raises(CdrError, match="state: .* is not UTF-8"):
        TICK_CODEC.encode(ramp_row(0, state="half \ud800 a pair"))
