"""DentiBot: control software for robot-assisted root canal treatment.

Layers (see docs/architecture.md): ``control`` (pure maths), ``io`` (device interfaces and
drivers), ``sim`` (the simulated world), ``states``, ``runtime`` (the control loop), ``app``
(wiring a procedure on the simulator or the hardware), ``protocol``, ``telemetry``, the
workflows (``session``, ``experiments``) and ``cli``.
"""

__version__ = "0.1.0"
