"""The look ahead's rollouts: its shortcuts (obstacles moved once per world, walls measured only
where a candidate may be near them) change no bit of what the plain simulation gives."""

from __future__ import annotations

import numpy as np
import pytest

from qnav.contracts.lookahead import LookaheadModel, Rollouts, simulate
from qnav.contracts.motion import Outcome, clearance, move_obstacles, outcome, step_robot
from qnav.lab.oracle import keyed_sequences, lookahead_model
from qnav.sim.config import scenario
from qnav.sim.world import WorldState, reset


def plain_simulation(model: LookaheadModel, state: WorldState, sequences: np.ndarray) -> Rollouts:
    """The look ahead written the plain way: every candidate with its own copy of the obstacles
    and every surface measured at every step."""
    worlds, candidates, horizon = sequences.shape
    actions = sequences.reshape(worlds * candidates, horizon)
    pose = np.repeat(state.pose, candidates, axis=0)
    velocity = np.repeat(state.velocity, candidates, axis=0)
    obstacles = np.repeat(state.obstacle_xy, candidates, axis=0)
    obstacle_velocity = np.repeat(state.obstacle_velocity, candidates, axis=0)
    target = np.repeat(state.target_xy, candidates, axis=0)
    result = np.full(worlds * candidates, Outcome.RUNNING, dtype=np.int8)
    end_step = np.full(worlds * candidates, horizon, dtype=np.int64)
    score = np.zeros(worlds * candidates)
    alive = np.ones(worlds * candidates, dtype=bool)
    distance = gap = np.zeros(worlds * candidates)
    for h in range(horizon):
        pose, velocity = step_robot(pose, velocity, actions[:, h], model.dynamics,
                                    model.control_period_s)  # fmt: skip
        obstacles, obstacle_velocity = move_obstacles(
            obstacles, obstacle_velocity, model.obstacle_radius_m, model.room_size_m,
            model.control_period_s,
        )  # fmt: skip
        distance = np.linalg.norm(target - pose[:, :2], axis=1)
        gap = clearance(pose[:, :2], model.wall_start, model.wall_end, obstacles,
                        model.obstacle_radius_m)  # fmt: skip
        now = outcome(distance, gap, model.robot_radius_m)
        ended = alive & (now != Outcome.RUNNING)
        result[ended], end_step[ended] = now[ended], h + 1
        score[ended & (now == Outcome.SUCCESS)] = 1000.0 - h
        score[ended & (now == Outcome.COLLISION)] = -1000.0 + h
        alive &= ~ended
    score[alive] = -10.0 * distance[alive] + np.minimum(gap[alive], 1.0)
    shape = (worlds, candidates)
    return Rollouts(result.reshape(shape), end_step.reshape(shape), score.reshape(shape))


def _states(world_name: str, count: int) -> WorldState:
    """Spawned worlds, half of them moved next to a wall or a corner and set moving."""
    world = scenario(world_name)
    state = reset(world, np.arange(count), np.full(count, 11))
    rng = np.random.default_rng(3)
    pose = state.pose.copy()
    near = np.arange(count) % 2 == 0
    size = world.arena.size_m
    pose[near, :2] = rng.choice([0.35, 0.6, 1.2, size - 0.6, size - 1.2], size=(near.sum(), 2))
    pose[:, 2] = rng.uniform(-np.pi, np.pi, count)
    velocity = state.velocity.copy()
    if world.dynamics.kind == "inertia":
        velocity = np.stack([rng.uniform(0, 0.5, count), rng.uniform(-0.5, 0.5, count)], axis=1)
    return state._replace(pose=pose, velocity=velocity)


@pytest.mark.parametrize(
    "world_name", ["obstacles-inertia", "obstacles-increment", "walls-inertia", "walls-increment"]
)
@pytest.mark.parametrize("horizon", [20, 50])
@pytest.mark.parametrize("robot_radius_m", [None, 1.3])
def test_rollouts_are_the_plain_simulations_bit_for_bit(
    world_name: str, horizon: int, robot_radius_m: float | None
) -> None:
    state = _states(world_name, 40)
    sequences = keyed_sequences(state, horizon, 32)
    model = lookahead_model(scenario(world_name))
    if robot_radius_m is not None:  # a robot wider than the score's clearance cap
        model = model._replace(robot_radius_m=robot_radius_m)
    fast, plain = simulate(model, state, sequences), plain_simulation(model, state, sequences)
    if robot_radius_m is None:  # the worlds reach every kind of ending: each is compared
        assert set(np.unique(plain.outcome).tolist()) == {
            Outcome.SUCCESS, Outcome.COLLISION, Outcome.RUNNING
        }  # fmt: skip
    for name, value in fast._asdict().items():
        np.testing.assert_array_equal(value, getattr(plain, name), err_msg=name)
