"""A copy of the oracle planner that is given the world's state instead of reading it from scans.

`qnav lab imitate --privileged` asks where the copies of `lab.imitate` lose the planner: in
reading the obstacles' positions and motion from five scans, or in the policy itself. Its copy
sees, at every step, the target features, the robot's velocity, the scan's nearest return in
each of 72 sectors (the walls) and, for every obstacle, its exact position and velocity in the
robot's frame, nearest first: everything the planner needs to foresee the obstacles, whose
future follows from their positions and velocities alone. A small network (two hidden layers
of 512) learns the planner's action from that, and drives the test protocol's layouts.

Near the planner: reading the scans is what the paper's network cannot do. Stalled with the
other copies: a reactive policy, even with perfect state, does not learn the planner's dodges
from its decisions. Diagnostics only: no policy file holds this network.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn
from tqdm import tqdm

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.motion import Outcome
from qnav.contracts.observation import TARGET_FEATURES
from qnav.lab.imitate import (
    AGREEMENT_PROBE,
    DEMONSTRATION_LAYOUT_SEED,
    ImitationResult,
    clone,
    fraction_true,
    greedy_choices,
    held_out_counts,
)
from qnav.lab.imitation_settings import ImitationSettings
from qnav.lab.oracle import OracleDriver
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalResult, EvalSettings, drive, go_to_target
from qnav.sim.world import Observation, WorldState

SECTORS = 72
"""Sectors of the scan the copy sees (nearest return in each, 5 degrees wide)."""
_POSITION_SCALE_M = 10.0
_SPEED_SCALE_M_S = 1.5


def privileged_features(
    config: WorldConfig, state: WorldState, observation: Observation
) -> NDArray[np.float32]:
    """(N, F) what the privileged copy sees (module docstring), each part scaled to about
    [-1, 1]; the first `TARGET_FEATURES` are the target's (distance, sin, cos of its bearing)."""
    n = state.pose.shape[0]
    target = observation.target_features()
    target = np.column_stack([target[:, 0] / _POSITION_SCALE_M, target[:, 1:]])
    parts = [target, state.velocity]
    if observation.scan_m is not None and config.lidar is not None:
        beams = observation.scan_m.shape[1]
        nearest = observation.scan_m.reshape(n, SECTORS, beams // SECTORS).min(axis=2)
        parts.append(np.minimum(nearest / config.lidar.max_range_m, 1.0))
    heading = state.pose[:, 2:3]
    cos, sin = np.cos(heading), np.sin(heading)
    offset = state.obstacle_xy - state.pose[:, None, :2]
    order = np.argsort(np.linalg.norm(offset, axis=2), axis=1)
    offset = np.take_along_axis(offset, order[..., None], axis=1)
    velocity = np.take_along_axis(state.obstacle_velocity, order[..., None], axis=1)

    def robot_frame(xy: NDArray[np.float64]) -> NDArray[np.float64]:
        x, y = xy[..., 0], xy[..., 1]
        return np.stack([cos * x + sin * y, -sin * x + cos * y], axis=-1)

    parts += [
        (robot_frame(offset) / _POSITION_SCALE_M).reshape(n, -1),
        (robot_frame(velocity) / _SPEED_SCALE_M_S).reshape(n, -1),
    ]
    return np.concatenate(parts, axis=1).astype(np.float32)


_SECOND_OPINION_SEED = 1_000_003
"""Offset of the seed of the planner asked again on the held-out states."""


class _Collected(NamedTuple):
    features: NDArray[np.float32]
    actions: NDArray[np.int64]
    success: float
    """The planner's success in these episodes."""
    self_agreement: float
    """Share of the states on which the planner, asked again with other random sequences,
    picks the same action (0 unless asked)."""


def _collect(
    config: WorldConfig,
    settings: ImitationSettings,
    first: int,
    count: int,
    *,
    second_opinion: bool = False,
) -> _Collected:
    """The planner's features and actions on `count` training layouts from episode `first`."""
    config = replace(config, max_episode_steps=settings.max_episode_steps)
    driver = OracleDriver(config, seed=settings.seed + first)
    again = (
        OracleDriver(config, seed=settings.seed + first + _SECOND_OPINION_SEED)
        if second_opinion
        else None
    )
    features: list[NDArray[np.float32]] = []
    actions: list[NDArray[np.int64]] = []
    same: list[NDArray[np.bool_]] = []

    def record(state: WorldState, observation: Observation, action: NDArray[np.int64]) -> None:
        features.append(privileged_features(config, state, observation))
        actions.append(action)
        if again is not None:
            same.append(again.act(state) == action)

    outcomes = []
    with tqdm(total=count, unit="ep", desc="planner episodes", leave=False) as bar:
        for start in range(first, first + count, settings.parallel_worlds):
            ids = np.arange(start, min(start + settings.parallel_worlds, first + count))
            ended, _ = drive(
                config,
                DEMONSTRATION_LAYOUT_SEED + settings.seed,
                ids,
                lambda state, _: driver.act(state),
                record,
            )
            outcomes.append(ended)
            bar.update(ids.size)
    return _Collected(
        np.concatenate(features),
        np.concatenate(actions),
        float(np.mean(np.concatenate(outcomes) == Outcome.SUCCESS)),
        fraction_true(np.concatenate(same)) if same else 0.0,
    )


def _network(inputs: int) -> nn.Module:
    return nn.Sequential(
        nn.Linear(inputs, 512),
        nn.ReLU(),
        nn.Linear(512, 512),
        nn.ReLU(),
        nn.Linear(512, NUM_ACTIONS),
    )


def _baseline(features: NDArray[np.float32]) -> NDArray[np.int64]:
    """The go-to-target baseline's action from `privileged_features` rows."""
    return go_to_target(features[:, :TARGET_FEATURES])


def imitate_privileged(world: WorldConfig, settings: ImitationSettings) -> ImitationResult:
    """Collect, clone (dodges weighted as `imitate` weighs them), test (module docstring); no
    DAgger."""
    started = time.perf_counter()
    torch.set_num_threads(settings.threads)
    torch.manual_seed(settings.seed)
    features, actions, planner_success, _ = _collect(world, settings, 0, settings.episodes)
    held = _collect(
        world, settings, settings.episodes, settings.held_out_episodes, second_opinion=True
    )
    held_features, held_actions = held.features, held.actions
    network = _network(features.shape[1])
    optimizer = torch.optim.Adam(network.parameters(), lr=settings.learning_rate)
    rng = np.random.default_rng(settings.seed)
    clone(
        network,
        optimizer,
        inputs=features,
        actions=actions,
        baseline=_baseline(features),
        settings=settings,
        rng=rng,
    )
    probe = rng.integers(0, actions.size, AGREEMENT_PROBE)
    protocol = EvalSettings(episodes=settings.test_episodes)
    test_world = replace(world, max_episode_steps=protocol.max_episode_steps)
    outcomes, steps = drive(
        test_world,
        protocol.seed,
        np.arange(settings.test_episodes),
        lambda state, observation: greedy_choices(
            network, privileged_features(test_world, state, observation)
        ),
    )
    return ImitationResult(
        planner_success=planner_success,
        windows=int(actions.size),
        train_agreement=fraction_true(greedy_choices(network, features[probe]) == actions[probe]),
        **held_out_counts(
            greedy_choices(network, held_features), held_actions, _baseline(held_features)
        ),
        test=EvalResult.of_outcomes(outcomes, steps),
        dagger=[],
        planner_self_agreement=held.self_agreement,
        minutes=round((time.perf_counter() - started) / 60, 1),
    )
