"""Stable-Baselines3 through the gymnasium faces: its checker, its VecEnv API, a short DQN run."""

import warnings
from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import DQN
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.vec_env import VecMonitor

from qnav.contracts.actions import Action
from qnav.contracts.errors import ConfigError
from qnav.sim.config import scenario
from qnav.sim.gym_env import EncodedWindow, EncodedWindowVector, NavVectorEnv, env_id
from qnav.sim.sb3 import SB3VecEnv, sb3_vec_env


@pytest.mark.parametrize("name", ["obstacles-inertia", "toycar-increment"])
def test_registered_env_passes_sb3_checker_without_a_warning(name: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # SB3 raises on +inf or NaN in observations
        check_env(gym.make(env_id(name)))


def test_encoded_window_passes_sb3_checker() -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(EncodedWindow(gym.make(env_id("obstacles-increment"))))
    # The one remark: a (k, F) window is not a flat vector; SB3's MlpPolicy flattens it itself.
    assert [str(w.message) for w in caught if "unconventional shape" not in str(w.message)] == []


def test_vec_env_reports_truncation_with_the_terminal_window() -> None:
    config = replace(scenario("walls-increment"), max_episode_steps=6)
    envs = sb3_vec_env(config, num_envs=4, seed=3, window=3)
    reference = EncodedWindowVector(NavVectorEnv(config, 4, seed=3), length=3)
    first = envs.reset()
    np.testing.assert_array_equal(first, reference.reset()[0])
    turn = np.full(4, Action.LEFT)  # turning in place: no collision, no target, only the limit
    for step in range(6):
        observation, reward, dones, infos = envs.step(turn)
        expected, expected_reward, _, _, final = reference.step(turn)
        np.testing.assert_array_equal(observation, expected)
        np.testing.assert_array_equal(reward, expected_reward.astype(np.float32))
        assert dones.tolist() == [step == 5] * 4
    assert isinstance(observation, np.ndarray)  # windows, not a Dict
    for i, info in enumerate(infos):
        np.testing.assert_array_equal(info["terminal_observation"], final["final_obs"][i])
        assert info["TimeLimit.truncated"] is True and info["is_success"] is False
        assert not np.array_equal(info["terminal_observation"], observation[i])


def test_vec_env_reports_a_terminal_step_as_no_truncation() -> None:
    envs = sb3_vec_env("walls-increment", num_envs=4, seed=0, window=None)
    envs.reset()
    seen: set[object] = set()
    for _ in range(200):  # driving straight on ends at the target or at a wall
        _, _, dones, infos = envs.step(np.full(4, Action.FORWARD))
        for i in np.flatnonzero(dones):
            info = infos[i]
            assert info["outcome"] in (1, 2) and info["TimeLimit.truncated"] is False
            assert info["is_success"] is (info["outcome"] == 1)
            assert set(info["terminal_observation"]) == {"scan", "target"}
            seen.add(info["outcome"])
    assert seen == {1, 2}


def test_vec_env_seed_applies_at_the_next_reset() -> None:
    envs = sb3_vec_env("obstacles-inertia", num_envs=3)
    envs.seed(7)
    reference, _ = EncodedWindowVector(NavVectorEnv("obstacles-inertia", 3)).reset(seed=7)
    np.testing.assert_array_equal(envs.reset(), reference)


def test_vec_env_needs_same_step_autoreset() -> None:
    sync = gym.make_vec(env_id("walls-inertia"), 2, vectorization_mode="sync")  # NEXT_STEP
    with pytest.raises(ConfigError, match="autoreset_mode"):
        SB3VecEnv(sync)


def test_dqn_trains_through_the_vec_env_and_acts_on_the_single_env() -> None:
    """A few hundred steps of SB3's DQN on 8 batched worlds; the replay buffer holds the windows
    SB3 saw, with each ended episode's last window (not the next episode's first) as its next."""
    config = replace(scenario("walls-increment"), max_episode_steps=20)
    envs = VecMonitor(sb3_vec_env(config, num_envs=8, seed=0))
    model = DQN(
        "MlpPolicy",
        envs,
        buffer_size=1_000,
        learning_starts=100,
        batch_size=32,
        train_freq=4,
        target_update_interval=50,
        policy_kwargs={"net_arch": [32]},
        seed=0,
    )
    model.learn(total_timesteps=384)  # 12 rounds of train_freq 4 steps in 8 worlds

    assert model.num_timesteps == 384 and model._n_updates > 0
    # 8 worlds x 48 steps at 20 steps an episode at most: at least 16 ended, each counted once.
    assert model.ep_info_buffer is not None and model.ep_success_buffer is not None
    assert len(model.ep_info_buffer) >= 16
    assert len(model.ep_success_buffer) == len(model.ep_info_buffer)
    buffer = model.replay_buffer
    assert buffer is not None
    rows = buffer.pos  # 48 rows of 8 worlds, no wrap-around
    assert rows == 48
    observations = buffer.observations[:rows]
    following = buffer.next_observations[:rows]
    window = envs.observation_space
    assert all(window.contains(world) for row in observations for world in row)
    assert all(window.contains(world) for row in following for world in row)
    ended = buffer.dones[: rows - 1].astype(bool)
    assert ended.any() and buffer.timeouts[: rows - 1].astype(bool).any()
    same = (following[:-1] == observations[1:]).all(axis=(2, 3))
    np.testing.assert_array_equal(same, ~ended)

    single = EncodedWindow(gym.make(env_id("walls-increment")))
    observation, _ = single.reset(seed=0)
    action, _ = model.predict(observation, deterministic=True)
    assert int(action) in {int(a) for a in Action}
