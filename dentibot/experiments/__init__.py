"""The thesis's chapter-6 experiments on the built-in simulator (lock-step time).

- :mod:`~dentibot.experiments.alignment`: experiment 1, force-guided alignment under patient
  motion (Table 6.4 configs A, B, C; fig 6.7-6.16).
- :mod:`~dentibot.experiments.preclinical`: experiment 2, pre-clinical evaluation on six
  phantoms A-F (Table 6.5), with the drilling strategy as an ablation switch.

``dentibot experiment alignment|preclinical`` runs them (:mod:`dentibot.cli.experiment`).
"""
