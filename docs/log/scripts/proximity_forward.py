# Ad hoc measurement of issue 53 (2026-12-07); runs against the commit adding the proximity stop
# (controller/proximity.py), and later.
"""Does the proximity stop keep a driver that always drives forward off the walls? In a world of
static walls (walls-inertia), 64 cars drive forward (the first of their values), and turn left
(the second) where the controller's field forbids forward, the field read from each car's exact
scan as the controller reads it (`controller.proximity`). The simulator has no stop: where the
field forbids every action the car turns left, and the count is printed.

Usage: proximity_forward.py SCENARIO TRAVEL EPISODES   (TRAVEL: `proximity.travel_m`; "none":
no proximity stop)
"""

from __future__ import annotations

import sys

import numpy as np

from qnav.contracts.motion import action_velocities
from qnav.controller.proximity import (
    ProximitySettings,
    allowed_actions,
    blocked_parts,
    field_ranges,
    guarded_action,
)
from qnav.sim.config import scenario
from qnav.sim.world import BatchedWorld

CARS = 64
VALUES = np.array([1.0, 0.5, 0.0])  # forward first, then left, then right


def main() -> None:
    world, travel, episodes = scenario(sys.argv[1]), sys.argv[2], int(sys.argv[3])
    field = None if travel == "none" else ProximitySettings(travel_m=float(travel))
    assert world.lidar is not None
    linear = np.array([v for v, _ in action_velocities(world.dynamics, world.control_period_s)])
    angles = world.lidar.beam_angles_rad()
    cars = BatchedWorld(world, CARS, seed=7)
    observation = cars.reset(7)
    counts = {"success": 0, "collision": 0, "unfinished": 0}
    stops = ended = 0
    while ended < episodes:
        actions = np.zeros(CARS, dtype=np.int64)
        for row in range(CARS) if field is not None else ():
            assert observation.scan_m is not None
            ranges = field_ranges(observation.scan_m[row], 0.0, np.inf, False)
            blocked = blocked_parts(angles, ranges, field.footprint_m, field.travel_m)
            choice = guarded_action(0, allowed_actions(linear, blocked), VALUES)
            stops += choice is None
            actions[row] = 1 if choice is None else choice
        result = cars.step(actions)
        observation = result.observation
        done = result.transition.terminated | result.transition.truncated
        for row in np.flatnonzero(done):
            outcome = int(result.transition.outcome[row])
            counts[{0: "unfinished", 1: "success", 2: "collision"}[outcome]] += 1
            ended += 1
    print(sys.argv[1], f"travel {travel}", counts, f"every action forbidden {stops} times")


if __name__ == "__main__":
    main()
