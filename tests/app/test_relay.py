"""The relay: a compiled call's groups of ticks handed over by a thread while the call runs."""

from __future__ import annotations

import gc
import math
import os
import threading
import time
import weakref

import numpy as np
import pytest
from numba import njit

from dentibot.app import relay_kernels as rk
from dentibot.app.relay import Relay


@njit(nogil=True)
def _produce(n, relay, rows, ran_to):
    """A compiled call's shape: hold before each tick, write the row, publish after it;
    ``ran_to[0]`` is the last tick started (read by the test's hand-over)."""
    rk.begin(relay)
    for i in range(n):
        if not rk.hold(relay, i):
            rk.end(relay)
            return i
        ran_to[0] = i
        x = 0.0
        for j in range(2000):                 # some work, so that the two overlap
            x += np.sqrt(j + i)
        rows[i] = x
        rk.publish(relay, i)
    rk.end(relay)
    return n


def _expected(n: int) -> np.ndarray:
    out = np.zeros(n)
    for i in range(n):
        x = 0.0
        for j in range(2000):                     # the kernel's order of additions
            x += math.sqrt(j + i)
        out[i] = x
    return out


def test_every_group_is_handed_over_once_in_order_while_the_call_runs():
    relay = Relay(10, 12)
    rows, ran_to = np.zeros(103), np.zeros(1, dtype=np.int64)
    got, ahead = [], []

    def hand(start, stop, busy_ns):
        ahead.append(int(ran_to[0]) - stop)       # how far the call is past this group
        got.append((start, stop, rows[start:stop].copy(), busy_ns))
        time.sleep(0.002)                         # a slow recorder
        ahead.append(int(ran_to[0]) - stop)
    try:
        relay.start(hand)
        n = _produce(103, relay.kernel_args(), rows, ran_to)
        handed = relay.finish()
    finally:
        relay.close()
    assert n == 103 and handed == 100             # the 3 after the last group: the caller's
    assert [(a, b) for a, b, _, _ in got] == [(k, k + 10) for k in range(0, 100, 10)]
    want = _expected(103)
    for a, b, values, busy_ns in got:
        np.testing.assert_array_equal(values, want[a:b])
        assert busy_ns > 0
    # while a group is handed over, the call computes at most the next group, and waits
    assert max(ahead) <= 9
    assert max(ahead) >= 1                        # ... and does compute it meanwhile
    assert relay.tail_ns > 0


def test_a_failed_hand_over_stops_the_call_before_its_next_tick_and_is_raised():
    relay = Relay(5, 30)
    rows, ran_to = np.zeros(100), np.zeros(1, dtype=np.int64)

    def hand(start, stop, busy_ns):
        if start == 10:
            raise OSError("disk full")
    try:
        relay.start(hand)
        n = _produce(100, relay.kernel_args(), rows, ran_to)
        with pytest.raises(OSError, match="disk full"):
            relay.finish()
        # the group 10-15 failed while the call ran 15-20 at most: it stops before the next
        assert 15 <= n <= 20
        # the relay serves the next call
        seen = []
        relay.start(lambda a, b, ns: seen.append((a, b)))
        assert _produce(12, relay.kernel_args(), rows, ran_to) == 12
        assert relay.finish() == 10 and seen == [(0, 5), (5, 10)]
    finally:
        relay.close()


def test_a_call_without_a_relay_neither_waits_nor_publishes():
    rows, ran_to = np.zeros(40), np.zeros(1, dtype=np.int64)
    args = Relay.off_args()
    assert _produce(40, args, rows, ran_to) == 40
    np.testing.assert_array_equal(rows, _expected(40))
    assert not args[2].any()                       # nothing published, no limit read


def test_a_forgotten_relay_ends_its_thread_and_closes_its_descriptors():
    before = {t.ident for t in threading.enumerate()}
    fds_before = set(os.listdir("/proc/self/fd"))
    relay = Relay(4, 3)
    thread = next(t for t in threading.enumerate() if t.ident not in before)
    assert thread.name == "dentibot-relay"
    gone = weakref.ref(relay)
    del relay
    gc.collect()
    assert gone() is None
    thread.join(2.0)
    assert not thread.is_alive()
    assert set(os.listdir("/proc/self/fd")) <= fds_before


def test_a_group_is_at_least_one_tick():
    with pytest.raises(ValueError, match="every = 0"):
        Relay(0, 1)
