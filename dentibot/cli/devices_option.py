"""``--devices [FILE]`` and ``--sim``, shared by the commands that drive devices.

``--devices FILE`` names the configuration; a bare ``--devices`` looks for one
(``$DENTIBOT_DEVICES``, ``./devices.yaml``, the user's configuration directory); without
either, ``$DENTIBOT_DEVICES`` when set, else the built-in simulator. ``--sim`` takes the
built-in simulator whatever the environment says. The file used, and how it was found, is
said on stderr before anything connects.
"""

from __future__ import annotations

import argparse
import sys

from dentibot.io.devices import DEVICES_ENV, DevicesConfig, find_devices_file, load_devices_config


def add_devices_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--devices", nargs="?", const="", default=None, metavar="FILE",
                       help="device configuration YAML (wire simulators of 'dentibot sim serve' "
                            f"or hardware); bare: ${DEVICES_ENV}, ./devices.yaml or "
                            "~/.config/dentibot/devices.yaml, the first that exists; default: "
                            f"${DEVICES_ENV} when set, else the built-in simulator")
    group.add_argument("--sim", action="store_true",
                       help=f"the built-in simulator, even when ${DEVICES_ENV} is set")


def devices_from_args(args: argparse.Namespace, command: str) -> DevicesConfig | None:
    """The validated configuration ``args`` ask for (None: the built-in simulator); raises
    ConfigError / DevicesFileError before anything connects."""
    if args.sim:
        return None
    found = find_devices_file(args.devices)
    if found is None:
        return None
    path, how = found
    if how != "--devices":
        print(f"dentibot {command}: devices from {path} ({how})", file=sys.stderr)
    return load_devices_config(path)
