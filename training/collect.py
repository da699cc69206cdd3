"""Collect a round of training episodes in parallel worlds of the batched simulator."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import Outcome
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import Agent
from qnav.sim.world import WorldState, observe, reset, step
from qnav.training.episode_log import Episode


def collect_round(
    config: WorldConfig,
    agent: Agent,
    seed: int,
    episode_ids: NDArray[np.int64],
    *,
    labeller: Callable[[WorldState], NDArray[np.int64]] | None = None,
) -> list[Episode]:
    """Run one episode per world, each with the layout of (seed, its episode id), to its end.

    With a `labeller` (the worlds' full state -> actions) the episodes store its action for
    each state visited instead of the action taken (DAgger's labels, `training.imitation`)."""
    n = episode_ids.size
    state = reset(config, np.full(n, seed, dtype=np.int64), episode_ids)
    observation = observe(config, state)
    agent.start(np.arange(n), episode_ids)
    poses, scans, clearances, actions = (
        [observation.pose],
        [observation.scan_m],
        [observation.clearance_m],
        [],
    )
    obstacle_xy, obstacle_velocity = [observation.obstacle_xy], [observation.obstacle_velocity]
    length = np.zeros(n, dtype=np.int64)
    ending = np.full(n, Outcome.RUNNING, dtype=np.int64)
    active = np.ones(n, dtype=bool)
    while active.any():
        action = agent.act(observation)
        recorded = action if labeller is None else labeller(state)
        state, observation, transition = step(config, state, action)
        poses.append(observation.pose)
        scans.append(observation.scan_m)
        clearances.append(observation.clearance_m)
        obstacle_xy.append(observation.obstacle_xy)
        obstacle_velocity.append(observation.obstacle_velocity)
        actions.append(recorded)
        length[active] += 1
        done = (transition.terminated | transition.truncated) & active
        ending[done] = transition.outcome[done]
        active &= ~done
    pose, clearance, act = np.stack(poses), np.stack(clearances), np.stack(actions)
    scan = None if config.lidar is None else np.stack(scans)  # type: ignore[arg-type]
    centres, velocities = np.stack(obstacle_xy), np.stack(obstacle_velocity)
    return [
        Episode(
            pose=pose[: length[i] + 1, i],
            scan_m=None if scan is None else scan[: length[i] + 1, i],
            clearance_m=clearance[: length[i] + 1, i],
            action=act[: length[i], i],
            target_xy=state.target_xy[i],
            outcome=int(ending[i]),
            obstacle_xy=centres[: length[i] + 1, i],
            obstacle_velocity=velocities[: length[i] + 1, i],
        )
        for i in range(n)
    ]
