"""``dentibot recover RUN.mcap [--out OUT]``: rewrite a recording cut short (crash, kill, power
loss) into a finished MCAP file, and say what was saved.

Exit status: 0 recovered, or nothing to recover (the recording is intact); 2 bad input (missing
file, not an MCAP file, output exists without ``--force``).
"""

from __future__ import annotations

import argparse
import json

from dentibot.cli.common import user_errors


@user_errors
def cmd_recover(args: argparse.Namespace) -> int:
    from dentibot.telemetry.recover import recover_recording

    r = recover_recording(args.recording, args.out, force=args.force, rewrite=args.rewrite)
    if args.json:
        print(json.dumps(r.to_dict(), indent=2))
        return 0
    if r.intact and r.out is None:
        extra = ""
        if r.recovered_before is not None:
            extra = (f"; it was itself recovered from {r.recovered_before.get('source', '?')} "
                     "and stays incomplete")
        elif not r.has_end:
            extra = "; it has no /run/end"
        print(f"{r.source}: intact (finished by its recorder, {r.ticks} ticks): nothing to "
              f"recover{extra}. --rewrite writes a copy anyway.")
        return 0
    if r.intact:
        print(f"{r.source}: intact; copied {r.messages} messages ({r.ticks} ticks) to {r.out}")
        return 0
    print(f"recovered {_ticks_text(r)}, {r.events} events, {r.messages - len(r.skipped)} "
          f"messages in all, from {r.source} into {r.out}")
    end = ("it has a /run/end but its file was not finished" if r.has_end else
           "no /run/end: the run did not close its recording, what came after is lost")
    if r.journal:
        print(f"journal {r.journal}")
    print(f"the recording is INCOMPLETE: {end}; {r.stopped}")
    for problem in r.skipped[:5]:
        print(f"skipped: {problem}")
    return 0


def _ticks_text(r) -> str:
    """``N ticks (S s of procedure at R Hz; ticks A-B)``: what a recovery saved."""
    parts = []
    if r.seconds is not None:
        parts.append(f"{r.seconds:.3f} s of procedure at {r.rate_hz:g} Hz")
    if r.first_tick is not None:
        span = f"ticks {r.first_tick}-{r.last_tick}"
        if r.missing_ticks:
            span += f", {r.missing_ticks} missing between them"
        parts.append(span)
    return f"{r.ticks} ticks" + (f" ({'; '.join(parts)})" if parts else "")


def add_parser(sub) -> None:
    recover = sub.add_parser("recover", help="rewrite a recording cut short into a finished "
                             "MCAP file")
    recover.add_argument("recording", help="recording cut short, e.g. RUN.mcap")
    recover.add_argument("--out", help="file to write (default: RUN.recovered.mcap beside it)")
    recover.add_argument("--force", action="store_true", help="replace --out if it exists")
    recover.add_argument("--rewrite", action="store_true",
                         help="write a copy even when the recording is intact")
    recover.add_argument("--json", action="store_true",
                         help="print what was found and written as one JSON object")
    recover.set_defaults(func=cmd_recover)
