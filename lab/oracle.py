"""An oracle planner: it knows where the obstacles will be, so it bounds what a policy can reach.

Obstacles move in straight lines and bounce off the walls, so a planner given the world's true
state can simulate the future exactly. At every step this one simulates a set of action
sequences (each action held for a while, plus random held sequences) over a horizon, scores
them (reaching the target early is best, colliding late is better than early, otherwise being
close to the target and clear of surfaces), and takes the best sequence's first action
(model-predictive control by random shooting). A learned policy sees only its lidar window, so
it cannot be expected to beat this planner by much: where the planner fails, the world is hard.

The same simulation says which first actions are *doomed*: every continuation the planner
knows collides within a few seconds (`doomed_actions`; `lab.calibrate` counts the layouts lost
from the start).

`qnav eval --agent oracle --scenario obstacles-inertia` runs it under the test protocol. Its
random sequences are drawn from (seed, episode, step), so an episode's plan does not depend on
which other episodes run beside it.
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from qnav.contracts import lookahead
from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.lookahead import (
    LookaheadModel,
    Rollouts,
    candidate_sequences,
    random_blocks_needed,
)
from qnav.sim import rng
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalResult, EvalSettings, drive
from qnav.sim.geometry import wall_segments
from qnav.sim.world import Observation, WorldState

F64 = NDArray[np.float64]

_SEQUENCE_STREAM = 211

DOOM_HORIZON_S = 4.0
"""How far ahead `doomed_actions` looks: an action is doomed when every continuation collides
within this time."""


def lookahead_model(config: WorldConfig) -> LookaheadModel:
    """What the look ahead knows of `config`'s world: all of it (its walls with their openings)."""
    segments = wall_segments(config.arena)
    return LookaheadModel(
        dynamics=config.dynamics,
        control_period_s=config.control_period_s,
        robot_radius_m=config.robot_radius_m,
        obstacle_radius_m=config.obstacles.radius_m,
        room_size_m=config.arena.size_m,
        wall_start=segments.start,
        wall_end=segments.end,
    )


def held_sequences(horizon: int, random_count: int, rng: np.random.Generator) -> NDArray[np.int64]:
    """(S, horizon) candidate sequences: the structured ones plus `random_count` random
    sequences of actions held three steps each."""
    random = rng.integers(0, NUM_ACTIONS, size=(random_count, random_blocks_needed(horizon)))
    return candidate_sequences(random, horizon)


def keyed_sequences(
    state: WorldState, horizon: int, random_count: int, salt: int = 0
) -> NDArray[np.int64]:
    """(N, S, horizon): `held_sequences` for each world, the random ones drawn from that world's
    (seed, episode, step) and `salt`, so a world's candidates do not depend on its batch."""
    keys = rng.episode_keys(
        rng.episode_keys(state.seed, state.episode) ^ np.uint64(salt), state.steps
    )
    draw = rng.uniform(keys, _SEQUENCE_STREAM, (random_count, random_blocks_needed(horizon)))
    random = np.minimum((draw * NUM_ACTIONS).astype(np.int64), NUM_ACTIONS - 1)
    return candidate_sequences(random, horizon)


def simulate(config: WorldConfig, state: WorldState, sequences: NDArray[np.int64]) -> Rollouts:
    """Play every candidate sequence, (S, H) shared by all worlds or (N, S, H) per world, from
    each world of `state`, knowing the obstacles' future exactly."""
    return lookahead.simulate(lookahead_model(config), state, sequences)


def plan(config: WorldConfig, state: WorldState, sequences: NDArray[np.int64]) -> NDArray[np.int64]:
    """(N,) the first action of the best of the candidate sequences, (S, H) shared or (N, S, H)
    per world, for each world in `state`."""
    return lookahead.best_first_actions(lookahead_model(config), state, sequences)


def doom_horizon_steps(config: WorldConfig, horizon_s: float = DOOM_HORIZON_S) -> int:
    """`horizon_s` in control periods (at least one)."""
    return max(1, round(horizon_s / config.control_period_s))


def doomed_actions(
    config: WorldConfig,
    state: WorldState,
    *,
    horizon_s: float = DOOM_HORIZON_S,
    random_sequences: int = 64,
    salt: int = 0,
) -> NDArray[np.bool_]:
    """(N, A): True where every continuation the planner knows, after taking that action first,
    collides within `horizon_s`. A non-doomed action is truly safe for that long; a doomed one
    might be saved by a sequence the planner does not try."""
    shares = collision_shares(
        config, state, horizon_s=horizon_s, random_sequences=random_sequences, salt=salt
    )
    return np.asarray(shares == 1.0, dtype=bool)


def collision_shares(
    config: WorldConfig,
    state: WorldState,
    *,
    horizon_s: float = DOOM_HORIZON_S,
    random_sequences: int = 64,
    salt: int = 0,
) -> NDArray[np.float64]:
    """(N, A): the share of the planner's continuations that collide within `horizon_s` after
    taking each action first (1 where the action is doomed). The same continuations (structured
    and random, drawn per world) follow every first action, so actions are judged alike; the
    share grades how close to doom an action is, where the doom label is all or nothing."""
    horizon = doom_horizon_steps(config, horizon_s)
    tails = keyed_sequences(state, horizon, random_sequences, salt)[:, :, : horizon - 1]
    return lookahead.collision_shares(lookahead_model(config), state, tails)


class StateError(NamedTuple):
    """How far from the true state a perceiver's estimate is: the spread (one standard
    deviation, per axis) of zero-mean Gaussian errors."""

    obstacle_position_m: float
    """Error of each obstacle's position."""
    obstacle_velocity_mps: float
    """Error of each obstacle's velocity."""
    robot_speed_mps: float
    """Error of the robot's own forward speed (hidden under inertia dynamics)."""
    robot_turn_radps: float
    """Error of the robot's own turn rate."""


PERCEPTION_LEVELS: dict[str, StateError] = {
    "exact": StateError(0.0, 0.0, 0.0, 0.0),
    "lidar-grade": StateError(0.01, 0.02, 0.0, 0.0),
    "tracker": StateError(0.03, 0.05, 0.05, 0.1),
    "coarse": StateError(0.1, 0.2, 0.1, 0.2),
}
"""Perception errors `qnav eval --agent oracle --state-error` knows.
A 720-beam lidar resolves 0.5 degree, a few centimetres at the ranges that matter, and five
frames 0.2 s apart give velocities to a few cm/s: "lidar-grade" is what a perfect perceiver of
the window could know, "tracker" a good hand-built obstacle tracker, "coarse" a sloppy one."""


def with_error(world: WorldState, error: StateError, random: np.random.Generator) -> WorldState:
    """A copy of the state as a perceiver with `error` would estimate it (fresh draws)."""

    def noisy(value: F64, sigma: F64 | float) -> F64:
        return value + random.normal(size=value.shape) * sigma

    robot_sigma = np.array([error.robot_speed_mps, error.robot_turn_radps])
    return world._replace(
        obstacle_xy=noisy(world.obstacle_xy, error.obstacle_position_m),
        obstacle_velocity=noisy(world.obstacle_velocity, error.obstacle_velocity_mps),
        velocity=noisy(world.velocity, robot_sigma),
    )


class OracleDriver:
    """The planner driving N worlds at once: `act(state)` gives each world's action.

    Its random candidates are drawn from each world's (seed, episode, step) and the driver's
    `seed`, so a world's plan is the same alone or in any batch.
    """

    def __init__(
        self,
        config: WorldConfig,
        seed: int,
        *,
        horizon: int = 20,
        random_sequences: int = 128,
        state_error: StateError | None = None,
    ) -> None:
        self.config = config
        self.seed = seed
        self.horizon = horizon
        self.random_sequences = random_sequences
        self.state_error = state_error
        self._random = np.random.default_rng([seed, 7])

    def act(self, state: WorldState) -> NDArray[np.int64]:
        """(N,) the planner's action in each world: planned on the true state, or on a fresh
        estimate of it with `state_error` (a perceive-then-plan controller's view)."""
        perceived = state
        if self.state_error is not None:
            perceived = with_error(state, self.state_error, self._random)
        # The candidates are drawn from the true state's keys: the same under any estimate.
        sequences = keyed_sequences(state, self.horizon, self.random_sequences, self.seed)
        return plan(self.config, perceived, sequences)


def run_oracle(
    config: WorldConfig,
    settings: EvalSettings,
    *,
    horizon: int = 20,
    random_sequences: int = 128,
    state_error: StateError | None = None,
    progress: bool = False,
) -> EvalResult:
    """The test protocol's episodes (same layouts as `sim.evaluate`) driven by the planner,
    `settings.num_worlds` episodes at a time; with `state_error`, planning on noisy estimates
    of the state (its error drawn afresh each step, and from the whole batch, so results
    depend on num_worlds)."""
    config = replace(config, max_episode_steps=settings.max_episode_steps)
    driver = OracleDriver(
        config,
        settings.seed,
        horizon=horizon,
        random_sequences=random_sequences,
        state_error=state_error,
    )

    def act(state: WorldState, observation: Observation) -> NDArray[np.int64]:
        return driver.act(state)

    batches = np.array_split(
        np.arange(settings.episodes), -(-settings.episodes // settings.num_worlds)
    )
    results = [
        drive(config, settings.seed, batch, act)
        for batch in tqdm(batches, desc="oracle", unit="batch", disable=not progress)
    ]
    outcomes, steps = (np.concatenate(parts) for parts in zip(*results, strict=True))
    return EvalResult.of_outcomes(outcomes, steps)
