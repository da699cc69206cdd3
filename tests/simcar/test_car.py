"""The sim-car's rotating lidar: each beam from the car's path and the obstacles of its time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import move_obstacles
from qnav.contracts.transport import ZenohSettings
from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings
from qnav.sim.geometry import cast_lidar
from qnav.sim.world import observe, reset
from qnav.simcar.car import SimCar, SimCarSettings, rotating_scan

TURN_S, PERIOD_S = 0.1, 0.2
MOVE = np.array([0.1, -0.05, 0.2])
"""The car's motion over the period (x m, y m, heading rad), at a steady rate."""


def test_a_rotating_scans_beams_are_cast_along_the_cars_path_among_the_obstacles_then() -> None:
    world = scenario("obstacles-inertia")
    assert world.lidar is not None
    radius, beams = world.obstacles.radius_m, world.lidar.num_beams
    start = reset(world, np.array([EvalSettings().seed]), np.array([2]))
    xy, velocity = move_obstacles(
        start.obstacle_xy, start.obstacle_velocity, radius, world.arena.size_m, PERIOD_S
    )
    end = start._replace(pose=start.pose + MOVE, obstacle_xy=xy, obstacle_velocity=velocity)
    times_s = np.linspace(-PERIOD_S, 0.0, 5)  # the test vehicle's physics steps
    path = start.pose + (1 + times_s[:, None] / PERIOD_S) * MOVE
    scan = rotating_scan(world, end, TURN_S, times_s, path)
    for beam in (0, 1, 250, 719):
        since_start_s = PERIOD_S - TURN_S + TURN_S * beam / beams  # beam j leaves j * dt late
        pose = start.pose + since_start_s / PERIOD_S * MOVE
        then, _ = move_obstacles(
            start.obstacle_xy, start.obstacle_velocity, radius, world.arena.size_m, since_start_s
        )
        expected = cast_lidar(pose, world.lidar, world.arena, then, radius)[0, beam]
        assert scan[beam] == pytest.approx(expected, abs=1e-5), beam
    instantaneous = observe(world, end).scan_m
    assert instantaneous is not None
    assert not np.array_equal(scan, instantaneous[0]), "the turn changed nothing"


def test_a_still_car_among_still_obstacles_gives_the_instantaneous_scan() -> None:
    world = scenario("obstacles-increment")
    state = reset(world, np.array([EvalSettings().seed]), np.array([0]))
    state = state._replace(obstacle_velocity=np.zeros_like(state.obstacle_velocity))
    scan = rotating_scan(world, state, TURN_S, np.zeros(1), state.pose)
    instantaneous = observe(world, state).scan_m
    assert instantaneous is not None
    np.testing.assert_array_equal(scan, instantaneous[0])


def test_a_path_through_the_heading_of_pi_turns_the_short_way() -> None:
    world = scenario("obstacles-inertia")
    state = reset(world, np.array([EvalSettings().seed]), np.array([1]))
    times_s = np.array([-PERIOD_S, 0.0])
    unwrapped = np.repeat(state.pose, 2, axis=0)
    unwrapped[:, 2] = [math.pi - 0.05, math.pi + 0.05]
    wrapped = unwrapped.copy()
    wrapped[1, 2] -= 2 * math.pi
    np.testing.assert_array_equal(
        rotating_scan(world, state, TURN_S, times_s, wrapped),
        rotating_scan(world, state, TURN_S, times_s, unwrapped),
    )


def test_a_rotating_lidar_needs_lockstep_and_a_turn_within_the_control_period() -> None:
    with pytest.raises(ConfigError, match="lidar_turn_s > 0 needs lockstep"):
        SimCarSettings(lidar_turn_s=TURN_S)
    with pytest.raises(ConfigError, match="lidar_turn_s"):
        SimCarSettings(lidar_turn_s=-0.1, lockstep=True)
    world = scenario("obstacles-inertia")
    too_long = SimCarSettings(lidar_turn_s=world.control_period_s * 1.5, lockstep=True)
    with pytest.raises(ConfigError, match=r"lidar_turn_s = 0\.3 s is longer than"):
        SimCar(world, too_long, ZenohSettings())
