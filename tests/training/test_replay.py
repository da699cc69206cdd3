from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from qnav.contracts.observation import (
    encode_scan,
)
from qnav.sim.config import scenario
from qnav.sim.evaluate import RandomAgent
from qnav.sim.geometry import cast_lidar, clearance
from qnav.sim.world import observe, reset, step
from qnav.training.collect import collect_round
from qnav.training.episode_log import Episode, read_rounds, write_round
from qnav.training.replay import EpisodeReplay
from qnav.training.sampling import draw_obstacle_paths, draw_targets, sample, view_with_obstacles

CONFIG = scenario("walls-increment")


def _episode(seed: int, steps: int = 400) -> tuple[Episode, list[float], list[bool]]:
    """One random-agent episode, with the rewards and terminations the simulator gave."""
    state = reset(CONFIG, np.array([seed]), np.array([0]))
    observation = observe(CONFIG, state)
    agent = RandomAgent(1, seed=seed)
    agent.start(np.array([0]), np.array([0]))
    assert observation.scan_m is not None
    poses, scans, gaps = (
        [observation.pose[0]],
        [observation.scan_m[0]],
        [observation.clearance_m[0]],
    )
    actions: list[int] = []
    rewards: list[float] = []
    ends: list[bool] = []
    for _ in range(steps):
        action = agent.act(observation)
        state, observation, transition = step(CONFIG, state, action)
        poses.append(observation.pose[0])
        scans.append(observation.scan_m[0])  # type: ignore[index]
        gaps.append(observation.clearance_m[0])
        actions.append(int(action[0]))
        rewards.append(float(transition.reward[0]))
        ends.append(bool(transition.terminated[0]))
        if transition.terminated[0] or transition.truncated[0]:
            break
    episode = Episode(
        np.array(poses),
        np.array(scans),
        np.array(gaps),
        np.array(actions),
        state.target_xy[0],
        int(transition.outcome[0]),
    )
    return episode, rewards, ends


def _replay(*episodes: Episode) -> EpisodeReplay:
    replay = EpisodeReplay(CONFIG, 10_000, window=5)
    for episode in episodes:
        replay.add(episode)
    return replay


def test_own_target_reproduces_the_simulators_rewards_and_terminations() -> None:
    episode, rewards, ends = _episode(3)
    replay = _replay(episode)
    now = np.arange(episode.action.size)
    batch = replay.transitions_at(now, np.repeat(episode.target_xy[None], now.size, axis=0))
    np.testing.assert_allclose(batch.reward, rewards, rtol=1e-6)
    np.testing.assert_array_equal(batch.terminal, ends)
    np.testing.assert_array_equal(batch.action, episode.action)


def test_windows_never_cross_an_episode_start() -> None:
    first, _, _ = _episode(1)
    second, _, _ = _episode(2)
    replay = _replay(first, second)
    start = first.pose.shape[0]  # the second episode's first frame
    batch = replay.transitions_at(np.array([start, start + 2]), np.zeros((2, 2)) + 5.0)
    scans = batch.frames[..., :720]
    # At the first step every earlier frame is a copy of the first frame.
    for frame in range(5):
        np.testing.assert_array_equal(scans[0, frame], scans[0, 4])
    # Two steps in, frames 0-2 are the first frame, then steps 1 and 2, then step 3 for s'.
    np.testing.assert_array_equal(scans[1, 0], scans[1, 2])
    assert not np.array_equal(scans[1, 2], scans[1, 3])


def test_next_window_is_the_following_transitions_window() -> None:
    episode, _, _ = _episode(4)
    replay = _replay(episode)
    target = np.array([[5.0, 5.0]])
    now = replay.transitions_at(np.array([6]), target).frames[0]
    following = replay.transitions_at(np.array([7]), target).frames[0]
    np.testing.assert_array_equal(now[1:], following[:-1])
    assert not np.array_equal(now[0], now[-1])


@pytest.mark.parametrize("relabel", ["paper", "local", "hindsight", "none"])
def test_sampled_targets_follow_the_relabel_rule(relabel: str) -> None:
    episode, _, _ = _episode(5)
    replay = _replay(episode)
    rng = np.random.default_rng(0)
    now = np.arange(episode.action.size)
    targets = draw_targets(replay, now, rng, relabel)  # type: ignore[arg-type]
    if relabel == "none":
        np.testing.assert_array_equal(targets, np.repeat(episode.target_xy[None], now.size, 0))
    elif relabel == "hindsight":
        later = [
            any(np.array_equal(t, p) for p in episode.pose[i + 1 :, :2])
            for i, t in zip(now, targets, strict=True)
        ]
        assert all(later)
    else:
        margin = CONFIG.spawn.wall_margin_m
        assert (targets >= margin).all() and (targets <= CONFIG.arena.size_m - margin).all()
        assert np.unique(targets[:, 0]).size == now.size
    if relabel == "local":
        distance = np.linalg.norm(targets - episode.pose[now, :2], axis=1)
        assert distance.max() <= CONFIG.spawn.target_max_distance_m + 1e-9


def test_hindsight_makes_some_sampled_transitions_successes() -> None:
    episode, _, _ = _episode(6)
    replay = _replay(episode)
    batch = sample(replay, 512, np.random.default_rng(0), "hindsight")
    assert (batch.reward == 1.0).any()
    assert (batch.terminal[batch.reward == 1.0]).all()


def test_n_step_returns_sum_the_simulators_discounted_rewards_to_the_episode_end() -> None:
    episode, rewards, ends = _episode(3)
    replay = _replay(episode)
    gamma, n = 0.9, 4
    now = np.arange(episode.action.size)
    batch = replay.transitions_at(now, np.repeat(episode.target_xy[None], now.size, 0), n, gamma)
    for t in range(now.size):
        steps = min(n, len(rewards) - t)
        expected = sum(gamma**j * rewards[t + j] for j in range(steps))
        assert batch.steps[t] == steps
        assert batch.reward[t] == pytest.approx(expected, rel=1e-5)
        assert batch.terminal[t] == ends[t + steps - 1]
        assert batch.discount[t] == pytest.approx(gamma**steps)


OBSTACLES = scenario("obstacles-inertia")


def _obstacle_episode(seed: int) -> Episode:
    config = replace(OBSTACLES, max_episode_steps=60)
    state = reset(config, np.array([seed]), np.array([0]))
    observation = observe(config, state)
    agent = RandomAgent(1, seed=seed)
    poses, scans, gaps, actions = [observation.pose[0]], [observation.scan_m], [], []
    gaps.append(observation.clearance_m[0])
    while True:
        action = agent.act(observation)
        state, observation, transition = step(config, state, action)
        poses.append(observation.pose[0])
        scans.append(observation.scan_m)
        gaps.append(observation.clearance_m[0])
        actions.append(int(action[0]))
        if transition.terminated[0] or transition.truncated[0]:
            break
    return Episode(
        np.array(poses),
        np.concatenate(scans),  # type: ignore[arg-type]
        np.array(gaps),
        np.array(actions),
        state.target_xy[0],
        int(transition.outcome[0]),
    )


def _obstacle_windows() -> tuple[EpisodeReplay, np.ndarray]:
    """A replay of six random obstacle episodes, and the frame indices (N, 8) of the windows of
    k = 5 frames and 3 steps ahead leaving every stored step but the last of each episode."""
    replay = EpisodeReplay(OBSTACLES, 10_000, window=5)
    for seed in range(6):
        replay.add(_obstacle_episode(seed))
    now = np.arange(replay.size)[replay.last[: replay.size] > np.arange(replay.size)]
    first, last = replay.first[now, None], replay.last[now, None]
    return replay, np.clip(now[:, None] + np.arange(-4, 4), first, last)


def test_redrawn_obstacles_move_as_the_simulators_and_never_touch_the_robot_before_now() -> None:
    replay, index = _obstacle_windows()
    moving = np.diff(index, axis=1) > 0
    rng = np.random.default_rng(2)
    centres, velocities = draw_obstacle_paths(
        OBSTACLES, replay.pose[index], moving, history=5, rng=rng
    )
    radius = OBSTACLES.obstacles.radius_m
    gap = np.linalg.norm(centres - replay.pose[index][:, :, None, :2], axis=-1) - radius
    assert (gap[:, :5] >= OBSTACLES.robot_radius_m).all()
    # Each frame follows from the one before by the simulator's obstacle motion, or stands still.
    for t in range(7):
        step_xy = centres[:, t + 1] - centres[:, t]
        still = ~moving[:, t]
        assert (np.abs(step_xy[still]) == 0).all()
        speed = np.linalg.norm(step_xy[~still], axis=-1) / OBSTACLES.control_period_s
        bounced = (centres[~still, t + 1] <= radius + 0.31) | (centres[~still, t + 1] >= 9.29)
        clean = ~bounced.any(-1)
        assert (speed[clean] >= OBSTACLES.obstacles.speed_min_mps - 1e-9).all()
        assert (speed[clean] <= OBSTACLES.obstacles.speed_max_mps + 1e-9).all()
        # The velocity kept with each frame is the one it moves on by (away from the walls).
        step_by_velocity = velocities[:, t] * OBSTACLES.control_period_s
        np.testing.assert_allclose(step_xy[~still][clean], step_by_velocity[~still][clean])


def test_redrawn_obstacles_give_the_scans_and_clearances_the_simulator_computes() -> None:
    replay = EpisodeReplay(OBSTACLES, 10_000, window=5)
    replay.add(_obstacle_episode(1))
    index = np.arange(replay.size)[:, None]
    pose = replay.pose[index]
    centres, _ = draw_obstacle_paths(
        OBSTACLES, pose, np.zeros((replay.size, 0), bool), history=1, rng=np.random.default_rng(3)
    )
    scans, gaps = view_with_obstacles(
        OBSTACLES, pose, centres, replay.walls_scan[index], replay.walls_clearance[index]
    )
    lidar = OBSTACLES.lidar
    assert lidar is not None
    radius = OBSTACLES.obstacles.radius_m
    expected = cast_lidar(pose[:, 0], lidar, OBSTACLES.arena, centres[:, 0], radius)
    np.testing.assert_allclose(scans[:, 0], encode_scan(expected, lidar.max_range_m), atol=1e-6)
    np.testing.assert_allclose(
        gaps[:, 0], clearance(pose[:, 0, :2], OBSTACLES.arena, centres[:, 0], radius), atol=1e-12
    )


def test_sampling_with_redrawn_obstacles_recomputes_collisions_from_the_fresh_obstacles() -> None:
    replay = EpisodeReplay(OBSTACLES, 10_000, window=5)
    for seed in range(6):
        replay.add(_obstacle_episode(seed))
    plain = sample(replay, 512, np.random.default_rng(0), "none", n_step=1)
    redrawn = sample(
        replay, 512, np.random.default_rng(0), "none", n_step=1, obstacle_redraw_probability=1.0
    )
    assert plain.frames.shape == redrawn.frames.shape
    assert not np.array_equal(plain.frames[..., :720], redrawn.frames[..., :720])
    # Targets and actions are those of the same transitions; only the obstacles changed.
    np.testing.assert_array_equal(plain.frames[..., 720:], redrawn.frames[..., 720:])


def test_collected_episodes_keep_their_obstacles_through_the_round_files(tmp_path: Path) -> None:
    config = replace(OBSTACLES, max_episode_steps=20)
    episodes = collect_round(config, RandomAgent(3, seed=0), 0, np.arange(3))
    write_round(tmp_path, 0, episodes)
    (read,) = read_rounds(tmp_path)
    for before, after in zip(episodes, read, strict=True):
        assert after.obstacle_xy is not None and before.obstacle_xy is not None
        np.testing.assert_array_equal(before.obstacle_xy, after.obstacle_xy)
        np.testing.assert_array_equal(before.obstacle_velocity, after.obstacle_velocity)
