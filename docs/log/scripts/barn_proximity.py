"""Gauge: a BARN policy file under the controller's proximity stop, on generated cave validation
worlds (never BARN's), for each safety field given as FOOTPRINT_M,TRAVEL_M ("none": no stop).

    .venv/bin/python docs/log/scripts/barn_proximity.py POLICY.onnx WORLDS none 0.5,0.5 0.3,0.3

The stop is the controller's (`controller.proximity`): a forbidden action is replaced by the best
allowed one by the policy's values, and where nothing may move the action stands and is counted
as a stop (the simulator has no stop; the controller would send one).
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import Outcome
from qnav.controller.proximity import (
    ProximitySettings,
    allowed_actions,
    blocked_parts,
    field_ranges,
    guarded_action,
)
from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings, StreamPolicyAgent, episode_outcomes
from qnav.sim.world import Observation
from qnav.stack import file_agent
from qnav.tracking import lidar_of

FORWARD_MPS = np.array([0.5, 0.0, 0.0])
"""Each action's forward velocity (forward, left, right): only forward needs the travel field."""


class Guarded:
    """The file's agent with the proximity stop below it."""

    def __init__(
        self, inner: StreamPolicyAgent, angles: NDArray[np.float64], field: ProximitySettings
    ) -> None:
        self.inner, self.angles, self.field = inner, angles, field
        self.stops = 0

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        self.inner.start(worlds, episodes)

    def act(self, observation: Observation) -> NDArray[np.int64]:
        actions = self.inner.act(observation).copy()
        assert observation.scan_m is not None
        for row, scan in enumerate(observation.scan_m):
            ranges = field_ranges(scan, 0.0, np.inf, below_min_is_no_return=False)
            blocked = blocked_parts(
                self.angles, ranges, self.field.footprint_m, self.field.travel_m
            )
            allowed = allowed_actions(FORWARD_MPS, blocked)
            choice = guarded_action(int(actions[row]), allowed, self.inner.last_q[row])
            if choice is None:
                self.stops += 1
            else:
                actions[row] = choice
        return actions


def main() -> None:
    policy, count = Path(sys.argv[1]), int(sys.argv[2])
    base = scenario("cave")
    layout = replace(base.layout, split="validation", worlds=count, order="cycle")
    world = replace(base, layout=layout)
    settings = EvalSettings(episodes=count, num_worlds=64, seed=0)
    for spec in sys.argv[3:]:
        agent = file_agent(policy, world, 64, lookahead=None)
        if spec != "none":
            footprint_m, travel_m = map(float, spec.split(","))
            field = ProximitySettings(footprint_m=footprint_m, travel_m=travel_m)
            agent = Guarded(agent, lidar_of(world).beam_angles_rad(), field)  # type: ignore[arg-type]
        outcomes, _ = episode_outcomes(world, agent, settings)
        stops = getattr(agent, "stops", 0)
        shares = [
            np.mean(outcomes == kind)
            for kind in (Outcome.SUCCESS, Outcome.COLLISION, Outcome.RUNNING)
        ]
        print(
            f"{spec}: success {shares[0]:.3f} collision {shares[1]:.3f} "
            f"timeout {shares[2]:.3f}, stops {stops}"
        )


if __name__ == "__main__":
    main()
