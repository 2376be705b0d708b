"""A file's life over the canals it prepares: cumulative cyclic-fatigue damage (Miner's rule).

A NiTi file turning in a curved canal bends back and forth once per revolution; at a surface
strain amplitude ``eps`` it survives ``N_f = (C / eps)^(1/b)`` such cycles (a strain-life law
of Coffin-Manson form, ``eps = C N_f^-b``; Coffin 1954, Manson 1953). The simulator uses it with
``C = 1.0``, ``b = 0.5`` (:meth:`dentibot.sim.nitifile.NiTiFile.cycles_to_failure`: about 330
cycles at 5.5 % strain, the order Pruett, Clement & Carnes 1997, J Endod 23:77, report for a
5 mm radius) and sums the damage ``sum n_i / N_f(eps_i)`` over every revolution under strain
(Miner 1945, J Appl Mech 12:A159; the world's ``fatigue_damage``, 1 = fatigue fracture). The
surface strain of a file of diameter ``d`` bent to radius ``rho`` is ``d / (2 rho)``
(:mod:`dentibot.sim.canal`).

Each procedure of a trial records both the simulator's Miner sum (``fatigue_damage_sim``) and
the sum under its file's own constants (``fatigue_damage``: the population's
``file.fatigue_c`` and ``file.fatigue_b``, the same by default), each from a fresh file.

Canals per file (:func:`canals_until_failure`): a file goes from canal to canal of the arm's
population (drawn with replacement from the arm's procedures), its damage adding up, until the
sum reaches 1 (fatigue) or a canal breaks it outright (a procedure that fractured). Assumptions:
the damage of a canal does not depend on the damage before it, and fatigue does not lower the
file's torsional strength (it does in fact: Jamleh et al. 2021, Saudi Dent J 33:614, report
lower torsional resistance of files held curved), so the counts are upper bounds; cleaning and
sterilisation between canals are not modelled.
"""

from __future__ import annotations

import math

import numpy as np

#: The simulator's strain-life constants (dentibot.sim.nitifile; a test holds them together).
FATIGUE_C = 1.0
FATIGUE_B = 0.5


def cycles_to_failure(strain: float, c: float = FATIGUE_C, b: float = FATIGUE_B) -> float:
    """Cycles to fatigue failure at surface strain amplitude ``strain``:
    ``(c / strain)^(1/b)``; infinite without strain."""
    if strain <= 0.0:
        return math.inf
    return (c / strain) ** (1.0 / b)


def bending_strain(diameter_mm: float, radius_mm: float) -> float:
    """Surface strain amplitude of a round file of ``diameter_mm`` bent to ``radius_mm``."""
    return diameter_mm / (2.0 * radius_mm)


def miner(cycles, strains, c: float = FATIGUE_C, b: float = FATIGUE_B) -> float:
    """Miner's sum ``sum n_i / N_f(eps_i)`` of ``cycles[i]`` cycles at ``strains[i]``."""
    return float(sum(n / cycles_to_failure(e, c, b) for n, e in zip(cycles, strains)))


def canals_until_failure(damage, fractured, rng: np.random.Generator, files: int = 2000,
                         max_canals: int = 200) -> np.ndarray:
    """Canals each of ``files`` simulated files prepares, the failing one included.

    Canal ``k`` of a file is a procedure drawn (with replacement) from ``damage`` (its Miner
    sum) and ``fractured`` (it broke the file outright); the file fails at the first canal
    where it breaks or where its damage so far reaches 1. A file that survives
    ``max_canals`` canals counts ``max_canals + 1`` (censored)."""
    damage = np.asarray(damage, float)
    fractured = np.asarray(fractured, bool)
    if damage.size == 0:
        return np.zeros(0, int)
    pick = rng.integers(0, damage.size, size=(files, max_canals))
    total = np.cumsum(np.nan_to_num(damage, nan=0.0)[pick], axis=1)
    fail = fractured[pick] | (total >= 1.0 - 1e-12)       # 10 x 0.1 is 0.999...9
    first = np.where(fail.any(axis=1), fail.argmax(axis=1) + 1, max_canals + 1)
    return first.astype(int)


def life_summary(canals: np.ndarray, max_canals: int) -> dict:
    """Median, quartiles and mean of the canals per file, the share of files lost in their
    first canal, and the share still whole after ``max_canals`` (censored)."""
    if canals.size == 0:
        return {"files": 0, "median": None, "q25": None, "q75": None, "mean": None,
                "first_canal_failure": None, "censored": None, "max_canals": max_canals}
    q25, med, q75 = (float(x) for x in np.percentile(canals, [25, 50, 75]))
    return {"files": int(canals.size), "median": med, "q25": q25, "q75": q75,
            "mean": float(canals.mean()),
            "first_canal_failure": float(np.mean(canals == 1)),
            "censored": float(np.mean(canals > max_canals)), "max_canals": max_canals}
