"""``dentibot session`` as a program: its arguments, bad input, and the real program in a real
terminal (tmux send-keys / capture-pane) on the built-in simulator in real time."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import pytest

from dentibot.cli import build_parser, main


def test_arguments():
    args = build_parser().parse_args(
        ["session", "--clock", "lockstep", "--calibrated", "-c", "connect", "-c", "align"])
    assert args.command == "session" and args.clock == "lockstep" and args.calibrated
    assert args.startup == ["connect", "align"] and args.devices is None


def test_bad_protocol_is_refused_before_anything_starts(tmp_path, capsys):
    bad = tmp_path / "p.yaml"
    bad.write_text("name: x\nsteps:\n  - drill: {tau_d_mnm: 99}\n")
    assert main(["session", "--protocol", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "steps.0.drill.tau_d_mnm" in err and "not below the torque limit" in err


class Tmux:
    """The real program in a detached tmux window on a private server."""

    def __init__(self, name: str) -> None:
        self.base = ["tmux", "-L", name]

    def __call__(self, *args: str) -> str:
        return subprocess.run([*self.base, *args], check=True, capture_output=True,
                              text=True, timeout=10).stdout

    def screen(self) -> str:
        return self("capture-pane", "-p", "-t", "s")

    def wait_for(self, text: str, timeout_s: float = 30.0) -> str:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            screen = self.screen()
            if text in screen:
                return screen
            time.sleep(0.1)
        raise AssertionError(f"{text!r} never appeared on the screen:\n{self.screen()}")

    def type(self, line: str) -> None:
        self("send-keys", "-t", "s", "-l", line)
        self("send-keys", "-t", "s", "Enter")


@pytest.mark.skipif(shutil.which("tmux") is None, reason="needs tmux")
def test_the_real_program_in_a_terminal(tmp_path):
    tmux = Tmux(f"dentibot-test-{os.getpid()}")
    cmd = (f"cd {tmp_path} && env -u COLUMNS -u LINES {sys.executable} -m dentibot.cli "
           "session --calibrated "
           f"-c connect -c 'align fz=1'; echo EXITED $?; sleep 30")
    tmux("new-session", "-d", "-s", "s", "-x", "130", "-y", "40", cmd)
    try:
        screen = tmux.wait_for("State     self_aligning")
        assert "built-in simulator (real time)" in screen
        tmux.type("drill tau_d=40")
        tmux.wait_for("treating > drilling > feeding")
        tmux("send-keys", "-t", "s", "Space")         # space on the empty line: pause
        tmux.wait_for("treating > paused")
        tmux.type("reverse")                          # not while paused: refused, with why
        screen = tmux.wait_for("'reverse' refused in state 'treating.paused'")
        assert "it needs state treating.drilling.feeding" in screen
        tmux.type("retract")
        tmux.wait_for("State     done")
        tmux("send-keys", "-t", "s", "C-q")
        screen = tmux.wait_for("EXITED 0")
    finally:
        subprocess.run([*tmux.base, "kill-server"], check=False, capture_output=True,
                       timeout=10)
