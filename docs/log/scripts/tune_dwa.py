"""Tune the DWA baseline on generated validation worlds (never on BARN's): a seeded random
search over its weights, horizon, margin and oscillation suppression, each candidate run once
in the first WORLDS worlds of the FAMILY validation split (cave: BARN's own family); prints each
candidate's success and metric, best last.

    .venv/bin/python docs/log/scripts/tune_dwa.py [CANDIDATES=16] [WORLDS=64] [FAMILY=cave]

The defaults of `sim.dwa.DwaSettings` are the winner of the run recorded in docs/barn.md.
"""

from __future__ import annotations

import sys
from dataclasses import asdict, replace

import numpy as np

from qnav.sim.benchmark import run_benchmark
from qnav.sim.config import scenario
from qnav.sim.dwa import DwaAgent, DwaSettings


def candidates(count: int, seed: int = 0) -> list[DwaSettings]:
    """The defaults, then `count` random draws."""
    rng = np.random.default_rng(seed)
    drawn = [DwaSettings()]
    for _ in range(count):
        drawn.append(
            DwaSettings(
                heading_weight=round(float(rng.uniform(0.2, 1.0)), 2),
                clearance_weight=round(float(rng.uniform(0.0, 0.5)), 2),
                velocity_weight=round(float(rng.uniform(0.0, 0.5)), 2),
                horizon_s=float(rng.choice([1.0, 1.5, 2.0, 3.0])),
                margin_m=float(rng.choice([0.02, 0.05, 0.1])),
                oscillation_reset_m=float(rng.choice([0.0, 0.3, 0.6])),
            )
        )
    return drawn


def main() -> None:
    count = int(sys.argv[1]) if len(sys.argv) > 1 else 16
    worlds = int(sys.argv[2]) if len(sys.argv) > 2 else 64
    family = sys.argv[3] if len(sys.argv) > 3 else "cave"
    base = scenario("clutter")
    layout = replace(base.layout, source=family, split="validation", worlds=worlds, order="cycle")
    world = replace(base, layout=layout)
    scored = []
    for settings in candidates(count):
        result = run_benchmark(world, DwaAgent(world, worlds, settings), "dwa", num_worlds=worlds)
        scored.append((result.success, result.metric, settings))
        print(
            f"success {result.success:.3f} metric {result.metric:.3f} loops {result.loops:.3f} "
            f"{asdict(settings)}",
            flush=True,
        )
    best = max(scored, key=lambda item: (item[0], item[1]))
    print(f"best: success {best[0]:.3f} metric {best[1]:.3f} {asdict(best[2])}")


if __name__ == "__main__":
    main()
