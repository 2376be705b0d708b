"""The only place that chooses the simulated world or the hardware and wires a procedure.

- :mod:`~dentibot.app.simulated`: the built-in simulator (world, in-process devices, lock-step
  clock) under a runtime;
- :mod:`~dentibot.app.steps`: what the protocol steps (calibrate, drag, align, drill) and the
  safe stop do on a running procedure;
- :mod:`~dentibot.app.runner`: a protocol run end to end, with its recording and summary;
- :mod:`~dentibot.app.selftest`: the fault catalogue injected while drilling.
"""
