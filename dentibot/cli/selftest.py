"""``dentibot selftest faults``: the fault catalogue, each injected while drilling.

Prints a table (fault, detection time, how long the file turned after it, reaction, final
state, samples lost) or, with ``--json``, a list of objects with ``fault``, ``detected_ms``,
``file_stopped_ms``, ``final_state``, ``samples_lost`` (and more). ``--wire`` adds the faults injected on the wire simulators (real
drivers, real time). Exit status 1 if any fault did not end safely in time with every sample.
"""

from __future__ import annotations

import argparse
import asyncio
import json

from rich.console import Console
from rich.table import Table

from dentibot.app.selftest import WIRE_FAULTS, run_catalogue, run_wire_fault


async def _all(args) -> list:
    results = await run_catalogue(seed=args.seed)
    if args.wire:
        results += [await run_wire_fault(f, seed=args.seed) for f in WIRE_FAULTS]
    return results


def cmd_faults(args: argparse.Namespace) -> int:
    results = asyncio.run(_all(args))
    if args.json:
        print(json.dumps([r.to_dict() for r in results], indent=2))
    else:
        t = Table(title="DentiBot fault catalogue")
        for col in ("fault", "detected (ms)", "file stopped (ms)", "reaction", "final state",
                    "samples lost", "ok"):
            t.add_column(col)
        for r in results:
            t.add_row(r.fault, "-" if r.detected_ms is None else f"{r.detected_ms:.0f}",
                      "-" if r.file_stopped_ms is None else f"{r.file_stopped_ms:.0f}",
                      r.reaction, r.final_state, str(r.samples_lost), "yes" if r.ok else "NO")
        console = Console()
        console.print(t)
        for r in results:
            if r.cause:
                console.print(f"{r.fault}: {r.cause.split('; ')[0]}", highlight=False)
    return 0 if all(r.ok for r in results) else 1


def add_parser(sub) -> None:
    st = sub.add_parser("selftest", help="self tests of the safety functions")
    stsub = st.add_subparsers(dest="selftest_command", required=True)
    f = stsub.add_parser("faults", help="inject every fault of the catalogue while drilling")
    f.add_argument("--json", action="store_true", help="JSON list instead of a table")
    f.add_argument("--wire", action="store_true",
                   help="also inject faults on the wire simulators (real time, ~5 s)")
    f.add_argument("--seed", type=int, default=1)
    f.set_defaults(func=cmd_faults)
