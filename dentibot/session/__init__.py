"""``dentibot session``: drive DentiBot step by step at the bench, through its state machine.

- :mod:`~dentibot.session.commands`: the command language (parsing, parameters validated by
  the protocol schema's step models, help, completion);
- :mod:`~dentibot.session.controller`: :class:`SessionController` (devices, the running
  control task, commands, refusals, safe stop, recording) without a screen;
- :mod:`~dentibot.session.panel`: the live panel's text;
- :mod:`~dentibot.session.app`: the terminal UI (textual), imported on demand.
"""

from dentibot.session.commands import COMMANDS, Command, CommandError, help_text, parse
from dentibot.session.controller import (
    PanelData,
    Reply,
    SessionController,
    SessionOptions,
    default_protocol,
)

__all__ = ["COMMANDS", "Command", "CommandError", "PanelData", "Reply", "SessionController",
           "SessionOptions", "default_protocol", "help_text", "parse"]
