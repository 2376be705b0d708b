"""An arm left paused by a run that did not park it: the next run refuses to move it unless
the operator asks for the resume (``open_devices(resume_arm=True)``, ``dentibot run
--resume-arm``, the session's ``connect resume-arm``). The four wire simulators on 127.0.0.1."""

from __future__ import annotations

import pytest

from dentibot.app.simulated import serve_wire
from dentibot.errors import DeviceFault
from dentibot.io.devices import ARM_PAUSED, open_devices
from dentibot.io.meca500 import Meca500Driver
from dentibot.session.commands import parse

pytestmark = [pytest.mark.wire, pytest.mark.timeout(60)]


async def _leave_paused(cfg) -> None:
    """A run that ends without parking the arm: activated, homed, motion paused."""
    a = cfg.arm
    arm = Meca500Driver(a.host, a.control_port, a.monitor_port, connection_watchdog_s=0)
    await arm.connect()
    await arm.activate()
    await arm.home()
    await arm.pause_motion()
    await arm.close(deactivate=False)


async def test_a_paused_arm_is_resumed_only_on_the_operators_word():
    async with serve_wire() as bot:
        cfg = bot.devices_config()
        await _leave_paused(cfg)
        with pytest.raises(DeviceFault) as err:
            async with open_devices(cfg):
                pass
        assert ARM_PAUSED in str(err.value)
        async with open_devices(cfg, resume_arm=True) as d:
            assert d.arm.activated and d.arm.homed and not d.arm.paused
        # the run parked the arm on its way out: the next one needs no resume
        async with open_devices(cfg) as d:
            assert not d.arm.paused


def test_the_session_takes_resume_arm_after_the_devices_file():
    cmd = parse("connect devices.yaml resume-arm")
    assert cmd.name == "connect" and cmd.args == ("devices.yaml", "resume-arm")
