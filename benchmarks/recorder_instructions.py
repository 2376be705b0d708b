"""The recorder's writer counted in instructions, not seconds: what it costs per tick to write
the main job's drilling blocks, repeatable on a shared machine.

    .venv/bin/python benchmarks/recorder_instructions.py [--blocks 40] [--json FILE]

Timings of the recorder's process swing by 1.5x from one minute to the next here, more than
most changes to the writer move them. valgrind's callgrind counts the instructions a process
runs, whatever else the machine does. The benchmark:

1. runs the main job (``protocols/root-canal.yaml``) on the built-in simulator as ``dentibot
   run`` does and keeps the drill step's blocks of compiled ticks, as the runner hands them
   to its readers (:class:`~dentibot.telemetry.blocks.TickBlock`, in their wire form);
2. writes ``--blocks`` of them (from the 21st on, the drilling well under way), whole (up to
   256 ticks) as the recorder's process receives them through its journal, into a
   :class:`~dentibot.telemetry.recorder.McapRecorder` that writes in the caller's thread with
   the recorder process's budget (:data:`~dentibot.telemetry.recorder_process.JOURNAL_S` at
   500 Hz) and the run's 3D view, under callgrind, twice: once stopping
   after a warm-up of 40 parts (imports, compiled kernels loaded, first chunks), once going
   on through all of them. The difference, over the ticks after the warm-up, is the writer's
   instructions per tick;
3. splits that difference by where it runs: the interpreter, zstd, CRC, memory copies, numpy,
   the rest.

Needs ``valgrind`` on the PATH (Debian's package). A few minutes. The compiled kernels run
as built for a generic x86-64 CPU (``NUMBA_CPU_NAME=generic``), the same in both runs.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

import structlog

sys.path.insert(0, str(Path(__file__).resolve().parent))

import real_tick

from dentibot.app.runner import ProtocolRunner
from dentibot.telemetry.blocks import TickBlock
from dentibot.telemetry.recorder_process import JOURNAL_S

WARM_PARTS = 10               # parts written before the counted ones (in both runs)
FIRST_BLOCK = 20              # the drill step's blocks from here on (its start skipped)
PART_TICKS = 256              # a block as the recorder's process receives it (a whole call's)
#: where a C function's instructions are counted: the first pattern its name matches
AREAS = (("interpreter", (r"ceval\.c|dictobject|obmalloc|object\.c|typeobject|longobject|"
                          r"listobject|tupleobject|frame\.c|unicodeobject|abstract\.c|call\.c")),
         ("zstd", r"zstd"), ("crc", r"crc32"), ("memory copies", r"memmove|memcpy|memset"),
         ("numpy", r"numpy|PyArray|ufunc|npy"))


def capture_blocks(path: Path) -> int:
    """Run the main job and write its drill step's blocks (wire form, length-prefixed) to
    ``path``; the number of blocks."""
    blocks: list[bytes] = []
    keep = ProtocolRunner._block_read

    def read(self, block, recorder=None):
        if block.step.endswith(real_tick.DRILL):
            blocks.append(b"".join(bytes(b) for b in block.packed()))
        return keep(self, block, recorder)

    ProtocolRunner._block_read = read
    try:
        with tempfile.TemporaryDirectory() as d:
            runner = ProtocolRunner(real_tick.main_job(), recording=Path(d) / "run.mcap",
                                    overwrite=True)
            asyncio.run(runner.run())
    finally:
        ProtocolRunner._block_read = keep
    with open(path, "wb") as f:
        f.writelines(len(b).to_bytes(8, "little") + b for b in blocks)
    return len(blocks)


def _parts(path: Path, blocks: int) -> list[TickBlock]:
    data, parts, at, k = path.read_bytes(), [], 0, 0
    while at < len(data):
        n = int.from_bytes(data[at:at + 8], "little")
        if FIRST_BLOCK <= k < FIRST_BLOCK + blocks:
            b = TickBlock.unpack(data[at + 8:at + 8 + n])
            parts += [b.part(s, min(len(b), s + PART_TICKS)) for s in range(0, len(b),
                                                                               PART_TICKS)]
        at, k = at + 8 + n, k + 1
    return parts


def write_parts(path: Path, blocks: int, counted: bool, out: Path) -> int:
    """The writer's side (run under callgrind): the warm-up parts, then (``counted``) the
    rest; the ticks after the warm-up."""
    from dentibot.telemetry.foxglove import FoxgloveView
    from dentibot.telemetry.recorder import McapRecorder
    parts = _parts(path, blocks)
    todo = parts if counted else parts[:WARM_PARTS]
    rec = McapRecorder(out, {"rate_hz": 500.0}, writer_thread=False, validate=False,
                       view=FoxgloveView(file_length_mm=25.0), overwrite=True,
                       max_queue=round(JOURNAL_S * 500.0))
    for p in todo:
        if rec.rows_queued - rec._settled + len(p) > rec.budget:   # as the recorder's
            rec._wait_for_room(None, len(p))      # process waits for room before a block
        rec.record_block(p)
    rec.close("ok")
    return sum(len(p) for p in parts[WARM_PARTS:])


#: the compiled kernels for a generic x86-64, in every run: numba's cache is kept per CPU, and
#: valgrind's looks like another one (its kernels would be compiled under valgrind, slowly,
#: and in one of the two runs only)
_ENV = {**os.environ, "NUMBA_CPU_NAME": "generic"}


def _callgrind(args: list[str], out: Path) -> Counter:
    """Instructions by C function of ``python args`` under callgrind."""
    subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}",
                    sys.executable, *args], check=True, capture_output=True, env=_ENV)
    text = subprocess.run(["callgrind_annotate", "--threshold=100", str(out)], check=True,
                          capture_output=True, text=True).stdout
    by_fn: Counter = Counter()
    for line in text.splitlines():
        m = re.match(r"\s*([\d,]+) \([^)]*\)\s+(.*)", line)
        if m and "PROGRAM TOTALS" not in m.group(2):
            by_fn[m.group(2).split(" [")[0]] += int(m.group(1).replace(",", ""))
    return by_fn


def measure(blocks: int = 40) -> dict:
    """Instructions per tick of the writer on ``blocks`` drilling blocks, by area."""
    if shutil.which("valgrind") is None or shutil.which("callgrind_annotate") is None:
        raise RuntimeError("valgrind (callgrind) is not installed")
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        captured = capture_blocks(d / "blocks.bin")
        if captured < FIRST_BLOCK + blocks:
            raise RuntimeError(f"the drill step gave {captured} blocks, "
                               f"{FIRST_BLOCK + blocks} needed")
        me = str(Path(__file__).resolve())
        args = [me, "--replay", str(d / "blocks.bin"), "--blocks", str(blocks),
                "--out", str(d / "replay.mcap")]
        subprocess.run([sys.executable, *args, "--counted"], check=True, capture_output=True,
                       env=_ENV)                 # the kernels compiled and cached, natively
        warm = _callgrind(args, d / "warm.out")
        full = _callgrind([*args, "--counted"], d / "full.out")
        ticks = int(subprocess.run([sys.executable, *args, "--counted", "--ticks"], check=True,
                                   capture_output=True, text=True).stdout.split()[-1])
    delta = {fn: full[fn] - warm.get(fn, 0) for fn in full}
    areas: Counter = Counter()
    for fn, n in delta.items():
        area = next((name for name, pattern in AREAS if re.search(pattern, fn)), "other")
        areas[area] += n
    total = sum(delta.values())
    return {"blocks": blocks, "ticks": ticks, "instructions_per_tick": total / ticks,
            "by_area_per_tick": {a: n / ticks for a, n in areas.most_common()}}


def print_report(r: dict) -> None:
    print(f"recorder writer, {r['ticks']} drilling ticks ({r['blocks']} blocks), callgrind:")
    print(f"  {r['instructions_per_tick'] / 1e3:8.1f} k instructions per tick")
    for area, n in r["by_area_per_tick"].items():
        print(f"    {area:<14}{n / 1e3:8.1f} k")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blocks", type=int, default=40)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--replay", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--counted", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--ticks", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))
    if args.replay is not None:                    # the writer's side, under callgrind
        if args.ticks:
            print(sum(len(p) for p in _parts(args.replay, args.blocks)[WARM_PARTS:]))
            return
        write_parts(args.replay, args.blocks, args.counted, args.out)
        return
    r = measure(args.blocks)
    print_report(r)
    if args.json is not None:
        args.json.write_text(json.dumps(r, indent=2))


if __name__ == "__main__":
    main()
