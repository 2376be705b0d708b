"""Median / p99 time of one World.step with the file in contact and cutting.

Run: ``.venv/bin/python benchmarks/world_step.py`` (target: median <= 30 us).
"""

from dentibot.sim.bench import world_step_times_us

if __name__ == "__main__":
    import numpy as np

    t = world_step_times_us()
    print(f"World.step (contact + cutting), n={t.size}: median {np.median(t):.1f} us, "
          f"p99 {np.percentile(t, 99):.1f} us, max {t.max():.1f} us")
