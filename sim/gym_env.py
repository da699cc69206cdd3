"""Gymnasium faces of the simulator: one world as a `gymnasium.Env`, N worlds as a `VectorEnv`.

Observations are in physical units, as the car's drivers deliver them: `scan` in metres (+inf for
no return) and `target` = (distance m, sin, cos of bearing). Agents encode them with
`contracts.observation`. The pose, the exact clearance and the outcome are in `info`.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from numpy.typing import NDArray

from contracts.actions import NUM_ACTIONS
from contracts.motion import Outcome
from sim.config import WorldConfig, scenario
from sim.world import BatchedWorld, Observation, Transition, observe, reset, step

ObsDict = dict[str, NDArray[Any]]


def observation_space(config: WorldConfig) -> spaces.Dict:
    """The space of one world's observation."""
    target = spaces.Box(
        low=np.array([0.0, -1.0, -1.0], dtype=np.float32),
        high=np.array([np.inf, 1.0, 1.0], dtype=np.float32),
        dtype=np.float32,
    )
    members: dict[str, spaces.Space[Any]] = {"target": target}
    if config.lidar is not None:
        members["scan"] = spaces.Box(0.0, np.inf, shape=(config.lidar.num_beams,), dtype=np.float32)
    return spaces.Dict(members)


def _as_dict(observation: Observation) -> ObsDict:
    values: ObsDict = {"target": observation.target_features().astype(np.float32)}
    if observation.scan_m is not None:
        values["scan"] = observation.scan_m
    return values


def _info(observation: Observation, transition: Transition | None) -> dict[str, Any]:
    info: dict[str, Any] = {"pose": observation.pose, "clearance_m": observation.clearance_m}
    if transition is not None:
        info["outcome"] = transition.outcome
    return info


def _config(world: str | WorldConfig) -> WorldConfig:
    return scenario(world) if isinstance(world, str) else world


class NavEnv(gym.Env[ObsDict, np.int64]):
    """One world. `reset(seed=s)` starts episode 0 of seed s; later resets continue with 1, 2, ...

    World i of `NavVectorEnv(seed=s)` runs exactly the episodes of `NavEnv` reset with seed s + i.
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 - gymnasium's convention

    def __init__(self, world: str | WorldConfig = "walls-inertia") -> None:
        self.config = _config(world)
        self.observation_space = observation_space(self.config)  # type: ignore[assignment]
        self.action_space = spaces.Discrete(NUM_ACTIONS)
        self._seed: int | None = None
        self._episode = 0
        self._state = reset(self.config, np.zeros(1, np.int64), np.zeros(1, np.int64))

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[ObsDict, dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None:
            self._seed, self._episode = seed, 0
        elif self._seed is None:
            self._seed, self._episode = int(self.np_random.integers(2**62)), 0
        else:
            self._episode += 1
        self._state = reset(self.config, np.array([self._seed]), np.array([self._episode]))
        observation = observe(self.config, self._state)
        return _single(_as_dict(observation)), _single(_info(observation, None))

    def step(self, action: np.int64) -> tuple[ObsDict, float, bool, bool, dict[str, Any]]:
        self._state, observation, transition = step(
            self.config, self._state, np.array([int(action)], dtype=np.int64)
        )
        info = _single(_info(observation, transition))
        info["outcome"] = Outcome(int(info["outcome"])).name.lower()
        return (
            _single(_as_dict(observation)),
            float(transition.reward[0]),
            bool(transition.terminated[0]),
            bool(transition.truncated[0]),
            info,
        )


def _single(values: dict[str, Any]) -> dict[str, Any]:
    return {key: value[0] for key, value in values.items()}


class NavVectorEnv(VectorEnv[ObsDict, NDArray[np.int64], NDArray[Any]]):
    """N worlds stepped as one array program, resetting in the same step an episode ends.

    Where an episode ended, the returned observation starts the next episode and
    `info["final_obs"]` holds the observation the step led to (gymnasium's SAME_STEP mode).
    """

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.SAME_STEP}  # noqa: RUF012

    def __init__(self, world: str | WorldConfig = "walls-inertia", num_envs: int = 16) -> None:
        self.config = _config(world)
        self.num_envs = num_envs
        self.world = BatchedWorld(self.config, num_envs)
        self.single_observation_space = observation_space(self.config)
        self.single_action_space = spaces.Discrete(NUM_ACTIONS)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)

    def reset(
        self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[ObsDict, dict[str, Any]]:
        if isinstance(seed, list):
            raise ValueError("NavVectorEnv takes one seed; world i uses seed + i")
        observation = self.world.reset(seed)
        return _as_dict(observation), _info(observation, None)

    def step(
        self, actions: NDArray[np.int64]
    ) -> tuple[ObsDict, NDArray[Any], NDArray[Any], NDArray[Any], dict[str, Any]]:
        result = self.world.step(np.asarray(actions, dtype=np.int64))
        transition = result.transition
        info = _info(result.next_observation, transition)
        done = transition.terminated | transition.truncated
        if done.any():
            info["final_obs"] = _as_dict(result.next_observation)
            info["_final_obs"] = done
        return (
            _as_dict(result.observation),
            transition.reward,
            transition.terminated,
            transition.truncated,
            info,
        )
