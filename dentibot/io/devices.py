"""Device configuration (YAML) and start-up of the real drivers.

A user with the hardware writes the addresses here; a user without it points the same
drivers at ``dentibot sim serve`` (the defaults of :func:`loopback_config`). No address is
assumed: an empty file, or a device without its host, is an error. Example::

    arm:       {host: 192.168.0.100, control_port: 10000, monitor_port: 10001}
    ft:        {host: 192.168.1.1, port: 49152, http_port: 80}
    handpiece: {interface: socketcand, host: 127.0.0.1, port: 29536, channel: vcan0, node_id: 1}
    aux:       {host: 192.168.0.50, port: 502, device_id: 1}
    tracker:   {interface: socketcand, host: 127.0.0.1, port: 29536, channel: vcan0,
                mount_anchors_mm: [[...], ...], tooth_anchors_mm: [[...], ...]}

Start-up order: F/T stream, aux I/O, handpiece (NMT, PDOs, CiA 402 enable), the patient
tracker when configured (its encoders identified, configured and started), arm (activate,
home, velocity timeout as the dead-man). A failure closes what was opened, then raises.
"""

from __future__ import annotations

import contextlib
import gc
import os
from collections.abc import AsyncIterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field

from dentibot.errors import ConfigError, DeviceFault
from dentibot.io.aux_modbus import AuxModbusDriver
from dentibot.io.epos4 import (
    DEFAULT_CONSUMER_MS,
    DEFAULT_FEED_TIMEOUT_S,
    DEFAULT_HOST_HEARTBEAT_PERIOD_S,
    DEFAULT_HOST_NODE_ID,
    DEFAULT_QUICK_STOP_FILE_RPM_S,
    Epos4Driver,
)
from dentibot.io.meca500 import Meca500Driver
from dentibot.io.netft import NetFTDriver
from dentibot.io.tracker import (
    DEFAULT_DRUM_MM_PER_REV,
    DEFAULT_NODE_IDS,
    DEFAULT_RANGE_MM,
    DEFAULT_RESOLUTION_MM,
    DEFAULT_TRANSMISSION_TYPE,
    DEFAULT_ZERO_LENGTH_MM,
    TrackerDriver,
)
from dentibot.yamlfile import StrictModel, YamlFileError, load


class DevicesFileError(YamlFileError):
    """A device configuration file is malformed or invalid."""

    kind = "device configuration"


class _Strict(StrictModel):
    """A section of the device configuration (see :class:`~dentibot.yamlfile.StrictModel`)."""


class ArmConfig(_Strict):
    host: str = Field(min_length=1, max_length=253, description="the Meca500's address")
    control_port: int = Field(10000, ge=1, le=65535)
    monitor_port: int = Field(10001, ge=1, le=65535)
    vel_timeout_s: float = Field(
        0.05, ge=0.005, le=0.1,
        description="SetVelTimeout, the arm's dead-man (s): the arm stops by itself when no "
                    "velocity command came for this long; at most 50 control periods")
    connection_watchdog_s: float = Field(
        0.2, ge=0.005, le=60.0,
        description="ConnectionWatchdog: the arm stops and drops the connection when DentiBot "
                    "has been silent this long (s)")


class FTConfig(_Strict):
    host: str = Field(min_length=1, max_length=253, description="the Net F/T box's address")
    port: int = Field(49152, ge=1, le=65535)
    http_port: int = Field(80, ge=1, le=65535)
    counts_per_force: float | None = Field(None, gt=0)
    counts_per_torque: float | None = Field(None, gt=0)
    stale_after_ms: float = Field(
        20.0, ge=2.0, le=500.0,
        description="the driver faults when its newest record is older than this (ms); the "
                    "runtime's own stale bound (limits.stale_periods.ft) usually acts first")


class HandpieceConfigIO(_Strict):
    interface: Literal["socketcand", "socketcan", "virtual", "pcan", "kvaser", "ixxat"]
    channel: str = Field("can0", min_length=1, max_length=64)
    host: str = Field("127.0.0.1", min_length=1, max_length=253)
    port: int = Field(29536, ge=1, le=65535)
    node_id: int = Field(1, ge=1, le=127)
    host_node_id: int = Field(DEFAULT_HOST_NODE_ID, ge=1, le=127,
                              description="DentiBot's node id on the bus (its heartbeat)")
    consumer_ms: int = Field(DEFAULT_CONSUMER_MS, ge=10, le=500,
                             description="the drive's heartbeat consumer time (ms): without "
                                         "DentiBot's heartbeat this long it stops the file")
    host_heartbeat_ms: int = Field(round(1000 * DEFAULT_HOST_HEARTBEAT_PERIOD_S), ge=1,
                                   le=166, description="DentiBot's heartbeat period (ms); at most a "
                                               "third of consumer_ms")
    feed_timeout_ms: int = Field(round(1000 * DEFAULT_FEED_TIMEOUT_S), ge=20, le=1000,
                                 description="the heartbeat is withheld when the control loop "
                                             "has not read the drive for this long (ms)")
    quick_stop_rpm_s: float = Field(DEFAULT_QUICK_STOP_FILE_RPM_S, ge=100.0, le=100_000.0,
                                    description="quick-stop deceleration at the file (rpm/s)")
    connect_timeout_s: float = Field(2.0, ge=0.1, le=30.0)


class AuxConfig(_Strict):
    host: str = Field(min_length=1, max_length=253, description="the aux I/O's address")
    port: int = Field(502, ge=1, le=65535)
    device_id: int = Field(1, ge=0, le=247)
    connect_timeout_s: float = Field(1.0, ge=0.1, le=30.0)
    watchdog_ms: int = Field(
        200, ge=50, le=1000,
        description="host watchdog armed on a map 1.1+ device (ms): host-lost is declared "
                    "after this long without the host's counter; at least 5 poll periods")


_Coord = Annotated[float, Field(ge=-1000.0, le=1000.0)]
_Angle = Annotated[float, Field(ge=-180.0, le=180.0)]
_NodeId = Annotated[int, Field(ge=1, le=127)]
_Xyz = tuple[_Coord, _Coord, _Coord]


class TrackerConfig(_Strict):
    """The patient tracking module: draw-wire encoders (CiA 406) on a CAN bus, string i
    from ``mount_anchors_mm[i]`` (frame {M}, on the handpiece mount) to
    ``tooth_anchors_mm[i]`` (frame {T}, on the tooth clamp). Six strings give the pose,
    three the position only."""

    interface: Literal["socketcand", "socketcan", "virtual", "pcan", "kvaser", "ixxat"]
    channel: str = Field("can0", min_length=1, max_length=64)
    host: str = Field("127.0.0.1", min_length=1, max_length=253)
    port: int = Field(29536, ge=1, le=65535)
    node_ids: list[_NodeId] = Field(default_factory=lambda: list(DEFAULT_NODE_IDS),
                                    min_length=3, max_length=6,
                                    description="node ids of strings 1..n")
    mount_anchors_mm: list[_Xyz] = Field(min_length=3, max_length=6,
                                         description="a_i in the mount frame {M} (mm)")
    tooth_anchors_mm: list[_Xyz] = Field(min_length=3, max_length=6,
                                         description="b_i in the tooth frame {T} (mm)")
    mount_in_flange_mm: _Xyz = Field((0.0, 0.0, 0.0),
                                     description="origin of {M} in the flange frame (mm)")
    mount_in_flange_deg: tuple[_Angle, _Angle, _Angle] = Field(
        (0.0, 0.0, 0.0), description="{M} in the flange frame, x-y-z Euler angles (deg)")
    tooth_in_mount_mm: _Xyz = Field(
        (0.0, 0.0, 90.0), description="where the clamp {T} is in {M} at set-up (mm, axes "
                                      "parallel): the first guess of the pose solve")
    resolution_mm: float = Field(DEFAULT_RESOLUTION_MM, ge=0.0001, le=1.0,
                                 description="measuring step (mm per unit)")
    drum_mm_per_rev: float = Field(DEFAULT_DRUM_MM_PER_REV, ge=1.0, le=1000.0)
    range_mm: float = Field(DEFAULT_RANGE_MM, ge=10.0, le=5000.0)
    zero_length_mm: list[Annotated[float, Field(ge=0.0, le=1000.0)]] | None = Field(
        None, min_length=3, max_length=6,
        description="string length at position value 0, per string (default 20 mm each)")
    min_length_mm: float = Field(30.0, ge=0.0, le=1000.0, description="slack minimum")
    max_length_mm: float = Field(300.0, ge=1.0, le=5000.0)
    transmission_type: int = Field(DEFAULT_TRANSMISSION_TYPE, ge=1, le=240,
                                   description="a position every n-th SYNC")
    sync_producer: bool = Field(False, description="the tracker sends SYNC itself (no "
                                                   "other master on the bus does)")
    sync_period_ms: float = Field(2.0, ge=0.5, le=100.0)
    heartbeat_ms: int = Field(100, ge=10, le=1000)
    heartbeat_timeout_ms: int = Field(350, ge=20, le=5000)
    stale_after_ms: int = Field(100, ge=5, le=1000)
    sdo_timeout_s: float = Field(0.5, ge=0.05, le=5.0)
    connect_timeout_s: float = Field(2.0, ge=0.1, le=30.0)
    vendor_id: int | None = Field(None, ge=0, le=0xFFFF_FFFF)
    product_code: int | None = Field(None, ge=0, le=0xFFFF_FFFF)

    def checks(self) -> list[tuple[tuple, str]]:
        out = []
        n = len(self.node_ids)
        if len(set(self.node_ids)) != n:
            out.append((("tracker", "node_ids"), "node ids must be distinct"))
        if n not in (3, 6):
            out.append((("tracker", "node_ids"), f"{n} strings: 6 (pose) or 3 (position)"))
        for key in ("mount_anchors_mm", "tooth_anchors_mm", "zero_length_mm"):
            v = getattr(self, key)
            if v is not None and len(v) != n:
                out.append((("tracker", key), f"{len(v)} entries for {n} strings"))
        if self.min_length_mm >= self.max_length_mm:
            out.append((("tracker", "min_length_mm"), "below max_length_mm"))
        if self.heartbeat_timeout_ms < 2 * self.heartbeat_ms:
            out.append((("tracker", "heartbeat_timeout_ms"),
                        f"at least two heartbeat periods ({2 * self.heartbeat_ms} ms)"))
        return out


class DevicesConfig(_Strict):
    """The devices of a real (or wire-simulated) set-up: every address written out, none
    assumed. The aux I/O carries the emergency stop: leaving it out needs ``estop_waiver``, a
    sentence saying why (e.g. a bench with a hardware e-stop in the arm's power)."""

    arm: ArmConfig
    ft: FTConfig
    handpiece: HandpieceConfigIO
    aux: AuxConfig | None = None
    tracker: TrackerConfig | None = None
    estop_waiver: str | None = Field(None, min_length=10, max_length=500)

    def cross_checks(self) -> list[tuple[tuple, str]]:
        out = []
        if self.aux is None and self.estop_waiver is None:
            out.append((("aux",), "the aux I/O (emergency stop, pedal) is required: configure "
                                  "it, or state why it is left out in estop_waiver"))
        h = self.handpiece
        if h.host_node_id == h.node_id:
            out.append((("handpiece", "host_node_id"),
                        f"{h.host_node_id} is the drive's own node id: choose another"))
        if 3 * h.host_heartbeat_ms > h.consumer_ms:
            out.append((("handpiece", "host_heartbeat_ms"),
                        f"{h.host_heartbeat_ms} ms: at most a third of consumer_ms "
                        f"({h.consumer_ms} ms), so that one lost beat is not a fault"))
        t = self.tracker
        if t is not None:
            out.extend(t.checks())
            same_bus = (t.interface, t.channel, t.host, t.port) == (
                h.interface, h.channel, h.host, h.port)
            taken = set(t.node_ids) & {h.node_id, h.host_node_id}
            if same_bus and taken:
                out.append((("tracker", "node_ids"),
                            f"{sorted(taken)} already used on this bus by the handpiece"))
        return out


def loopback_config(host: str = "127.0.0.1", meca_port: int = 10000, netft_port: int = 49152,
                    netft_http_port: int = 8080, modbus_port: int = 5020,
                    can_port: int = 29536, can_channel: str = "vcan0",
                    meca_monitor_port: int | None = None,
                    tracker: TrackerConfig | None = None,
                    ft_stale_after_ms: float | None = None) -> DevicesConfig:
    """The addresses ``dentibot sim serve`` listens on (by default: its default ports; the
    Meca500 monitoring port is the next one unless given; ``tracker`` as given; the F/T
    driver's own freshness bound ``ft_stale_after_ms``, the hardware default unless
    given)."""
    ft = {} if ft_stale_after_ms is None else {"stale_after_ms": ft_stale_after_ms}
    return DevicesConfig(
        arm=ArmConfig(host=host, control_port=meca_port,
                      monitor_port=meca_monitor_port or meca_port + 1),
        ft=FTConfig(host=host, port=netft_port, http_port=netft_http_port, **ft),
        handpiece=HandpieceConfigIO(interface="socketcand", host=host, port=can_port,
                                    channel=can_channel),
        aux=AuxConfig(host=host, port=modbus_port), tracker=tracker)


def devices_yaml(cfg: DevicesConfig) -> str:
    """``cfg`` as a device configuration file (what :func:`load_devices_config` reads back)."""
    import yaml

    return yaml.safe_dump(cfg.model_dump(mode="json", exclude_none=True), sort_keys=False)


def load_devices_config(path: str | Path) -> DevicesConfig:
    """Read and validate a device configuration file; raises :class:`DevicesFileError`
    (file, line, field, value, limit) before anything connects."""
    return load(path, DevicesConfig, DevicesFileError)


#: Why a paused arm is not resumed without the operator (and how they resume it).
ARM_PAUSED = ("the arm is paused (a previous run ended without parking it, or its connection "
              "watchdog expired): nothing moves until the operator resumes it, once the "
              "workspace is clear (dentibot run --resume-arm; in a session: connect "
              "resume-arm)")

#: Environment variable naming the device configuration file.
DEVICES_ENV = "DENTIBOT_DEVICES"
#: File name looked for in the working directory and in the user's configuration directory.
DEVICES_FILE_NAME = "devices.yaml"


def devices_search_path(env: Mapping[str, str], cwd: Path) -> list[tuple[Path, str]]:
    """Where a device configuration is looked for, in order, each with how it was found:
    ``$DENTIBOT_DEVICES``, ``./devices.yaml``, ``$XDG_CONFIG_HOME/dentibot/devices.yaml``
    (``~/.config`` when ``XDG_CONFIG_HOME`` is unset, as the XDG base-directory rules say)."""
    out: list[tuple[Path, str]] = []
    if env.get(DEVICES_ENV):
        out.append((Path(env[DEVICES_ENV]).expanduser(), f"${DEVICES_ENV}"))
    out.append((cwd / DEVICES_FILE_NAME, "the working directory"))
    home = env.get("HOME")
    config_home = env.get("XDG_CONFIG_HOME") or (str(Path(home) / ".config") if home else None)
    if config_home:
        out.append((Path(config_home) / "dentibot" / DEVICES_FILE_NAME,
                     "the user's configuration directory"))
    return out


def find_devices_file(requested: str | None, *, env: Mapping[str, str] | None = None,
                      cwd: Path | None = None) -> tuple[Path, str] | None:
    """The device configuration a command uses, and how it was chosen; None for the built-in
    simulator.

    ``requested`` is ``--devices``'s value: a path (used as given), ``""`` for a bare
    ``--devices`` (the first file of :func:`devices_search_path` that exists; none is an
    error naming the places looked at), or None. With None only ``$DENTIBOT_DEVICES`` is
    taken: a ``devices.yaml`` lying in a directory never sends a run to hardware unasked.
    """
    env = os.environ if env is None else env
    cwd = Path.cwd() if cwd is None else cwd
    if requested:
        return Path(requested), "--devices"
    if requested is None:
        value = env.get(DEVICES_ENV)
        return (Path(value).expanduser(), f"${DEVICES_ENV}") if value else None
    places = devices_search_path(env, cwd)
    for path, how in places:
        if path.is_file():
            return path, how
    looked = "; ".join(str(p) for p, _ in places)
    raise ConfigError("--devices", "", f"a device configuration file; none found at {looked}",
                      f"write one with 'dentibot sim serve --write-devices "
                      f"{DEVICES_FILE_NAME}', or name the file")


@dataclass
class OpenDevices:
    arm: Meca500Driver
    ft: NetFTDriver
    motor: Epos4Driver
    aux: AuxModbusDriver | None
    tracker: TrackerDriver | None = None


def tracker_driver(t: TrackerConfig) -> TrackerDriver:
    """The driver a ``tracker:`` section describes (not yet connected)."""
    return TrackerDriver(
        interface=t.interface, channel=t.channel, host=t.host, port=t.port,
        bus_kwargs={"host": t.host, "port": t.port} if t.interface == "socketcand" else None,
        node_ids=t.node_ids, resolution_mm=t.resolution_mm, drum_mm_per_rev=t.drum_mm_per_rev,
        range_mm=t.range_mm,
        zero_length_mm=(t.zero_length_mm if t.zero_length_mm is not None
                        else DEFAULT_ZERO_LENGTH_MM),
        min_length_mm=t.min_length_mm, max_length_mm=t.max_length_mm,
        transmission_type=t.transmission_type, sync_producer=t.sync_producer,
        sync_period_s=t.sync_period_ms / 1000.0, heartbeat_ms=t.heartbeat_ms,
        heartbeat_timeout_s=t.heartbeat_timeout_ms / 1000.0,
        stale_after_s=t.stale_after_ms / 1000.0, sdo_timeout_s=t.sdo_timeout_s,
        connect_timeout_s=t.connect_timeout_s, vendor_id=t.vendor_id,
        product_code=t.product_code)


@contextlib.asynccontextmanager
async def open_devices(cfg: DevicesConfig, *, home: bool = True,
                       resume_arm: bool = False) -> AsyncIterator[OpenDevices]:
    """Connect and start every device; close them all (in reverse) on exit.

    An arm found paused (a run that ended without parking it, an expired connection
    watchdog) is an error unless ``resume_arm``: resuming is the operator's decision, taken
    once the workspace is clear (:meth:`Meca500Driver.resume`, which refuses an arm in
    error).

    What the process holds before the devices start is frozen out of the garbage collector's
    sight first (``gc.freeze``; unfrozen on exit): from the aux I/O's watchdog (200 ms) and
    the drive's heartbeat consumer (30 ms) on, the devices watch the host, and a full
    collection over a start-up heap (the libraries a command imports) can pause the event
    loop longer than that, which they rightly take for a dead host. Nothing is collected
    first: a collection of a test process's heap takes 60-100 ms, twice that on a busy
    machine, and one after the aux I/O armed its watchdog let it expire (the STO open, the
    drive's enable refused); one before the connection could outlast what is left of a
    previous connection's watchdog. Garbage frozen with the rest is freed after the exit."""
    a, f, h, x = cfg.arm, cfg.ft, cfg.handpiece, cfg.aux
    async with contextlib.AsyncExitStack() as stack:
        gc.freeze()
        stack.callback(gc.unfreeze)
        ft = NetFTDriver(f.host, f.port, f.http_port, counts_per_force=f.counts_per_force,
                         counts_per_torque=f.counts_per_torque,
                         stale_after_s=f.stale_after_ms / 1000.0)
        await ft.connect()
        stack.push_async_callback(ft.close)
        aux = None
        if x is not None:
            aux = AuxModbusDriver(x.host, x.port, x.device_id, watchdog_ms=x.watchdog_ms,
                                  connect_timeout_s=x.connect_timeout_s)
            await aux.connect()
            stack.push_async_callback(aux.close)
        bus_kwargs = {"host": h.host, "port": h.port} if h.interface == "socketcand" else {}
        motor = Epos4Driver(interface=h.interface, channel=h.channel, host=h.host, port=h.port,
                            node_id=h.node_id, bus_kwargs=bus_kwargs or None,
                            host_node_id=h.host_node_id, consumer_ms=h.consumer_ms,
                            host_heartbeat_period_s=h.host_heartbeat_ms / 1000.0,
                            feed_timeout_s=h.feed_timeout_ms / 1000.0,
                            quick_stop_file_rpm_s=h.quick_stop_rpm_s,
                            connect_timeout_s=h.connect_timeout_s)
        await motor.connect()
        stack.push_async_callback(motor.close)
        await motor.enable()
        tracker = None
        if cfg.tracker is not None:
            tracker = tracker_driver(cfg.tracker)
            await tracker.connect()
            stack.push_async_callback(tracker.close)
        arm = Meca500Driver(a.host, a.control_port, a.monitor_port,
                            vel_timeout_s=a.vel_timeout_s,
                            connection_watchdog_s=a.connection_watchdog_s)
        await arm.connect()
        stack.push_async_callback(arm.close)
        if arm.paused and arm.activated:
            if not resume_arm:
                raise DeviceFault("meca500", ARM_PAUSED)
            await arm.resume()
        if home:
            await arm.activate()
            await arm.home()
        yield OpenDevices(arm, ft, motor, aux, tracker)
