"""DentiBot: control software for robot-assisted root canal treatment.

Layers (see ARCHITECTURE.md): ``control`` (pure maths), ``io`` (device interfaces and
drivers), ``sim`` (the simulated world), ``states``, runtime, protocol runner, CLI.
"""

__version__ = "0.1.0"
