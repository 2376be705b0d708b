"""The recorder process's journal: a ring of messages in a file, written by one process and
read by another, that keeps what the recording file lacks through a crash of either; and
``dentibot recover`` adding what it holds to the file."""

from __future__ import annotations

import os
import pickle
import signal
import time

import numpy as np
import pytest
from numba import njit
from telemetry_helpers import real_row

from dentibot.cli import main
from dentibot.telemetry import read_recording
from dentibot.telemetry.blocks import WIDTH, TickBlock
from dentibot.telemetry.journal import (
    HEAD,
    LENGTH_BYTES,
    SETTLED,
    Journal,
    items_of,
    journal_path,
    read_journal,
)
from dentibot.telemetry.recorder_process import RecorderProcess
from dentibot.telemetry.recover import recover_recording
from dentibot.telemetry.schema import TelemetryError
from dentibot.telemetry.wire_kernels import (
    BUDGET,
    MAX_WAIT_MS,
    OK,
    QUEUED,
    ST_SIZE,
    STATUS,
    send_block,
)

pytestmark = pytest.mark.timeout(120)

META = {"protocol": "journal-test", "rate_hz": 500.0, "start_wall_ns": 1_700_000_000 * 10**9}


def test_messages_wrap_around_the_ring_and_come_back_whole_and_in_order(tmp_path):
    """A 100-byte ring, messages of 1 to 40 bytes: each takes its length + 4 bytes of room,
    wraps at the end when it must, and reads back as written; released bytes are room again."""
    j = Journal.create(tmp_path / "r.journal", 100)
    rng = np.random.default_rng(3)
    written, read_at, wrapped = [], 0, 0
    for _ in range(300):
        msg = rng.integers(0, 256, int(rng.integers(1, 41)), dtype=np.uint8).tobytes()
        if j.room() < len(msg) + LENGTH_BYTES:    # the reader takes all and releases it
            got = list(j.messages(read_at))
            assert [m for _, m in got] == written
            read_at = got[-1][0]
            j.release(read_at, 0, [])
            written = []
            assert j.room() == 100
        room = j.room()
        head = int(j.hdr[HEAD])
        wrapped += head % 100 + len(msg) + LENGTH_BYTES > 100
        j.put(msg)
        written.append(msg)
        assert j.room() == room - len(msg) - LENGTH_BYTES
    assert wrapped > 10                           # many messages were cut by the ring's end
    # a second mapping of the file (the other process) reads the same
    other = Journal.open(tmp_path / "r.journal")
    assert [m for _, m in other.messages(read_at)] == written
    other.close()
    j.close()


def test_a_journal_left_by_a_crash_gives_the_messages_after_its_tail(tmp_path):
    path = tmp_path / "run.mcap.journal"
    j = Journal.create(path, 64)
    for m in (b"a" * 20, b"b" * 10, b"c" * 30):
        j.put(m)
    j.release(24, 7, [1, 2])                     # the first is in the file
    j.put(b"d" * 6)                              # wraps: 24 + 14 + 34 + 10 > 64
    cells, messages = read_journal(path)
    assert cells == {"tail": 24, "head": 24 + 14 + 34 + 10, "settled": 7}
    assert messages == [b"b" * 10, b"c" * 30, b"d" * 6]
    j.close()
    path.write_bytes(b"not a journal at all" * 20)
    with pytest.raises(TelemetryError, match="not a DentiBot journal"):
        read_journal(path)


def test_a_journal_loads_rows_but_no_code():
    row = real_row(3)
    row["q_deg"] = [np.float64(1.5), 2.0, 3.0, 4.0, 5.0, 6.0]   # numpy scalars are values
    items = [("tick", row), ("event", ("note", "x", None, None))]
    assert items_of(pickle.dumps(items, pickle.HIGHEST_PROTOCOL)) == items

    class Evil:
        def __reduce__(self):
            return (os.system, ("true",))
    with pytest.raises(pickle.UnpicklingError, match="system"):
        items_of(pickle.dumps([("tick", Evil())]))


@njit
def _send_all(st, hdr, ring, msg, head, k0_at, n_at, rows_u8, start, stop, k0):
    return send_block(st, hdr, ring, msg, head, k0_at, n_at, rows_u8, start, stop, k0)


def test_compiled_code_puts_blocks_into_the_ring_as_python_does(tmp_path):
    """Blocks put by the compiled sender into a small ring (wrapping many times) read back as
    the blocks, and the same bytes as :meth:`Journal.put` of their wire form."""
    from dentibot.telemetry.blocks import WIRE_K0_AT, WIRE_N_AT

    step = ("4:drill", "treating.drilling.feeding", 0.002, 16.0, 2, (180.0, 0.0, 90.0))
    rows = np.ascontiguousarray(np.arange(200)[:, None] + np.arange(WIDTH)[None, :] / 100.0)
    head = TickBlock(np.zeros((1, WIDTH)), 0, step[2], *step[:2], *step[3:]).packed()[0]
    msg = np.zeros(LENGTH_BYTES + len(head) + 8 * WIDTH * 25, dtype=np.uint8)
    msg[LENGTH_BYTES:LENGTH_BYTES + len(head)] = np.frombuffer(head, dtype=np.uint8)
    size = LENGTH_BYTES + len(head) + 8 * WIDTH * 7
    compiled = Journal.create(tmp_path / "c.journal", 3 * size + 101)
    by_python = Journal.create(tmp_path / "p.journal", 3 * size + 101)
    st = np.zeros(ST_SIZE, dtype=np.int64)
    st[BUDGET], st[MAX_WAIT_MS] = 10**6, 1
    st[2] = st[3] = -1                            # no pipes: nothing rings, nothing reports
    read_at, got = 0, []
    for k0 in range(0, 196, 7):
        assert _send_all(st, compiled.hdr, compiled.ring, msg, LENGTH_BYTES + len(head),
                         LENGTH_BYTES + WIRE_K0_AT, LENGTH_BYTES + WIRE_N_AT,
                         rows.view(np.uint8), k0, k0 + 7, k0)
        assert st[STATUS] == OK and st[QUEUED] == k0 + 7
        block = TickBlock(rows[k0:k0 + 7], k0, step[2], *step[:2], *step[3:])
        by_python.put(b"".join(block.packed()))
        assert bytes(compiled.ring) == bytes(by_python.ring)
        assert compiled.hdr[HEAD] == by_python.hdr[HEAD]
        for end, m in compiled.messages(read_at):
            (kind, b), = items_of(m)
            assert kind == "block"
            got.append(b)
            read_at = end
        compiled.release(read_at, int(st[QUEUED]), [])
        by_python.release(read_at, 0, [])
    assert compiled.hdr[HEAD] > 4 * compiled.capacity          # wrapped many times
    assert np.array_equal(np.concatenate([b.cols for b in got]), rows[:196])
    assert [b.k0 for b in got] == list(range(0, 196, 7))
    compiled.close()
    by_python.close()


def _stop_and_kill(pid: int) -> None:
    os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            with open(f"/proc/{pid}/stat") as f:
                state = f.read().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            return
        if state == "Z":
            return
        time.sleep(0.02)


def test_a_killed_recorder_process_loses_nothing_recover_adds_the_journal(tmp_path, capsys):
    """150 rows reach the file; the recorder's process frozen, 150 more and an event go into
    the journal only; then it is killed. Items leave in batches of 10 (rows and events
    alike): 151 items made 15 batches and left row 299 waiting; the batch that row 308
    completes still goes into the journal (the control process learns of the death as it
    hands it over), and row 309 raises, saying where the 159 rows not in the file are. The
    file alone has the first 150; the recovered file has all 309, the event and the run's end,
    exactly as they were handed over."""
    path = tmp_path / "run.mcap"
    rec = RecorderProcess(path, dict(META), validate=False)
    rows = [real_row(i) for i in range(320)]
    for row in rows[:150]:
        rec.record(row)
    deadline = time.monotonic() + 10
    while rec._settled < 150 and time.monotonic() < deadline:   # the child's timed flush
        time.sleep(0.01)
    assert rec._settled == 150
    os.kill(rec.pid, signal.SIGSTOP)
    for i, row in enumerate(rows[150:300], start=150):
        rec.record(row)
        if i == 200:
            rec.event("note", "in the journal only")
    assert rec.at_risk == 150 and rec.journal.hdr[SETTLED] == 150
    _stop_and_kill(rec.pid)
    handed = 300
    with pytest.raises(TelemetryError, match=r"159 ticks .* kept in run\.mcap\.journal"):
        for row in rows[300:]:
            rec.record(row)
            handed += 1
    assert handed == 309
    rec.close("fault", "recorder died")
    assert len(read_recording(path).rows) == 150
    cells, _ = read_journal(journal_path(path))
    assert cells["settled"] == 150 and cells["head"] > cells["tail"]
    result = recover_recording(path)
    assert result.journal_ticks == 159 and result.journal_events == 1
    assert (result.ticks, result.first_tick, result.last_tick, result.missing_ticks) == \
        (309, 0, 308, 0)
    got = read_recording(result.out)
    assert got.rows == rows[:309]
    # the run's end, handed over by close() after the death, is in the journal too; a
    # recovered file stays flagged incomplete
    assert got.end == {"status": "fault", "reason": "recorder died", "duration_s": 309 / 500}
    assert not got.complete
    assert [(e["tick"], e["detail"]) for e in got.events] == [(200, "in the journal only")]
    assert got.recovered["journal_ticks"] == "159"
    # the command says what the journal added
    assert main(["recover", str(path), "--out", str(tmp_path / "cli.mcap")]) == 0
    out = capsys.readouterr().out
    assert "recovered 309 ticks" in out
    assert "journal run.mcap.journal: 159 ticks, 1 events, the run end added" in out
