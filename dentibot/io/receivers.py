"""The drivers' receiver threads: the threads of the control process that read a device's
link and hand what they read to the event loop (a CAN bus's reader; the other drivers read
in the event loop itself).

They take the interpreter lock like the control loop does. A receiver preempted by another
job while it holds the lock stalls the control loop until it runs again, however high the
loop's own priority (at 500 Hz over the wire with one CPU-bound job beside it, ticks woke
1-12 ms late a few times a minute). So the control loop raises them with itself while it
runs (``dentibot.runtime.clock.others_raised``); a receiver only ever runs briefly between
two blocking reads, so it may run ahead of ordinary jobs without taking a core from them.
"""

from __future__ import annotations

import threading
import weakref

_THREADS: weakref.WeakSet[threading.Thread] = weakref.WeakSet()


def register(thread: threading.Thread) -> None:
    """``thread`` (started) is a receiver until it ends."""
    _THREADS.add(thread)


def native_ids() -> set[int]:
    """The kernel's thread ids of the receivers alive now."""
    return {t.native_id for t in list(_THREADS) if t.is_alive() and t.native_id is not None}
