"""The thesis's chapter-6 experiments on the built-in simulator (lock-step time).

- :mod:`~dentibot.experiments.alignment`: experiment 1, force-guided alignment under patient
  motion (Table 6.4 configs A, B, C; fig 6.7-6.16).
- :mod:`~dentibot.experiments.preclinical`: experiment 2, pre-clinical evaluation on six
  phantoms A-F (Table 6.5), with the drilling strategy as an ablation switch.

- :mod:`~dentibot.experiments.results`: an experiment end to end (runs, figures, the
  thesis's claims checked) and its machine-readable result.

``dentibot experiment alignment|preclinical`` runs them (:mod:`dentibot.cli.experiment`), and
so does :func:`dentibot.api.run_experiment`.
"""
