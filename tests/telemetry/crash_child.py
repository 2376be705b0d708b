"""A process that records and is killed: the child of the crash-safety tests.

    python crash_child.py rows OUT.mcap     # realistic rows, handed over as fast as possible
    python crash_child.py main OUT.mcap     # the main job (protocols/root-canal.yaml) on the
                                            # built-in simulator, lock-step time

After each row has been handed to the recorder (``record()`` returned), the child writes the
row's tick number and a newline to its standard output with one unbuffered ``os.write``
(logs go to the standard error; the main job first says ``p<pid>`` of its recorder process): the
parent's count of what was handed over is independent of the recorder's own counters and
survives the child's SIGKILL (what was written to the pipe is in the pipe).
"""

from __future__ import annotations

import asyncio
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).resolve().parent))


# The reports own the original standard output; everything else printed (logs) goes to the
# standard error, so the parent reads nothing but tick numbers.
_REPORT_FD = os.dup(1)
os.dup2(2, 1)


def _report(tick: int) -> None:
    os.write(_REPORT_FD, b"%d\n" % tick)


def rows(out: str) -> None:
    from telemetry_helpers import real_row

    from dentibot.telemetry import McapRecorder

    rec = McapRecorder(out, {"protocol": "crash-test", "seed": 1, "rate_hz": 500.0,
                             "devices": {"arm": "sim"}}, validate=False)
    i = 0
    while True:                              # until killed
        rec.record(real_row(i))
        _report(i)
        i += 1


def main_job(out: str) -> None:
    from dentibot.app.runner import ProtocolRunner
    from dentibot.protocol.loader import load_protocol

    class Reporting(ProtocolRunner):
        """The CLI's runner, reporting each row after handing it over (the drilling ticks'
        rows in blocks, after the compiled call that sent them)."""

        said = False

        def _say_pid(self) -> None:           # the recorder process's id, once: "p<pid>"
            if not self.said:
                self.said = True
                os.write(_REPORT_FD, b"p%d\n" % self.recorder.pid)

        def _row(self, row: dict) -> None:
            super()._row(row)
            self._say_pid()
            _report(row["tick"])

        def _block_read(self, block, recorder=None) -> None:
            # every block of rows: recorded here (``recorder``), or already sent to the
            # recorder by the compiled ticks that computed them
            super()._block_read(block, recorder)
            self._say_pid()
            for k in block.ticks:
                _report(k)

    runner = Reporting(load_protocol(ROOT / "protocols" / "root-canal.yaml"), recording=out)
    asyncio.run(runner.run())


if __name__ == "__main__":
    {"rows": rows, "main": main_job}[sys.argv[1]](sys.argv[2])
