"""In-silico trials: populations of canals, files and patients, each procedure run on the
built-in simulator, and the rates a researcher chooses settings by.

- :mod:`~dentibot.trials.population`: the distributions (data, each with its source), seeded
  per procedure;
- :mod:`~dentibot.trials.spec`: the trial file (YAML): population overrides, arms, ``n``;
- :mod:`~dentibot.trials.runner`: the procedures in batches over worker processes (or a Ray
  cluster), each finished batch on disk at once, resumable;
- :mod:`~dentibot.trials.fatigue`: a file's cumulative fatigue over the canals it prepares;
- :mod:`~dentibot.trials.report`: rates with Wilson intervals per arm and curvature class,
  the JSON summary and the figures.

``dentibot trial SPEC.yaml`` runs one (:mod:`dentibot.cli.trial`).
"""
