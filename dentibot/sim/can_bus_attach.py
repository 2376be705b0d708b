"""Attach the simulated CAN bus to another python-can bus: a kernel vcan, or any interface.

The simulated EPOS4 node (:class:`~dentibot.sim.epos4_node.Epos4Node`) sits on an in-process
python-can ``virtual`` channel, which :class:`~dentibot.sim.socketcand.SocketcandServer` makes
reachable over TCP. :class:`CanBusBridge` joins that channel to a second bus, opened from a
python-can interface and channel::

    external = open_bus("socketcan", "vcan0")          # a kernel virtual CAN interface
    bridge = CanBusBridge(can.Bus(interface="virtual", channel=sim_channel), external)

so that any SocketCAN program on the host (python-canopen, candump, a CANopen master) sees the
node on ``vcan0``, while socketcand clients keep seeing it too: the two buses become one.

Every data frame received on one side is sent on the other, unchanged (identifier, 11/29 bit,
data, remote flag); error frames are not forwarded. Neither side hears its own frames
(python-can's ``receive_own_messages`` is off by default, for ``socketcan`` and ``virtual``
alike), so nothing loops back. A frame that cannot be sent (a full or downed interface) is
counted in ``send_errors`` and dropped, as a CAN controller drops it after its retries.

Creating a kernel vcan needs root and is the host's business, not this module's::

    sudo modprobe vcan
    sudo ip link add dev vcan0 type vcan
    sudo ip link set up vcan0

python-can's ``virtual`` interface stands in for it in tests (one process only).
"""

from __future__ import annotations

import threading
from typing import Self

import can
import structlog

from dentibot.errors import ConfigError

log = structlog.get_logger(__name__)


def open_bus(interface: str, channel: str, **kwargs) -> can.BusABC:
    """A python-can bus on ``interface``/``channel`` (e.g. ``socketcan``/``vcan0``), with a
    :class:`ConfigError` that names the set-up step when it cannot be opened."""
    try:
        return can.Bus(interface=interface, channel=channel, **kwargs)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        hint = (f" (as root: modprobe vcan, ip link add dev {channel} type vcan, "
                f"ip link set up {channel})" if interface == "socketcan" else "")
        raise ConfigError("sim.can_interface", f"{interface}/{channel}",
                          f"a python-can bus that can be opened{hint}: {exc}") from exc


class _Forward(can.Listener):
    def __init__(self, bridge: CanBusBridge, target: can.BusABC, direction: str) -> None:
        self.bridge = bridge
        self.target = target
        self.direction = direction

    def on_message_received(self, msg: can.Message) -> None:
        self.bridge._forward(msg, self.target, self.direction)


class CanBusBridge:
    """Forwards every frame between ``inner`` (the simulator's bus) and ``outer`` (the
    external one), both ways, from python-can Notifier threads. Counters: ``to_outer``,
    ``to_inner``, ``send_errors``. ``start()``/``close()`` (or ``with``); the buses stay the
    caller's unless ``own_buses``: then ``close()`` shuts them down."""

    def __init__(self, inner: can.BusABC, outer: can.BusABC, *,
                 own_buses: bool = False) -> None:
        if inner is outer:
            raise ConfigError("sim.can_bridge", "one bus", "two different buses")
        self.inner = inner
        self.outer = outer
        self.own_buses = own_buses
        self.to_outer = 0
        self.to_inner = 0
        self.send_errors = 0
        self._lock = threading.Lock()
        self._notifiers: list[can.Notifier] = []
        self._closed = False

    def start(self) -> None:
        if self._notifiers:
            return
        if self._closed:
            raise ConfigError("sim.can_bridge", "closed", "a bridge that has not been closed")
        self._notifiers = [
            can.Notifier(self.inner, [_Forward(self, self.outer, "to_outer")], timeout=0.05),
            can.Notifier(self.outer, [_Forward(self, self.inner, "to_inner")], timeout=0.05),
        ]
        log.info("can bus attached", outer=getattr(self.outer, "channel_info", "?"))

    def close(self) -> None:
        """Stop forwarding (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for notifier in self._notifiers:
            notifier.stop(timeout=1.0)
        self._notifiers = []
        if self.own_buses:
            self.inner.shutdown()
            self.outer.shutdown()

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _forward(self, msg: can.Message, target: can.BusABC, direction: str) -> None:
        if self._closed or msg.is_error_frame:
            return
        out = can.Message(arbitration_id=msg.arbitration_id, data=bytes(msg.data),
                          dlc=msg.dlc, is_extended_id=msg.is_extended_id,
                          is_remote_frame=msg.is_remote_frame)
        try:
            target.send(out)
        except (can.CanError, OSError) as exc:
            with self._lock:
                self.send_errors += 1
            log.warning("can bridge send failed", direction=direction, error=str(exc),
                        cob_id=hex(msg.arbitration_id))
            return
        with self._lock:
            setattr(self, direction, getattr(self, direction) + 1)
