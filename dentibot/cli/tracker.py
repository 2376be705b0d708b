"""``dentibot tracker calibrate``: the patient tracker's anchors identified on the set-up
(:mod:`dentibot.app.tracker_calibration`; docs/patient-tracker.md, "Anchor calibration").

The arm turns the handpiece about the file tip and moves it away and sideways through
fourteen poses while the clamp is held still; the report (per string the anchors' change from
the device file's, its standard deviation, the rms residual, the condition number, pass or
fail) and the anchors in the device file's format are printed. ``--write`` puts them into the
device file (only when every string passes): the two anchor lists of its ``tracker:`` section
are replaced, the rest of the file (comments included) is kept, and the file is read back and
validated before it replaces the old one. Exit status: 0 pass, 3 fail, 2 bad input.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import sys
import tempfile
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from dentibot.app.procedure import Procedure
from dentibot.app.runner import runtime_config, world_config
from dentibot.app.tracker_calibration import TrackerCalibrationParams, calibrate_tracker
from dentibot.app.tracking import sim_tracking, tracked_config
from dentibot.cli.common import user_errors
from dentibot.cli.devices_option import add_devices_options
from dentibot.errors import ConfigError
from dentibot.io.devices import find_devices_file, load_devices_config, open_devices
from dentibot.protocol.schema import Protocol

_ANCHOR_KEYS = ("mount_anchors_mm", "tooth_anchors_mm")


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip(" "))


def replace_anchors(text: str, mount_mm, tooth_mm) -> str:
    """``text`` (a device file) with the ``tracker:`` section's two anchor lists replaced by
    ``mount_mm`` and ``tooth_mm`` (n x 3, mm, written with 3 decimals as block lists); every
    other line is kept. Raises ConfigError when the section or a key is not found."""
    lines = text.splitlines(keepends=True)
    start = next((i for i, ln in enumerate(lines) if re.match(r"tracker:\s*(#.*)?$", ln)), None)
    if start is None:
        raise ConfigError("tracker", None, "a tracker: section in the device file")
    end = next((i for i in range(start + 1, len(lines))
                if lines[i].strip() and not lines[i].lstrip().startswith("#")
                and _indent(lines[i]) == 0), len(lines))
    values = {"mount_anchors_mm": mount_mm, "tooth_anchors_mm": tooth_mm}
    for key in _ANCHOR_KEYS:
        at = next((i for i in range(start + 1, end)
                   if re.match(rf"\s+{key}:", lines[i])), None)
        if at is None:
            raise ConfigError(f"tracker.{key}", None, "the key in the device file's tracker "
                              "section")
        ind = _indent(lines[at])
        rest = lines[at].split(":", 1)[1]
        stop = at + 1
        depth = rest.split("#", 1)[0].count("[") - rest.split("#", 1)[0].count("]")
        while stop < end:                      # a flow list over lines, or a block list
            ln = lines[stop]
            s = ln.strip()
            if depth > 0:
                depth += s.count("[") - s.count("]")
            elif not s or s.startswith("#") or _indent(ln) < ind or (
                    _indent(ln) == ind and not s.startswith("- ")):
                break
            stop += 1
        comment = rest.split("#", 1)[1].strip() if "#" in rest else ""
        head = f"{' ' * ind}{key}:" + (f"  # {comment}" if comment else "") + "\n"
        body = [f"{' ' * (ind + 2)}- [{', '.join(f'{float(x):.3f}' for x in v)}]\n"
                for v in np.asarray(values[key], float)]
        lines[at:stop] = [head, *body]
        end += 1 + len(body) - (stop - at)
    return "".join(lines)


def write_anchors(path: Path, mount_mm, tooth_mm) -> None:
    """Replace the device file's anchors (:func:`replace_anchors`); the new file is read back
    and validated, and must give these anchors, before it replaces the old one."""
    text = replace_anchors(path.read_text(encoding="utf-8"), mount_mm, tooth_mm)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".yaml")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        t = load_devices_config(tmp).tracker
        if t is None or not (np.allclose(t.mount_anchors_mm, mount_mm, atol=6e-4)
                             and np.allclose(t.tooth_anchors_mm, tooth_mm, atol=6e-4)):
            raise ConfigError("tracker anchors", str(path), "a device file whose anchors can "
                              "be replaced in place (write them by hand from the listing)")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _protocol(args: argparse.Namespace) -> Protocol:
    try:
        return Protocol.model_validate({
            "name": "tracker-calibration", "patient": {"tracker": True},
            "tool": {"tip_mm": tuple(args.tip_mm)},
            "steps": [{"calibrate_tracker": {"rotation_deg": args.rotation_deg,
                                             "translation_mm": args.translation_mm}}]})
    except ValidationError as exc:
        e = exc.errors()[0]
        raise ConfigError(".".join(map(str, e["loc"])), e.get("input"), e["msg"]) from None


async def _calibrate(p: Protocol, devices, params: TrackerCalibrationParams):
    cfg = runtime_config(p)
    if devices is None:
        async with Procedure.simulated(world_config(p), cfg, **sim_tracking(p)) as proc:
            return await calibrate_tracker(proc, params=params)
    cfg = tracked_config(p, cfg, devices)          # ConfigError without a tracker section
    async with open_devices(devices) as d:       # an arm found paused is refused
        async with Procedure.over(d, cfg) as proc:
            return await calibrate_tracker(proc, params=params)


def cmd_calibrate(args: argparse.Namespace) -> int:
    return user_errors(_run)(args)


def _run(args: argparse.Namespace) -> int:
    p = _protocol(args)
    spec = p.steps[0].spec
    params = TrackerCalibrationParams(rotation_deg=spec.rotation_deg,
                                      translation_mm=spec.translation_mm)
    found = None if args.sim else find_devices_file(args.devices)
    path = None if found is None else found[0]
    if args.write and path is None:
        raise ConfigError("--write", True, "a device file (--devices FILE) to write into")
    devices = None if path is None else load_devices_config(path)
    if devices is not None and not args.yes:
        answer = input("The file is out of the canal and the patient's clamp is held still; "
                       "the arm will turn the handpiece about the file tip. Go on? [y/N] ")
        if answer.strip().lower() not in ("y", "yes"):
            print("dentibot tracker: nothing moved", file=sys.stderr)
            return 2
    result = asyncio.run(_calibrate(p, devices, params))
    print(result.report(), end="")
    if not result.ok:
        print("dentibot tracker: the calibration failed its bounds: the device file is "
              "unchanged", file=sys.stderr)
        return 3
    if args.write:
        g = result.geometry
        write_anchors(path, g.mount_mm, g.tooth_mm)
        print(f"anchors written to {path}")
    return 0


def add_parser(sub) -> None:
    tracker = sub.add_parser("tracker", help="the patient tracker")
    tsub = tracker.add_subparsers(dest="tracker_command", required=True)
    cal = tsub.add_parser("calibrate", help="identify the tracker's anchors on the set-up "
                                            "(the arm moves the handpiece; the file out of "
                                            "the canal, the clamp held still)")
    add_devices_options(cal)
    cal.add_argument("--write", action="store_true",
                     help="write the identified anchors into the device file (only when "
                          "every string passes)")
    cal.add_argument("--tip-mm", nargs=3, type=float, default=(0.0, 0.0, 90.0),
                     metavar=("X", "Y", "Z"),
                     help="the file tip in the flange frame (mm), the centre of the turns "
                          "(default 0 0 90)")
    cal.add_argument("--rotation-deg", type=float, default=10.0,
                     help="turn about each of two axes at the file tip (deg, 2..15)")
    cal.add_argument("--translation-mm", type=float, default=5.0,
                     help="move away from the tooth and sideways (mm, 1..10)")
    cal.add_argument("--yes", action="store_true",
                     help="do not ask: the file is out of the canal and the clamp held still")
    cal.set_defaults(func=cmd_calibrate)
