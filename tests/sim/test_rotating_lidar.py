"""A rotating lidar (`WorldConfig.lidar_turn_s`): each beam from the robot's path and the
obstacles of its own time (`sim.world.rotating_scans`)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from numpy.typing import NDArray

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import move_obstacles, step_robot
from qnav.sim.config import WorldConfig, scenario
from qnav.sim.evaluate import EvalSettings
from qnav.sim.geometry import cast_lidar
from qnav.sim.world import WorldState, observe, reset, robot_path, rotating_scans, step

TURN_S = 0.1


def _turning(name: str) -> WorldConfig:
    return replace(scenario(name), lidar_turn_s=TURN_S)


def _beam(
    world: WorldConfig, state: WorldState, after_s: float, pose: NDArray[np.float64], beam: int
) -> float:
    """Beam `beam` of an instantaneous scan from `pose` (1, 3), the obstacles moved on from
    `state` by `after_s` (back for a negative one)."""
    assert world.lidar is not None
    radius = world.obstacles.radius_m
    sign = 1.0 if after_s >= 0 else -1.0
    xy, _ = move_obstacles(
        state.obstacle_xy, sign * state.obstacle_velocity, radius, world.arena.size_m, abs(after_s)
    )
    return float(cast_lidar(pose, world.lidar, world.arena, xy, radius)[0, beam])


def test_each_beam_is_cast_from_where_the_robot_and_the_obstacles_were_at_its_time() -> None:
    world = _turning("obstacles-inertia")
    assert world.lidar is not None
    beams, period_s = world.lidar.num_beams, world.control_period_s
    start = reset(world, np.array([EvalSettings().seed]), np.array([2]))
    start = start._replace(velocity=np.array([[0.4, 0.3]]))  # driving and turning already
    action = np.array([2])
    end, observation, _ = step(world, start, action)
    assert observation.scan_m is not None
    times_s, path = robot_path(world, start, action)
    np.testing.assert_array_equal(path[:, -1], end.pose)  # the path ends where `step` does
    # Beams 0 and B/2 leave at the physics steps 0.1 s and 0.15 s into the period: exactly
    # where the dynamics put the robot then; beam B/4 between them, on the path's chord.
    for beam, after_s in ((0, 0.1), (beams // 2, 0.15)):
        pose, _ = step_robot(start.pose, start.velocity, action, world.dynamics, after_s)
        expected = _beam(world, start, after_s, pose, beam)
        assert observation.scan_m[0, beam] == pytest.approx(expected, abs=1e-4), beam
    assert times_s.tolist() == pytest.approx([-0.2, -0.15, -0.1, -0.05, 0.0])
    middle = (path[:, 2] + path[:, 3]) / 2
    expected = _beam(world, start, period_s - 0.075, middle, beams // 4)
    assert observation.scan_m[0, beams // 4] == pytest.approx(expected, abs=1e-4)
    instantaneous = observe(replace(world, lidar_turn_s=0.0), end).scan_m
    assert instantaneous is not None
    assert not np.array_equal(observation.scan_m, instantaneous), "the turn changed nothing"


def test_an_increment_robots_move_is_read_as_taken_at_a_steady_rate() -> None:
    world = _turning("obstacles-increment")
    assert world.lidar is not None
    start = reset(world, np.array([EvalSettings().seed]), np.array([0]))
    end, observation, _ = step(world, start, np.array([0]))  # forward 0.2 m over 0.5 s
    assert observation.scan_m is not None
    share = 1 - TURN_S / world.control_period_s  # beam 0 leaves 0.4 s into the period
    pose = start.pose + share * (end.pose - start.pose)
    expected = _beam(world, end, -TURN_S, pose, 0)
    assert observation.scan_m[0, 0] == pytest.approx(expected, abs=1e-4)


def test_a_still_robot_among_still_obstacles_sees_the_instantaneous_scan() -> None:
    world = _turning("obstacles-inertia")
    state = reset(world, np.full(2, EvalSettings().seed), np.arange(2))
    state = state._replace(obstacle_velocity=np.zeros_like(state.obstacle_velocity))
    np.testing.assert_array_equal(
        observe(world, state).scan_m, observe(replace(world, lidar_turn_s=0.0), state).scan_m
    )


def test_the_first_scan_of_an_episode_sees_the_obstacles_move_during_the_turn() -> None:
    world = _turning("obstacles-inertia")
    state = reset(world, np.array([EvalSettings().seed]), np.array([4]))
    scan = observe(world, state).scan_m
    instantaneous = observe(replace(world, lidar_turn_s=0.0), state).scan_m
    assert scan is not None and instantaneous is not None
    on_obstacles = np.flatnonzero(scan[0] != instantaneous[0])
    assert on_obstacles.size >= 20  # the beams that see an obstacle that moved during the turn
    for beam in [*on_obstacles, *range(0, 720, 45)]:
        # The robot stands at its start; beam j left 0.1 (1 - j / B) s before the observation.
        expected = _beam(world, state, -TURN_S * (1 - beam / 720), state.pose, beam)
        assert scan[0, beam] == pytest.approx(expected, abs=1e-4), beam


def test_a_path_through_the_heading_of_pi_turns_the_short_way() -> None:
    world = _turning("obstacles-inertia")
    state = reset(world, np.array([EvalSettings().seed]), np.array([1]))
    times_s = np.array([-world.control_period_s, 0.0])
    unwrapped = np.repeat(state.pose[:, None], 2, axis=1)
    unwrapped[0, :, 2] = [math.pi - 0.05, math.pi + 0.05]
    wrapped = unwrapped.copy()
    wrapped[0, 1, 2] -= 2 * math.pi
    np.testing.assert_array_equal(
        rotating_scans(world, state, (times_s, wrapped)),
        rotating_scans(world, state, (times_s, unwrapped)),
    )


def test_a_turn_must_fit_in_the_control_period_on_a_world_with_a_lidar() -> None:
    with pytest.raises(ConfigError, match="lidar_turn_s"):
        replace(scenario("obstacles-inertia"), lidar_turn_s=0.3)
    with pytest.raises(ConfigError, match="lidar_turn_s is set but toycar-inertia has no lidar"):
        replace(scenario("toycar-inertia"), lidar_turn_s=TURN_S)
