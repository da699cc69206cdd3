"""Doom labels from a training run's own experience: its stored steps among re-drawn obstacles.

A policy's experience shows the outcome of the actions it took, never of the ones it avoided,
and labels of the taken action alone teach a doom network nothing (`probe.labelled_actions =
taken`). The fast preset already re-draws obstacles around each stored step for TD
(`training.sampling.draw_obstacle_paths`): the obstacles never react to the robot, so its stored
path is as possible among any others. Here the same fresh obstacles meet the planner's labels
for every action (`lab.oracle.collision_shares`, the simulator's own rollouts), so the few
hundred episodes a run collects give as many labelled states as there is CPU to label them,
each decisive state of them a new arrangement of obstacles around a pose the learner reached.

`qnav lab probe --probe-set probe.redrawn_from=RUN` fits the doom network to them; `qnav lab
label FOLDER --probe-set probe.redrawn_from=RUN` adds rounds that label, of fresh re-drawn states
at the same stored steps, only those where the latest fit doubts (`lab.doubt.redraw_and_label`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from qnav.contracts.errors import ConfigError
from qnav.contracts.judge_file import encoded_surroundings
from qnav.contracts.motion import step_robot
from qnav.contracts.observation import (
    distance_scale_m,
)
from qnav.lab.decisive import DRIVERS, DecisiveStates, is_decisive
from qnav.lab.oracle import collision_shares
from qnav.sim.config import WorldConfig
from qnav.sim.world import WorldState, concatenate_rows, take_rows
from qnav.training.episode_log import read_rounds
from qnav.training.run_folder import read_settings
from qnav.training.sampling import draw_obstacle_paths

STORED_PATH = DRIVERS.index("a run's stored path")
"""`DecisiveStates.driver` of a state on a run's stored path."""

LABEL_BATCH = 2000
"""States labelled together (bounds the planner's rollout arrays)."""


class StoredSteps(NamedTuple):
    """Every step a run's episodes took, flattened, with what the labels need of it."""

    pose: NDArray[np.float64]
    """(S, 3) the robot's pose before the step."""
    velocity: NDArray[np.float64]
    """(S, 2) its speed and turn rate there, rebuilt by replaying the stored actions."""
    target_xy: NDArray[np.float64]
    """(S, 2) the episode's target."""
    action: NDArray[np.int64]
    """(S,) the action the run took there."""
    episode: NDArray[np.int64]
    """(S,) the episode's index in the run."""
    step: NDArray[np.int64]
    """(S,) the step's index in its episode."""
    window: NDArray[np.int64]
    """(S, k) rows of `pose` of the k frames up to this one, oldest first (the first repeated at
    an episode's start)."""


def stored_steps(world: WorldConfig, run_dir: Path, window: int) -> StoredSteps:
    """The steps of every episode stored in `run_dir`, which must have been trained in
    `world`; the velocities are replayed from the stored actions, and a run whose poses do not
    replay (another world's dynamics) is refused."""
    trained_in = read_settings(run_dir).world
    if trained_in.name != world.name:
        raise ConfigError(
            f"probe.redrawn_from: {run_dir} was trained in {trained_in.name!r}, not {world.name!r}"
        )
    parts: list[tuple[NDArray[Any], ...]] = []
    first_row = 0
    episodes = [episode for found in read_rounds(run_dir / "episodes") for episode in found]
    if not episodes:
        raise ConfigError(f"probe.redrawn_from: {run_dir} holds no episodes yet")
    for index, episode in enumerate(episodes):
        steps = len(episode.action)
        pose = episode.pose[:1].copy()
        velocity = np.zeros((1, 2))
        velocities = np.zeros((steps, 2))
        for t in range(steps):
            velocities[t] = velocity[0]
            pose, velocity = step_robot(
                pose, velocity, episode.action[t : t + 1], world.dynamics, world.control_period_s
            )
            if not np.allclose(pose[0, :2], episode.pose[t + 1, :2], atol=1e-6):
                raise ConfigError(
                    f"probe.redrawn_from: episode {index} of {run_dir} does not replay in "
                    f"{world.name!r} at step {t} (trained under other dynamics?)"
                )
        step_index = np.arange(steps)
        back = np.arange(window - 1, -1, -1)
        parts.append(
            (
                episode.pose[:-1],
                velocities,
                np.repeat(episode.target_xy[None], steps, axis=0),
                episode.action,
                np.full(steps, index),
                step_index,
                first_row + np.maximum(step_index[:, None] - back[None], 0),
            )
        )
        first_row += steps
    pose, velocity, target, action, episode_index, step, rows = (
        np.concatenate(part) for part in zip(*parts, strict=True)
    )
    return StoredSteps(pose, velocity, target, action, episode_index, step, rows)


def redrawn_worlds(
    world: WorldConfig,
    steps: StoredSteps,
    rows: NDArray[np.int64],
    *,
    window: int,
    seed: int,
    chance: np.random.Generator,
) -> WorldState:
    """The worlds at stored steps `rows` among fresh obstacles drawn from `chance`, each of
    which kept clear of the robot over its last `window` frames (as TD's re-drawing)."""
    frames = steps.window[rows]
    centres, velocities = draw_obstacle_paths(
        world, steps.pose[frames], np.diff(frames, axis=1) > 0, history=window, rng=chance
    )
    return WorldState(
        pose=steps.pose[rows],
        velocity=steps.velocity[rows],
        target_xy=steps.target_xy[rows],
        obstacle_xy=centres[:, -1],
        obstacle_velocity=velocities[:, -1],
        steps=steps.step[rows],
        seed=np.full(rows.size, seed, dtype=np.int64),
        episode=steps.episode[rows],
    )


def encoded_view(
    world: WorldConfig, state: WorldState
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """What a doom network given the obstacles sees of worlds known without an observation:
    the encoded target (K, TARGET_FEATURES) and obstacles (K, OBSTACLE_FEATURES)."""
    return encoded_surroundings(
        state.pose,
        state.target_xy,
        state.obstacle_xy,
        state.obstacle_velocity,
        distance_scale_m(world.lidar),
    )


def redrawn_states(
    world: WorldConfig,
    run_dir: Path,
    count: int,
    *,
    window: int,
    ordinary_share: float,
    seed: int,
    progress: bool = False,
) -> DecisiveStates:
    """`count` stored steps of the run, drawn uniformly with replacement, each among fresh
    obstacles that kept clear of the robot over its last `window` frames, labelled by the
    planner; kept are the decisive ones and `ordinary_share` of the others. The states carry
    no scans: their windows hold the encoded target alone, for doom networks given the
    obstacles (`probe.inputs` state or slots)."""
    steps = stored_steps(world, run_dir, window)
    chance = np.random.default_rng([seed, 2])
    picked = chance.integers(0, len(steps.pose), count)
    kept: list[tuple[WorldState, NDArray[np.float32], NDArray[np.int64]]] = []
    for start in tqdm(
        range(0, count, LABEL_BATCH), desc="label re-drawn", unit="batch", disable=not progress
    ):
        rows = picked[start : start + LABEL_BATCH]
        state = redrawn_worlds(world, steps, rows, window=window, seed=seed, chance=chance)
        share = collision_shares(world, state).astype(np.float32)
        keep = is_decisive(share == 1.0) | (chance.random(rows.size) < ordinary_share)
        where = np.flatnonzero(keep)
        kept.append((take_rows(state, where), share[where], rows[where]))
    states, shares, picked_rows = zip(*kept, strict=True)
    world_rows = concatenate_rows(list(states))
    target, obstacles = encoded_view(world, world_rows)
    visited = np.zeros(len(DRIVERS), dtype=np.int64)
    visited[STORED_PATH] = count
    return DecisiveStates(
        windows=target[:, None, :],
        obstacle_windows=obstacles[:, None, :],
        collide_share=np.concatenate(shares),
        world=world_rows,
        driver=np.full(len(world_rows.pose), STORED_PATH, dtype=np.int8),
        taken=steps.action[np.concatenate(picked_rows)].astype(np.int8),
        visited=visited,
    )
