"""Stable-Baselines3's face of the batched simulator: a gymnasium vector env as SB3's `VecEnv`.

SB3 steps N environments through its own `VecEnv` API (observations only from `reset`, `dones`,
a list of info dicts with `terminal_observation` and `TimeLimit.truncated`). `SB3VecEnv` gives
that API to any gymnasium vector env that resets in the step an episode ends (SAME_STEP), such as
`NavVectorEnv`, so SB3 trains on the N worlds stepped as one array program, not on N copies of a
single env. `sb3_vec_env` builds the usual one: the paper's window of k encoded frames.

Importing this module imports SB3 and so torch: the dev extra's, never the car's
(`pip install 'qnav[dev]'`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from numpy.typing import NDArray
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import (
    VecEnvIndices,
    VecEnvObs,
    VecEnvStepReturn,
)

from qnav.contracts.errors import ConfigError
from qnav.contracts.observation import WINDOW_LENGTH
from qnav.sim.config import WorldConfig
from qnav.sim.gym_env import EncodedWindowVector, NavVectorEnv


def split_info(info: dict[str, Any], num_envs: int) -> list[dict[str, Any]]:
    """Gymnasium's vector info (arrays, with `_key` masks) as SB3's list of per-env dicts."""
    infos: list[dict[str, Any]] = [{} for _ in range(num_envs)]
    for key, values in info.items():
        if key.startswith("_") or key == "final_obs":
            continue
        mask = info.get(f"_{key}")
        for i in range(num_envs):
            if mask is None or mask[i]:
                infos[i][key] = _row(values, i)
    return infos


def _row(values: Any, i: int) -> Any:
    """Row i of an array (a plain Python value for a scalar), or of every array in a dict."""
    if isinstance(values, dict):
        return {key: value[i] for key, value in values.items()}
    row = values[i]
    return row.item() if isinstance(row, np.generic) else row


class SB3VecEnv(VecEnv):
    """A gymnasium vector env that resets in the step an episode ends, seen as SB3's `VecEnv`.

    Where an episode ended, `infos[i]["terminal_observation"]` is the observation its last step
    led to (SB3 bootstraps from it on truncation), `infos[i]["TimeLimit.truncated"]` says whether
    it was cut by the step limit, and the env's own keys (`is_success`, `outcome`, ...) are
    copied where the env set them. `seed(s)` before `reset()` seeds world i with s + i.
    """

    def __init__(self, envs: VectorEnv[Any, Any, Any]) -> None:
        mode = envs.metadata.get("autoreset_mode")
        if mode is not AutoresetMode.SAME_STEP:
            raise ConfigError(
                f"autoreset_mode {mode}: SB3VecEnv needs an env that resets in the step an "
                "episode ends (AutoresetMode.SAME_STEP), as NavVectorEnv does"
            )
        self.envs = envs
        self._actions: NDArray[Any] | None = None
        super().__init__(envs.num_envs, envs.single_observation_space, envs.single_action_space)

    def reset(self) -> VecEnvObs:
        observation, info = self.envs.reset(seed=self._seeds[0], options=self._options[0] or None)
        self.reset_infos = split_info(info, self.num_envs)
        self._reset_seeds()
        self._reset_options()
        return observation  # type: ignore[no-any-return]

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async(actions) first")
        observation, reward, terminated, truncated, info = self.envs.step(self._actions)
        self._actions = None
        dones = np.logical_or(terminated, truncated)
        infos = split_info(info, self.num_envs)
        for i in np.flatnonzero(dones):
            infos[i]["terminal_observation"] = _row(info["final_obs"], int(i))
            infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        return observation, np.asarray(reward, dtype=np.float32), dones, infos

    def close(self) -> None:
        self.envs.close()

    # The N worlds are one object, so attributes and methods are the vector env's, shared by all.

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        value = getattr(self.envs, attr_name)
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        if len(list(self._get_indices(indices))) != self.num_envs:
            raise NotImplementedError(f"set_attr({attr_name!r}): the worlds share one env")
        setattr(self.envs, attr_name, value)

    def env_method(
        self,
        method_name: str,
        *method_args: Any,
        indices: VecEnvIndices = None,
        **method_kwargs: Any,
    ) -> list[Any]:
        raise NotImplementedError(
            f"env_method({method_name!r}): the worlds are one array program, not separate envs"
        )

    def env_is_wrapped(
        self, wrapper_class: type[gym.Wrapper[Any, Any, Any, Any]], indices: VecEnvIndices = None
    ) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        raise NotImplementedError(
            "SB3VecEnv draws nothing: render one world with gymnasium.make(id, render_mode=...)"
        )


def sb3_vec_env(
    world: str | WorldConfig = "walls-inertia",
    num_envs: int = 16,
    seed: int = 0,
    window: int | None = WINDOW_LENGTH,
) -> SB3VecEnv:
    """N worlds for SB3: each observation the paper's window of `window` encoded frames (k, F),
    or the physical Dict observation with `window=None` (for SB3's MultiInputPolicy)."""
    worlds = NavVectorEnv(world, num_envs, seed)
    return SB3VecEnv(worlds if window is None else EncodedWindowVector(worlds, window))
