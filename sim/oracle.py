"""An oracle planner: it knows where the obstacles will be, so it bounds what a policy can reach.

Obstacles move in straight lines and bounce off the walls, so a planner given the world's true
state can simulate the future exactly. At every step this one simulates a set of action
sequences (each action held for a while, plus random held sequences) over a horizon, scores
them (reaching the target early is best, colliding late is better than early, otherwise being
close to the target and clear of surfaces), and takes the best sequence's first action
(model-predictive control by random shooting). A learned policy sees only its lidar window, so
it cannot be expected to beat this planner by much: where the planner fails, the world is hard.

`qnav eval --agent oracle --scenario obstacles-inertia` runs it under the test protocol.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from contracts.actions import NUM_ACTIONS
from sim.config import IncrementDynamics, WorldConfig
from sim.dynamics import move_obstacles, step_increment, step_inertia
from sim.evaluate import EvalResult, EvalSettings, drive
from sim.geometry import clearance
from sim.world import WorldState

_HOLDS = (1, 3, 6, 10)


def held_sequences(horizon: int, random_count: int, rng: np.random.Generator) -> NDArray[np.int64]:
    """(S, horizon) candidate sequences: a held then b held, for every a, b and hold, plus
    `random_count` random sequences of actions held three steps each."""
    structured = [
        [a] * hold + [b] * (horizon - hold)
        for a in range(NUM_ACTIONS)
        for hold in (*_HOLDS, horizon)
        for b in range(NUM_ACTIONS)
        if hold <= horizon
    ]
    blocks = -(-horizon // 3)
    random = rng.integers(0, NUM_ACTIONS, size=(random_count, blocks)).repeat(3, axis=1)
    return np.concatenate([np.array(structured)[:, :horizon], random[:, :horizon]])


def plan(config: WorldConfig, state: WorldState, sequences: NDArray[np.int64]) -> NDArray[np.int64]:
    """(N,) the first action of the best of the (S, horizon) sequences for each world in
    `state` (all S are simulated for every world at once)."""
    candidates, horizon = sequences.shape
    worlds = state.pose.shape[0]
    count = worlds * candidates
    actions = np.tile(sequences, (worlds, 1))  # (N * S, horizon), world-major like the states
    pose = np.repeat(state.pose, candidates, axis=0)
    velocity = np.repeat(state.velocity, candidates, axis=0)
    obstacles = np.repeat(state.obstacle_xy, candidates, axis=0)
    obstacle_velocity = np.repeat(state.obstacle_velocity, candidates, axis=0)
    target = np.repeat(state.target_xy, candidates, axis=0)
    radius = config.robot_radius_m
    score = np.zeros(count)
    alive = np.ones(count, dtype=bool)
    distance = gap = np.zeros(count)
    for h in range(horizon):
        if isinstance(config.dynamics, IncrementDynamics):
            pose, velocity = step_increment(pose, velocity, actions[:, h], config.dynamics)
        else:
            pose, velocity = step_inertia(
                pose, velocity, actions[:, h], config.dynamics, config.control_period_s
            )
        obstacles, obstacle_velocity = move_obstacles(
            obstacles,
            obstacle_velocity,
            config.obstacles.radius_m,
            config.arena.size_m,
            config.control_period_s,
        )
        distance = np.linalg.norm(target - pose[:, :2], axis=1)
        gap = clearance(pose[:, :2], config.arena, obstacles, config.obstacles.radius_m)
        reached = alive & (distance < radius)
        hit = alive & ~reached & (gap < radius)
        score[reached] = 1000.0 - h
        score[hit] = -1000.0 + h
        alive &= ~(reached | hit)
    score[alive] = -10.0 * distance[alive] + np.minimum(gap[alive], 1.0)
    best = np.argmax(score.reshape(worlds, candidates), axis=1)
    return np.asarray(sequences[best, 0], dtype=np.int64)


class OracleDriver:
    """The planner driving N worlds at once, for collecting demonstrations: `act(state)`."""

    def __init__(
        self, config: WorldConfig, seed: int, *, horizon: int = 20, random_sequences: int = 128
    ) -> None:
        self.config = config
        self.horizon = horizon
        self.random_sequences = random_sequences
        self.rng = np.random.default_rng(seed)

    def act(self, state: WorldState) -> NDArray[np.int64]:
        """(N,) the planner's action in each world."""
        sequences = held_sequences(self.horizon, self.random_sequences, self.rng)
        return plan(self.config, state, sequences)


def run_oracle(
    config: WorldConfig,
    settings: EvalSettings,
    *,
    horizon: int = 20,
    random_sequences: int = 128,
    progress: bool = False,
) -> EvalResult:
    """The test protocol's episodes (same layouts as `sim.evaluate`) driven by the planner."""
    config = replace(config, max_episode_steps=settings.max_episode_steps)
    driver = OracleDriver(config, settings.seed, horizon=horizon, random_sequences=random_sequences)
    # One episode at a time: the planner's random draws then follow the episode, not the batch.
    results = [
        drive(config, settings.seed, np.array([episode]), lambda state, _: driver.act(state))
        for episode in tqdm(
            range(settings.episodes), desc="oracle", unit="ep", disable=not progress
        )
    ]
    outcomes, steps = (np.concatenate(parts) for parts in zip(*results, strict=True))
    return EvalResult.of_outcomes(outcomes, steps)
