"""Data for offline imitation without a learner in the loop (DART, Laskey et al. 2017): the
planner given the map drives generated training caves (never BARN's) with random actions
injected, and every state is labelled with its clean choice.

    .venv/bin/python docs/log/scripts/barn_dart_collect.py OUT_RUN WORLDS EPISODES_PER_WORLD NOISE

OUT_RUN gets settings.toml (seed 0's run, `layout.worlds` = WORLDS) and imitation/round_N files
that `barn_offline_bc.py data=OUT_RUN` reads. NOISE: the chance that a step starts a random
action, held 1-3 steps (the learner's mistakes, so the data holds the way back from them).
"""

from __future__ import annotations

import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import Outcome
from qnav.sim.mapplan import MapPlanner
from qnav.sim.world import Observation
from qnav.training.collect import collect_round
from qnav.training.episode_log import write_round
from qnav.training.run_folder import read_settings

BATCH = 256
"""Episodes collected together."""


class NoisyPlanner:
    """The planner, with random actions held for 1-3 steps injected."""

    def __init__(self, planner: MapPlanner, noise: float, streams: int, seed: int) -> None:
        self.planner, self.noise = planner, noise
        self.rng = np.random.default_rng(seed)
        self.held = np.zeros(streams, dtype=np.int64)
        self.random = np.zeros(streams, dtype=np.int64)

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        self.held[worlds] = 0

    def act(self, observation: Observation) -> NDArray[np.int64]:
        clean = self.planner.act(observation)
        n = clean.size
        fresh = (self.held == 0) & (self.rng.random(n) < self.noise)
        self.random[fresh] = self.rng.integers(0, 3, int(fresh.sum()))
        self.held[fresh] = self.rng.integers(1, 4, int(fresh.sum()))
        noisy = self.held > 0
        self.held[noisy] -= 1
        return np.where(noisy, self.random, clean)


def main() -> None:
    out, worlds, per_world, noise = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
    source = Path("runs/cave/dagger-recurrent-seed0")
    settings = read_settings(source)
    world = replace(settings.world, layout=replace(settings.world.layout, worlds=worlds, order="cycle"))
    (out / "imitation").mkdir(parents=True, exist_ok=True)
    shutil.copy(source / "settings.toml", out / "settings.toml")
    planner = MapPlanner(world)
    episodes = np.arange(worlds * per_world, dtype=np.int64)
    started = time.perf_counter()
    for index, ids in enumerate(np.array_split(episodes, max(1, episodes.size // BATCH))):
        agent = NoisyPlanner(planner, noise, ids.size, seed=index)
        collected = collect_round(
            world, agent, 0, ids, labeller=lambda s: planner.act_at(s.pose, s.layout)  # type: ignore[arg-type]
        )
        write_round(out / "imitation", index, collected)
        outcomes = np.array([e.outcome for e in collected])
        print(
            f"round {index}: {ids.size} episodes, {sum(len(e.action) for e in collected)} steps,"
            f" success {np.mean(outcomes == Outcome.SUCCESS):.2f}"
            f" ({time.perf_counter() - started:.0f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
