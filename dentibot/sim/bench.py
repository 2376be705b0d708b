"""World-step timing with the file in contact and cutting (see benchmarks/world_step.py)."""

from __future__ import annotations

import time

import numpy as np

from dentibot.sim.world import World, WorldConfig


def world_step_times_us(n: int = 20000, seed: int = 0) -> np.ndarray:
    """Per-step times (us) of ``World.step`` while the file feeds at 0.1 mm/s at 60 rpm,
    8 mm deep and pressed 0.2 mm sideways (lateral contact, engagement, cutting, debris)."""
    w = World(WorldConfig(seed=seed))
    w.handpiece.set_velocity(60.0)

    def drive(v, seconds):
        for k in range(int(seconds / w.ts)):
            if k % 5 == 0:
                w.arm.command_velocity(w.tool_rates(v), w.t)
            w.step()

    drive((0.0, 0.0, 1.0), 6.0)       # gap + 4 mm
    drive((0.0, 0.0, 0.5), 8.0)       # 8 mm deep, cutting
    drive((0.4, 0.0, 0.0), 0.5)       # 0.2 mm sideways: lateral contact
    qd = w.tool_rates((0.0, 0.0, 0.1))
    out = np.empty(n)
    step = w.step
    clock = time.perf_counter_ns
    for k in range(n):
        if k % 20 == 0:
            w.arm.command_velocity(qd, w.t)
        t0 = clock()
        step()
        out[k] = clock() - t0
    assert w.interaction.engagement_mm2 > 0.0 and w.fractured is None
    assert any(w.interaction.f_lat)
    return out / 1000.0


def main() -> None:  # pragma: no cover - a benchmark
    t = world_step_times_us()
    import sys
    sys.stdout.write(f"World.step (contact + cutting), n={t.size}: median {np.median(t):.1f} us, "
                     f"p99 {np.percentile(t, 99):.1f} us, max {t.max():.1f} us\n")


if __name__ == "__main__":  # pragma: no cover
    main()
