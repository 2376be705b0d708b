"""``dentibot sim serve``: a virtual DentiBot on loopback, over the real wire protocols.

Point the drivers (``dentibot run --devices``), the vendors' own clients, or a second process
at it. Ctrl-C stops it. Binds 127.0.0.1 unless ``--host`` says otherwise.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
from pathlib import Path

from dentibot.app.runner import served_world
from dentibot.cli.common import user_errors
from dentibot.io.devices import devices_yaml
from dentibot.protocol.schema import DEFAULT_WORLD, WORLDS
from dentibot.runtime.clock import (
    SIMULATOR_FIFO_PRIORITY,
    check_cpus,
    pinned,
    raised_priority,
)
from dentibot.sim.serve import ServePorts, VirtualDentiBot


async def _serve(args: argparse.Namespace) -> None:
    ports = ServePorts(host=args.host, meca_port=args.meca_port, netft_port=args.netft_port,
                       netft_http_port=args.netft_http_port, modbus_port=args.modbus_port,
                       can_port=args.can_port, node_id=args.node_id,
                       can_channel=args.can_channel, can_interface=args.can_interface)
    async with VirtualDentiBot(served_world(args.world, args.seed, args.motion), ports) as bot:
        # Everything built so far leaves the collector's view: a full collection over it took
        # 35-85 ms under load, long enough for the F/T stream to look stale to a driver.
        gc.freeze()
        p = bot.ports
        print(f"virtual DentiBot on {p['host']}: Meca500 tcp/{p['meca_port']} (monitoring "
              f"tcp/{p['meca_monitor_port']}), Net F/T udp/{p['netft_port']} (http "
              f"tcp/{p['netft_http_port']}), Modbus tcp/{p['modbus_port']}, EPOS4 node "
              f"{args.node_id} via socketcand tcp/{p['can_port']} channel {p['can_channel']}"
              + (f" and {args.can_interface} {args.can_channel}" if args.can_interface else ""),
              flush=True)
        if args.write_devices:
            Path(args.write_devices).write_text(devices_yaml(bot.devices_config()),
                                                encoding="utf-8")
            print(f"device configuration for these ports: {args.write_devices}", flush=True)
        if args.duration is not None:
            await asyncio.sleep(args.duration)
        else:
            await asyncio.Event().wait()


@user_errors
def cmd_serve(args: argparse.Namespace) -> int:
    # A simulated device keeps its deadlines as a real one does: ahead of ordinary jobs. Its
    # loop sleeps between steps (half a period), so it may run at SCHED_FIFO where permitted
    # (else at a raised nice value); the threads it starts (the CAN bus's receivers) inherit
    # the policy, so none of them is preempted by an ordinary job while it holds the
    # interpreter lock. Measured: the F/T stream went 20.3 ms stale at nice -10 under one
    # CPU-bound job beside the control loop.
    cpus = check_cpus("--cpus", args.cpus)
    with contextlib.suppress(KeyboardInterrupt), pinned(cpus), \
            raised_priority(fifo_priority=SIMULATOR_FIFO_PRIORITY, threads_inherit=True):
        asyncio.run(_serve(args))
    return 0


def add_parser(sub) -> None:
    sim = sub.add_parser("sim", help="simulators")
    simsub = sim.add_subparsers(dest="sim_command", required=True)
    serve = simsub.add_parser("serve", help="serve a virtual DentiBot over the wire protocols",
                              formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    serve.add_argument("--host", default="127.0.0.1", help="address to bind (default loopback)")
    serve.add_argument("--meca-port", type=int, default=10000,
                       help="Meca500 control port; monitoring on the next port")
    serve.add_argument("--netft-port", type=int, default=49152, help="Net F/T RDT UDP port")
    serve.add_argument("--netft-http-port", type=int, default=8080,
                       help="Net F/T calibration page (HTTP) port")
    serve.add_argument("--modbus-port", type=int, default=5020, help="aux I/O Modbus TCP port")
    serve.add_argument("--can-port", type=int, default=29536, help="socketcand TCP port")
    serve.add_argument("--cpus", type=int, nargs="+", default=None,
                       help="keep the simulators to these CPUs (e.g. other ones than the "
                            "control loop's control.cpus)")
    serve.add_argument("--can-channel", default="vcan0",
                       help="CAN channel: the socketcand channel name and the --can-interface "
                            "channel")
    serve.add_argument("--can-interface", metavar="INTERFACE",
                       help="also attach the EPOS4 node to this python-can interface on "
                            "--can-channel (e.g. socketcan for a kernel vcan)")
    serve.add_argument("--node-id", type=int, default=1, help="EPOS4 CANopen node id")
    serve.add_argument("--seed", type=int, default=0, help="simulated world seed")
    serve.add_argument("--motion", default="static", choices=["static", "square", "head"],
                       help="patient / phantom motion")
    serve.add_argument("--world", default=DEFAULT_WORLD, choices=sorted(WORLDS),
                       help="the simulated physics, as a protocol's world: bench (the arm and "
                            "the canal's drag fitted to the thesis bench's recordings) or "
                            "thesis (the ideal arm, no drag)")
    serve.add_argument("--duration", type=float, help="stop after this many seconds")
    serve.add_argument("--write-devices", metavar="FILE",
                       help="write the device configuration for the served ports (the file "
                            "'dentibot run --devices' and 'dentibot session --devices' read)")
    serve.set_defaults(func=cmd_serve)
