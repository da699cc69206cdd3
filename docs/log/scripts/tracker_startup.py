# Ad hoc measurement of issue 19 (2026-12-06).
"""What perception costs the shield, by step of the episode: the shielded DQN on the onboard
tracker collides more than on the true state mostly in an episode's first seconds
(shield_rule.py's collisions_by_step). At each decision, every true obstacle within RANGE_M of the
car is matched to the nearest track: missed (none within 0.3 m), or its velocity error.

Usage: tracker_startup.py RUN EPISODES SEED
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from shield_rule import RuledShield, shielded  # this folder, where the script runs from

from qnav.controller.lookahead import LookaheadSettings
from qnav.sim.evaluate import episode_outcomes

RANGE_M = 3.0
STEPS = 12


class Watched(RuledShield):
    """The committed shield, tabulating the tracker against the truth by step of the episode:
    per step, [obstacles, missed, position errors, velocity errors]."""

    def __init__(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        self.rule = f"near{self.settings.overrule_share}"
        self.table = {k: [0, 0, [], []] for k in range(STEPS)}

    def act(self, observation):  # type: ignore[no-untyped-def]
        action = super().act(observation)
        for row, car in enumerate(self.cars):
            step = int(self.steps[row]) - 1
            if not self.counting[row] or step >= STEPS:
                continue
            belief = car.belief(observation.target_xy[row])
            truth_xy = self.state.obstacle_xy[row]
            truth_v = self.state.obstacle_velocity[row]
            near = np.linalg.norm(truth_xy - self.state.pose[row, :2], axis=1) < RANGE_M
            tracks_xy, tracks_v = belief.obstacle_xy[0], belief.obstacle_velocity[0]
            cell = self.table[step]
            for index in np.flatnonzero(near):
                cell[0] += 1
                if len(tracks_xy) == 0:
                    cell[1] += 1
                    continue
                gaps = np.linalg.norm(tracks_xy - truth_xy[index], axis=1)
                nearest = int(gaps.argmin())
                if gaps[nearest] > 0.3:
                    cell[1] += 1
                    continue
                cell[2].append(gaps[nearest])
                cell[3].append(np.linalg.norm(tracks_v[nearest] - truth_v[index]))
        return action


def main() -> None:
    torch.set_num_threads(1)
    run, episodes, seed = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    lookahead = LookaheadSettings(mode="shield")
    agent, world, settings = shielded(run, episodes, seed, lookahead, Watched)
    episode_outcomes(world, agent, settings, watch=agent.watch)
    print(f"{run}, {episodes} episodes: true obstacles within {RANGE_M} m of the car, by step")
    print(
        "step | obstacles | missed | position error median / p90 m | "
        "velocity error median / p90 m/s"
    )
    for step, (count, missed, position, velocity) in agent.table.items():
        p = np.percentile(position, [50, 90]) if position else [np.nan] * 2
        v = np.percentile(velocity, [50, 90]) if velocity else [np.nan] * 2
        print(
            f"{step} | {count} | {missed / max(count, 1):.3f} | {p[0]:.3f} / {p[1]:.3f} | "
            f"{v[0]:.3f} / {v[1]:.3f}"
        )


if __name__ == "__main__":
    main()
