"""``dentibot session``: the interactive terminal session (connect, calibrate, drag, align,
drill, pause, reverse, retract ... step by step), on the built-in simulator in real time by
default, or on devices (``--devices``: wire simulators of ``dentibot sim serve`` or hardware).

Whatever ends the screen (``quit``, Ctrl+Q, Ctrl+C, a crash of the UI), the session stops
safely before the process exits: file withdrawn if it was in the canal, arm and file stopped,
recording closed, devices closed.
"""

from __future__ import annotations

import argparse
import asyncio
import sys

from dentibot.cli.common import user_errors
from dentibot.cli.devices_option import add_devices_options, devices_from_args
from dentibot.protocol.loader import load_protocol


def cmd_session(args: argparse.Namespace) -> int:
    return user_errors(_session)(args)


def _session(args: argparse.Namespace) -> int:
    from dentibot.session.app import SessionApp
    from dentibot.session.controller import SessionController, SessionOptions

    protocol = load_protocol(args.protocol) if args.protocol else None   # bad input: exit 2
    devices = devices_from_args(args, "session")
    ctl = SessionController(SessionOptions(protocol=protocol, devices=devices, clock=args.clock,
                                           calibrated=args.calibrated))
    app = SessionApp(ctl, refresh_hz=args.refresh_hz, startup=tuple(args.startup))

    async def main() -> None:
        try:
            await app.run_async()
        finally:
            if not ctl.closed:
                print("dentibot session: stopping safely ...", file=sys.stderr, flush=True)
                reply = await ctl.shutdown()
                print(reply.text, file=sys.stderr)

    asyncio.run(main())
    for line in app.transcript[-3:]:
        print(line)
    return 0


def add_parser(sub) -> None:
    s = sub.add_parser("session", help="interactive session: connect, calibrate, drag, align, "
                       "drill, pause, retract ... step by step")
    add_devices_options(s)
    s.add_argument("--protocol", help="protocol whose phantom, tool, limits and steps the "
                   "session uses ('step N' runs its step N); default: the schema's defaults")
    s.add_argument("--clock", choices=["realtime", "lockstep"], default="realtime",
                   help="built-in simulator: real time (default) or lock-step as fast as "
                   "possible")
    s.add_argument("--calibrated", action="store_true",
                   help="built-in simulator: the load is known (skip 'calibrate load')")
    s.add_argument("-c", "--exec", dest="startup", action="append", default=[],
                   metavar="COMMAND",
                   help="run this command at start (repeatable, in order), e.g. -c connect")
    s.add_argument("--refresh-hz", type=float, default=5.0,
                   help="panel refresh rate (Hz, default 5; each redraw takes about 1.4 ms "
                   "of the control task's event loop)")
    s.set_defaults(func=cmd_session)
