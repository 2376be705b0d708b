"""LoopVirtualBus: python-can's virtual bus, both ways with plain virtual buses of the same
channel, read by the event loop without a thread and without leaving a frame behind."""

import asyncio
import select
import threading
import time
import uuid

import can
import pytest

from dentibot.io.can_reader import MAX_BATCH, LoopReader
from dentibot.io.virtual_bus import LoopVirtualBus


def _channel() -> str:
    return f"loopbus-{uuid.uuid4().hex}"


def _readable(fd: int) -> bool:
    return bool(select.select([fd], [], [], 0)[0])


def _msg(i: int, can_id: int = 0x181) -> can.Message:
    return can.Message(arbitration_id=can_id, data=i.to_bytes(4, "little"),
                       is_extended_id=False)


def test_it_talks_to_plain_virtual_buses_both_ways_with_their_semantics():
    ch = _channel()
    loop_bus = LoopVirtualBus(channel=ch)
    plain = can.Bus(interface="virtual", channel=ch)
    other = can.Bus(interface="virtual", channel=ch)
    try:
        sent = can.Message(arbitration_id=0x201, data=[1, 2, 3], is_extended_id=False)
        loop_bus.send(sent)
        a, b = plain.recv(1.0), other.recv(1.0)
        assert loop_bus.recv(0) is None                   # not its own frame
        for got in (a, b):
            assert (got.arbitration_id, bytes(got.data), got.dlc) == (0x201, b"\x01\x02\x03", 3)
            assert got.is_rx and not got.is_extended_id and got.channel == ch
            assert abs(got.timestamp - time.time()) < 5.0
        a.data[0] = 99                                    # each receiver its own copy
        assert b.data[0] == 1 and sent.data[0] == 1
        plain.send(_msg(7))
        got = loop_bus.recv(1.0)
        assert int.from_bytes(got.data, "little") == 7 and got.is_rx
    finally:
        for bus in (loop_bus, plain, other):
            bus.shutdown()


def test_own_frames_when_asked_and_a_full_queue_as_python_can_reports_it():
    ch = _channel()
    own = LoopVirtualBus(channel=ch, receive_own_messages=True, rx_queue_size=1)
    try:
        own.send(_msg(1))
        got = own.recv(0)
        assert got is not None and not got.is_rx          # its own frame, sent not received
        own.send(_msg(2))
        with pytest.raises(can.CanOperationError, match="one or more recipients"):
            own.send(_msg(3), timeout=0.01)               # the queue holds one frame
    finally:
        own.shutdown()


def test_the_descriptor_is_readable_exactly_while_frames_wait():
    ch = _channel()
    rx = LoopVirtualBus(channel=ch)
    tx = can.Bus(interface="virtual", channel=ch)
    try:
        fd = rx.fileno()
        assert not _readable(fd)
        for i in range(5):
            tx.send(_msg(i))
        assert _readable(fd)
        assert [int.from_bytes(m.data, "little") for m in rx.drain(3)] == [0, 1, 2]
        assert _readable(fd)                              # two still wait
        assert [int.from_bytes(m.data, "little") for m in rx.drain(10)] == [3, 4]
        assert not _readable(fd)
        tx.send(_msg(5))
        assert _readable(fd) and rx.recv(0) is not None and rx.recv(0) is None
        assert not _readable(fd)
    finally:
        rx.shutdown()
        tx.shutdown()
    with pytest.raises(can.CanOperationError):
        rx.drain(1)


async def test_the_loop_reads_it_without_a_thread_and_leaves_no_frame_behind():
    """Another thread sends 20,000 frames in bursts while the loop reads: every one arrives,
    in order, in far fewer hand-overs than frames."""
    ch = _channel()
    rx = LoopVirtualBus(channel=ch)
    tx = can.Bus(interface="virtual", channel=ch)
    got: list[int] = []
    reader = LoopReader(rx, lambda m: got.append(int.from_bytes(m.data, "little")),
                        loop=asyncio.get_running_loop())
    n = 20_000

    def burst() -> None:
        for i in range(n):
            tx.send(_msg(i))
            if i % 97 == 0:
                time.sleep(0.0002)

    try:
        assert not reader.threaded
        sender = threading.Thread(target=burst)
        sender.start()
        t_end = time.monotonic() + 30.0
        while len(got) < n and time.monotonic() < t_end:
            await asyncio.sleep(0.001)
        sender.join()
        await asyncio.sleep(0.01)
        assert got == list(range(n))
        assert reader.batches < n and reader.frames == n
        assert not _readable(rx.fileno())
    finally:
        reader.stop()
        rx.shutdown()
        tx.shutdown()


async def test_filters_are_kept_on_the_loop():
    """With receive filters the reader takes frames one by one (python-can filters them):
    only the matching ones arrive, and the descriptor is left clear."""
    ch = _channel()
    rx = LoopVirtualBus(channel=ch, can_filters=[{"can_id": 0x181, "can_mask": 0x7FF}])
    tx = can.Bus(interface="virtual", channel=ch)
    got: list[int] = []
    reader = LoopReader(rx, lambda m: got.append(m.arbitration_id),
                        loop=asyncio.get_running_loop())
    try:
        for i in range(MAX_BATCH + 10):
            tx.send(_msg(i, 0x181 if i % 2 else 0x281))
        t_end = time.monotonic() + 5.0
        while len(got) < (MAX_BATCH + 10) // 2 and time.monotonic() < t_end:
            await asyncio.sleep(0.002)
        await asyncio.sleep(0.01)
        assert got == [0x181] * ((MAX_BATCH + 10) // 2)
        assert not _readable(rx.fileno())
    finally:
        reader.stop()
        rx.shutdown()
        tx.shutdown()
