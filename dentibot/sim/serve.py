"""A virtual DentiBot on loopback: one simulated World behind the four real wire protocols.

- Meca500 TCP text API on ``meca_port`` (monitoring on the next port);
- ATI Net F/T RDT over UDP on ``netft_port`` plus its HTTP calibration page on ``netft_http_port``;
- the auxiliary-I/O Modbus TCP server on ``modbus_port``;
- the EPOS4 as a CANopen node on a python-can ``virtual`` bus (read on the event loop:
  :class:`~dentibot.io.virtual_bus.LoopVirtualBus`), exposed to other processes
  through a socketcand-compatible TCP endpoint on ``can_port`` (channel ``can_channel``) and,
  with ``can_interface`` set, on that python-can bus as well (e.g. ``socketcan`` on a kernel
  vcan named ``can_channel``: :class:`~dentibot.sim.can_bus_attach.CanBusBridge`);
- the patient tracker's six CiA 406 draw-wire encoders (node ids 0x21..0x26) on the same
  CAN bus (``tracker``, on by default: they stay PRE-OPERATIONAL and silent, heartbeat off,
  until a tracker driver configures and starts them).

The aux I/O's host-lost output is wired to the EPOS4's safe-torque-off input (in series with
the emergency stop, as a clinic's safety relay chain would be): when the host stops feeding the
aux watchdog, the drive loses its power stage and the file stops, whatever the drive's own
heartbeat supervision says (``docs/device-liveness.md``).

The World is stepped in real time (:class:`~dentibot.sim.timing.RealTimeStepper`). Everything
binds to ``host`` (127.0.0.1 unless configured otherwise): nothing accepts remote commands by
default. Port 0 means an ephemeral port (tests); the bound ports are in :attr:`ports`.
"""

from __future__ import annotations

import asyncio
import itertools
from dataclasses import dataclass

import can
import structlog

from dentibot.errors import ConfigError
from dentibot.io.devices import DevicesConfig, TrackerConfig, loopback_config
from dentibot.io.virtual_bus import LoopVirtualBus
from dentibot.sim.aux_modbus_server import AuxModbusServer
from dentibot.sim.can_bus_attach import CanBusBridge, open_bus
from dentibot.sim.epos4_node import Epos4Node
from dentibot.sim.meca500_server import Meca500Server
from dentibot.sim.netft_server import NetFTServer
from dentibot.sim.socketcand import SocketcandServer
from dentibot.sim.timing import RealTimeStepper
from dentibot.sim.tracker_device import TrackerSimParams
from dentibot.sim.tracker_nodes import TrackerNodes
from dentibot.sim.world import World, WorldConfig

log = structlog.get_logger("dentibot.sim.serve")
#: The STO source name of the aux I/O's host-lost relay.
STO_AUX_HOST_LOST = "aux host-lost"
_bus_ids = itertools.count(1)


@dataclass(frozen=True)
class ServePorts:
    host: str = "127.0.0.1"
    meca_port: int = 10000
    netft_port: int = 49152
    netft_http_port: int = 8080
    modbus_port: int = 5020
    can_port: int = 29536
    can_channel: str = "vcan0"
    node_id: int = 1
    netft_rate_hz: float = 500.0
    #: python-can interface to attach the CAN bus to as well ("socketcan" for a kernel vcan
    #: named ``can_channel``); None: socketcand only.
    can_interface: str | None = None
    #: the patient tracker's encoders on the CAN bus.
    tracker: bool = True


class VirtualDentiBot:
    """All four wire simulators over one World; ``async with`` starts and stops them."""

    def __init__(self, world: World | WorldConfig | None = None,
                 ports: ServePorts = ServePorts(),
                 tracker: TrackerSimParams | None = None) -> None:
        self.world = world if isinstance(world, World) else World(world)
        self.cfg = ports
        self.tracker_params = tracker or TrackerSimParams()
        self.tracker: TrackerNodes | None = None
        self._tracker_bus: can.BusABC | None = None
        self.stepper = RealTimeStepper(self.world)
        self._bus_channel = f"dentibot-serve-{id(self)}-{next(_bus_ids)}"
        self._bus: can.BusABC | None = None
        self._stop = asyncio.Event()
        self._step_task: asyncio.Task | None = None
        self.meca: Meca500Server | None = None
        self.netft: NetFTServer | None = None
        self.modbus: AuxModbusServer | None = None
        self.epos: Epos4Node | None = None
        self.socketcand: SocketcandServer | None = None
        self.can_bridge: CanBusBridge | None = None

    @property
    def can_channel(self) -> str:
        """The in-process virtual bus channel (same-process drivers use it directly)."""
        return self._bus_channel

    @property
    def ports(self) -> dict:
        return {
            "host": self.cfg.host,
            "meca_port": self.meca.port, "meca_monitor_port": self.meca.monitor_port,
            "netft_port": self.netft.port, "netft_http_port": self.netft.http_port,
            "modbus_port": self.modbus.port, "can_port": self.socketcand.port,
            "can_channel": self.cfg.can_channel, "can_virtual_channel": self._bus_channel,
            "can_interface": self.cfg.can_interface,
        }

    def devices_config(self, tracker: bool = False,
                       ft_stale_after_ms: float | None = None) -> DevicesConfig:
        """The device configuration that points the real drivers at these simulators
        (``tracker``: with the patient tracker's section, its geometry the simulator's;
        ``ft_stale_after_ms``: the F/T driver's own freshness bound, the hardware default
        unless given)."""
        p = self.ports
        return loopback_config(p["host"], p["meca_port"], p["netft_port"], p["netft_http_port"],
                               p["modbus_port"], p["can_port"], p["can_channel"],
                               meca_monitor_port=p["meca_monitor_port"],
                               tracker=self.tracker_config() if tracker else None,
                               ft_stale_after_ms=ft_stale_after_ms)

    def tracker_config(self) -> TrackerConfig:
        """The ``tracker:`` section for the simulated encoders (through socketcand; SYNC
        from the handpiece driver)."""
        if self.tracker is None:
            raise ConfigError("sim.tracker", False, "a VirtualDentiBot started with the tracker")
        tp, p = self.tracker_params, self.ports
        return TrackerConfig(
            interface="socketcand", host=p["host"], port=p["can_port"],
            channel=p["can_channel"], node_ids=[n.node_id for n in self.tracker.nodes],
            mount_anchors_mm=[tuple(map(float, a)) for a in tp.mount_mm],
            tooth_anchors_mm=[tuple(map(float, b)) for b in tp.tooth_mm],
            resolution_mm=tp.resolution_mm, drum_mm_per_rev=tp.drum_mm_per_rev,
            range_mm=tp.range_mm, zero_length_mm=[tp.zero_length_mm] * len(tp.mount_mm),
            min_length_mm=tp.min_length_mm, max_length_mm=tp.max_length_mm)

    async def start(self) -> None:
        c, w = self.cfg, self.world
        self._stop.clear()
        self._step_task = asyncio.create_task(self.stepper.run(self._stop),
                                              name="world-stepper")
        self.meca = Meca500Server(w, c.host, c.meca_port,
                                  None if c.meca_port else 0)
        self.netft = NetFTServer(w, c.host, c.netft_port, http_port=c.netft_http_port,
                                 rate_hz=c.netft_rate_hz)
        self.modbus = AuxModbusServer(w, c.host, c.modbus_port)
        self._bus = LoopVirtualBus(channel=self._bus_channel, receive_own_messages=False)
        self.epos = Epos4Node(w, self._bus, c.node_id)
        epos = self.epos
        self.modbus.host_lost_outputs.append(
            lambda lost: epos.set_sto(STO_AUX_HOST_LOST, lost))
        self.socketcand = SocketcandServer(
            LoopVirtualBus(channel=self._bus_channel), c.host, c.can_port, c.can_channel)
        if c.tracker:
            self._tracker_bus = LoopVirtualBus(channel=self._bus_channel)
            self.tracker = TrackerNodes(w, self._tracker_bus, self.tracker_params)
        try:
            if c.can_interface:
                outer = open_bus(c.can_interface, c.can_channel)
                self.can_bridge = CanBusBridge(
                    can.Bus(interface="virtual", channel=self._bus_channel), outer,
                    own_buses=True)
                self.can_bridge.start()
            for server in (self.meca, self.netft, self.modbus, self.epos, self.tracker,
                           self.socketcand):
                if server is not None:
                    await server.start()
        except BaseException:
            await self.close()
            raise
        log.info("virtual dentibot serving", **self.ports)

    async def close(self) -> None:
        self._stop.set()
        for server in (self.socketcand, self.tracker, self.epos, self.modbus, self.netft,
                       self.meca):
            if server is not None:
                await server.close()
        if self._tracker_bus is not None:
            self._tracker_bus.shutdown()
            self._tracker_bus = None
        if self.socketcand is not None:
            self.socketcand.bus.shutdown()
        if self.can_bridge is not None:
            self.can_bridge.close()
            self.can_bridge = None
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None
        if self._step_task is not None:
            await self._step_task
            self._step_task = None

    async def __aenter__(self) -> VirtualDentiBot:  # noqa: PYI034
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()
