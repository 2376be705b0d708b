"""The recorder process's journal from compiled code: blocks sent by a compiled loop reach the
recording as record_block's, within the same budget, and its failures are raised as
record_block raises them."""

from __future__ import annotations

import io
import itertools
import os
import signal

import numpy as np
import pytest
from mcap.reader import make_reader
from numba import njit
from telemetry_helpers import real_row

from dentibot.telemetry.blocks import WIDTH, TickBlock
from dentibot.telemetry.recorder import TelemetryOverflow
from dentibot.telemetry.recorder_process import RecorderProcess, Wire
from dentibot.telemetry.schema import TelemetryError
from dentibot.telemetry.wire_kernels import NO_ROOM, OK, OTHER, PIPE, STATUS, send_block

pytestmark = pytest.mark.timeout(60)

RATE_HZ = 500.0
TS = 1.0 / RATE_HZ
META = {"protocol": "wire", "seed": 1, "rate_hz": RATE_HZ, "start_wall_ns": 10**18}
BLOCK = ("4:drill", "treating.drilling.feeding", TS, 16.0, 2, (180.0, 0.0, 90.0))


def _block(rows: np.ndarray, k0: int) -> TickBlock:
    step, state, ts, wl, rev, euler = BLOCK
    return TickBlock(rows, k0, ts, step, state, wl, rev, euler)


@njit(nogil=True)
def _send(wire, rows_u8, starts, k0):
    """A compiled loop's sends: rows ``starts[j]`` to ``starts[j + 1]`` as block ``j``, until
    one is not sent or a report stops it; how many were sent."""
    st, hdr, ring, msg, head, k0_at, n_at = wire
    sent = 0
    for j in range(starts.shape[0] - 1):
        if not send_block(st, hdr, ring, msg, head, k0_at, n_at, rows_u8, starts[j],
                          starts[j + 1], k0 + starts[j]):
            break
        sent += 1
        if st[STATUS] != OK:
            break
    return sent


def _rows(n: int) -> np.ndarray:
    k = np.arange(n)[:, None]
    return np.ascontiguousarray(k + np.arange(WIDTH)[None, :] / 100.0)


def _messages(path) -> list:
    with open(path, "rb") as f:
        data = f.read()
    return [(c.topic, m.log_time, m.sequence, m.data) for _s, c, m in
            make_reader(io.BytesIO(data)).iter_messages()]


def test_blocks_sent_by_compiled_code_make_the_recording_record_block_makes(tmp_path):
    rows = _rows(160)
    starts = np.array([0, 25, 50, 75, 100, 125, 150], dtype=np.int64)
    paths = []
    for wired in (True, False):
        path = tmp_path / f"w{wired}.mcap"
        rec = RecorderProcess(path, dict(META), validate=False, max_queue=50)
        if wired:
            wire = Wire(rec, WIDTH, 256)
            assert _send(wire.begin(*BLOCK), rows.view(np.uint8), starts, 0) == 6
            wire.end(149, TS, 25)
            assert rec.rows_queued == 150 and rec.at_risk_max <= rec.budget == 50
            rec.record_block(_block(rows[150:], 150))     # the rest, from Python
        else:
            for a, b in itertools.pairwise(starts):
                rec.record_block(_block(rows[a:b], int(a)))
            rec.record_block(_block(rows[150:], 150))
        rec.close()
        assert rec.ticks_written == 160 and rec.rows_dropped == 0
        paths.append(path)
    got, want = (_messages(p) for p in paths)
    assert len(got) == len(want) > 320 and got == want


def test_what_was_handed_over_before_goes_first(tmp_path):
    """A row and an event still in the recorder's batch reach the file before the blocks
    the compiled loop sends."""
    path = tmp_path / "order.mcap"
    rec = RecorderProcess(path, dict(META), validate=False)
    rec.record(real_row(0))
    rec.event("note", "before the blocks")
    wire = Wire(rec, WIDTH, 256)
    rows = _rows(51)
    assert _send(wire.begin(*BLOCK), rows.view(np.uint8), np.array([1, 26, 51]), 0) == 2
    wire.end(50, TS, 25)
    rec.close()
    ticks = [m for m in _messages(path) if m[0] in ("/tick", "/events")]
    assert [t for t, *_ in ticks[:2]] == ["/tick", "/events"]
    assert [seq for t, _, seq, _ in ticks if t == "/tick"] == list(range(51))


def test_a_stopped_recorder_process_is_an_overflow_of_the_block_that_found_no_room(tmp_path):
    rec = RecorderProcess(tmp_path / "stop.mcap", dict(META), validate=False, max_wait_s=0.2,
                          max_queue=50)
    wire = Wire(rec, WIDTH, 256)
    rows = _rows(100)
    args = wire.begin(*BLOCK)
    os.kill(rec.pid, signal.SIGSTOP)
    try:
        # two blocks fill the budget of 50; the third waits 0.2 s for the file, in vain
        sent = _send(args, rows.view(np.uint8), np.array([0, 25, 50, 75]), 0)
        assert sent == 2 and wire.st[STATUS] == NO_ROOM
        with pytest.raises(TelemetryOverflow, match="made no room in 0.2 s") as err:
            wire.end(49, TS, 25)
        assert err.value.rows_dropped == 25 and rec.overflowed and rec.rows_queued == 50
    finally:
        os.kill(rec.pid, signal.SIGCONT)
    rec.close("fault", "telemetry overflow")
    assert rec.ticks_written == 50


def test_a_dead_recorder_process_stops_the_sends_and_is_raised(tmp_path):
    rec = RecorderProcess(tmp_path / "dead.mcap", dict(META), validate=False)
    wire = Wire(rec, WIDTH, 256)
    rows = _rows(100)
    args = wire.begin(*BLOCK)
    os.kill(rec.pid, signal.SIGKILL)
    rec._proc.join(5.0)
    sent = _send(args, rows.view(np.uint8), np.array([0, 25, 50, 75, 100]), 0)
    assert sent < 4 and wire.st[STATUS] in (PIPE, OTHER)
    with pytest.raises(TelemetryError, match="recorder process"):
        wire.end(25 * sent - 1, TS, 25)
    with pytest.raises(TelemetryError):
        wire.begin(*BLOCK)                        # and stays dead
    rec.close("fault", "recorder died")
