import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

from sim.config import SCENARIOS
from sim.gym_env import NavEnv, NavVectorEnv


@pytest.mark.filterwarnings("ignore:.*maximum value is infinity")
@pytest.mark.parametrize("name", list(SCENARIOS))
def test_single_world_env_passes_gymnasium_checker(name: str) -> None:
    check_env(NavEnv(name), skip_render_check=True)


def test_vector_env_declares_same_step_autoreset() -> None:
    assert NavVectorEnv("walls-inertia", 2).metadata["autoreset_mode"] is AutoresetMode.SAME_STEP


def test_vector_env_returns_final_observation_where_an_episode_ended() -> None:
    envs = NavVectorEnv("obstacles-inertia", 8)
    envs.reset(seed=0)
    for _ in range(200):
        observation, _, terminated, truncated, info = envs.step(np.zeros(8, np.int64))
        done = terminated | truncated
        if done.any():
            break
    assert done.any()
    np.testing.assert_array_equal(info["_final_obs"], done)
    index = int(np.flatnonzero(done)[0])
    assert not np.array_equal(info["final_obs"]["target"][index], observation["target"][index])


def test_vector_world_i_replays_the_single_env_seeded_s_plus_i() -> None:
    envs = NavVectorEnv("walls-increment", 4)
    single = NavEnv("walls-increment")
    vector_obs, _ = envs.reset(seed=100)
    single_obs, _ = single.reset(seed=102)
    actions = np.random.default_rng(0).integers(0, 3, size=(150, 4))
    for row in actions:
        np.testing.assert_array_equal(vector_obs["scan"][2], single_obs["scan"])
        vector_obs, reward, terminated, truncated, _ = envs.step(row)
        single_obs, single_reward, single_terminated, single_truncated, _ = single.step(row[2])
        assert reward[2] == single_reward
        assert terminated[2] == single_terminated and truncated[2] == single_truncated
        if single_terminated or single_truncated:
            single_obs, _ = single.reset()
