import os
import shutil
import subprocess
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

from qnav.contracts.actions import Action
from qnav.contracts.errors import ConfigError
from qnav.contracts.observation import FrameWindow, distance_scale_m, encode_frame
from qnav.sim.config import SCENARIOS, scenario
from qnav.sim.gym_env import (
    EncodedWindow,
    EncodedWindowVector,
    NavEnv,
    NavVectorEnv,
    env_id,
    frame_size,
)
from qnav.sim.world import BatchedWorld

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_registered_env_passes_gymnasium_checker_without_a_warning(name: str) -> None:
    env = gym.make(env_id(name))
    assert isinstance(env.unwrapped, NavEnv) and env.unwrapped.config == scenario(name)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an infinite bound or an out-of-space value would warn
        check_env(env.unwrapped, skip_render_check=True)


def test_gymnasium_checker_renders_every_declared_mode(monkeypatch: pytest.MonkeyPatch) -> None:
    _without_display(monkeypatch)  # "rgb_array" alone: no window opens during the suite
    env = gym.make(env_id("obstacles-inertia"), render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)


def test_ids_are_made_in_a_fresh_interpreter_by_naming_the_module() -> None:
    code = (
        "import gymnasium as gym\n"
        "env = gym.make('qnav.sim.gym_env:qnav/ObstaclesInertia-v0')\n"
        "vec = gym.make_vec('qnav/WallsIncrement-v0', 3, vectorization_mode='vector_entry_point')\n"
        "print(env.unwrapped.config.name, type(vec).__name__, vec.num_envs)"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True
    )
    assert result.stdout.split() == ["obstacles-inertia", "NavVectorEnv", "3"]


def test_no_return_reads_as_the_maximum_range_and_encodes_as_the_policy_does() -> None:
    config = scenario("walls-inertia")  # rays escaping through the openings find nothing
    assert config.lidar is not None
    world = BatchedWorld(config, 1, seed=3)
    raw = world.reset(seed=3)
    observation, _ = NavEnv("walls-inertia").reset(seed=3)
    assert raw.scan_m is not None and np.isinf(raw.scan_m).any()
    scan = observation["scan"]
    np.testing.assert_array_equal(np.isinf(raw.scan_m[0]), scan == config.lidar.max_range_m)
    assert np.isfinite(scan).all()
    scale = distance_scale_m(config.lidar)
    np.testing.assert_array_equal(
        encode_frame(scan, observation["target"], scale),
        encode_frame(raw.scan_m[0], raw.target_features()[0].astype(np.float32), scale),
    )


def _towards_target(target: np.ndarray) -> int:
    """Turn towards the target until it is nearly ahead, then drive."""
    _, sin, cos = target
    if cos > 0.98:
        return int(Action.FORWARD)
    return int(Action.LEFT if sin > 0 else Action.RIGHT)


def _run_episode(env: NavEnv, seed: int, drive_to_target: bool) -> list[dict[str, object]]:
    observation, _ = env.reset(seed=seed)
    infos = []
    terminated = truncated = False
    while not (terminated or truncated):
        action = _towards_target(observation["target"]) if drive_to_target else Action.FORWARD
        observation, _, terminated, truncated, info = env.step(np.int64(action))
        infos.append(info)
    return infos


def test_is_success_only_at_an_episode_end() -> None:
    env = NavEnv("walls-increment")  # no obstacles: the straight path to the target is clear
    reached = _run_episode(env, seed=5, drive_to_target=True)
    crashed = _run_episode(env, seed=5, drive_to_target=False)
    for infos in (reached, crashed):
        assert len(infos) > 1 and not any("is_success" in info for info in infos[:-1])
    assert reached[-1]["outcome"] == "success" and reached[-1]["is_success"] is True
    assert crashed[-1]["outcome"] == "collision" and crashed[-1]["is_success"] is False


def test_vector_is_success_marks_the_worlds_that_reached_the_target() -> None:
    envs = NavVectorEnv("walls-increment", 6, seed=40)
    observation, _ = envs.reset()
    first_success = np.full(6, -1)  # is_success of each world's first episode
    while (first_success < 0).any():
        actions = np.array([_towards_target(row) for row in observation["target"]])
        actions[3:] = Action.FORWARD  # worlds 3-5 drive into a wall
        observation, _, terminated, truncated, info = envs.step(actions)
        done = terminated | truncated
        if done.any():
            np.testing.assert_array_equal(info["_is_success"], done)
            np.testing.assert_array_equal(info["is_success"], done & (info["outcome"] == 1))
            first_success[done & (first_success < 0)] = info["is_success"][
                done & (first_success < 0)
            ]
        else:
            assert "is_success" not in info
    np.testing.assert_array_equal(first_success, [1, 1, 1, 0, 0, 0])


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


@pytest.mark.parametrize("name", ["obstacles-increment", "toycar-inertia"])
def test_encoded_windows_are_what_the_policy_sees(name: str) -> None:
    """The windows equal FrameWindow over encode_frame of the simulator's raw observations (the
    learner's and controller's path), episode ends included; every window lies in its Box."""
    config = replace(scenario(name), max_episode_steps=12)  # several ends in a short run
    envs = EncodedWindowVector(NavVectorEnv(config, 5, seed=9), length=4)
    world = BatchedWorld(config, 5, seed=9)
    reference = FrameWindow(5, frame_size(config), 4)
    scale = distance_scale_m(config.lidar)

    def frames(observation) -> np.ndarray:  # type: ignore[no-untyped-def]
        return encode_frame(observation.scan_m, observation.target_features(), scale)

    windows, _ = envs.reset(seed=9)
    np.testing.assert_array_equal(windows, reference.advance(frames(world.reset(seed=9))))
    actions = np.random.default_rng(1).integers(0, 3, size=(40, 5))
    ends = 0
    for row in actions:
        windows, _, terminated, truncated, info = envs.step(row)
        result = world.step(row)
        done = terminated | truncated
        if done.any():
            ends += int(done.sum())
            last = frames(result.next_observation)
            for i in np.flatnonzero(done):
                expected = np.concatenate([reference.frames[i, 1:], last[i : i + 1]])
                np.testing.assert_array_equal(info["final_obs"][i], expected)
            reference.restart(np.flatnonzero(done))
        np.testing.assert_array_equal(windows, reference.advance(frames(result.observation)))
        assert envs.observation_space.contains(windows)
    assert ends >= 5


def test_single_window_matches_the_vector_world_seeded_s_plus_i() -> None:
    single = EncodedWindow(NavEnv("obstacles-inertia"))
    envs = EncodedWindowVector(NavVectorEnv("obstacles-inertia", 3))
    window, _ = single.reset(seed=21)
    windows, _ = envs.reset(seed=20)
    for action in np.random.default_rng(2).integers(0, 3, size=30):
        np.testing.assert_array_equal(windows[1], window)
        window, _, terminated, truncated, _ = single.step(np.int64(action))
        windows, *_ = envs.step(np.full(3, action))
        if terminated or truncated:
            break
    assert single.observation_space == envs.single_observation_space


def test_encoded_window_passes_gymnasium_checker_and_is_rebuilt_from_its_spec() -> None:
    env = EncodedWindow(gym.make(env_id("obstacles-increment")), length=3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    # The one remark: the checker prefers an unwrapped env, and this one is a wrapper on purpose.
    assert [
        str(w.message) for w in caught if "different from the unwrapped" not in str(w.message)
    ] == []
    assert env.spec is not None
    assert env.spec.make().observation_space == env.observation_space


def test_window_length_is_checked() -> None:
    with pytest.raises(ConfigError, match="window length"):
        EncodedWindow(NavEnv(), length=0)


def test_rgb_array_draws_the_episode_so_far() -> None:
    env = gym.make(env_id("obstacles-inertia"), render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    for _ in range(5):
        env.step(Action.FORWARD)
    later = env.render()
    assert isinstance(first, np.ndarray) and isinstance(later, np.ndarray)
    assert first.dtype == np.uint8 and first.ndim == 3 and first.shape[2] == 3
    assert first.shape == later.shape
    assert (first != later).any()  # the robot and the obstacles moved
    env.reset(seed=0)
    np.testing.assert_array_equal(env.render(), first)  # a new episode starts a new picture


def _without_display(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)


def test_human_mode_without_a_display_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    _without_display(monkeypatch)
    with pytest.raises(ConfigError, match="render_mode 'human' needs a display"):
        gym.make(env_id("walls-inertia"), render_mode="human")
    assert NavEnv().metadata["render_modes"] == ["rgb_array"]


_HUMAN_WINDOW = """
import gymnasium as gym, numpy as np, sim.gym_env
shown = gym.make("qnav/ObstaclesInertia-v0", render_mode="human")
drawn = gym.make("qnav/ObstaclesInertia-v0", render_mode="rgb_array")
for env in (shown, drawn):
    env.reset(seed=4)
    for _ in range(3):
        env.step(0)
figure, image = shown.unwrapped._window
np.testing.assert_array_equal(image.get_array(), drawn.render())
print(type(figure.canvas).__name__)
shown.close()
"""


@pytest.mark.skipif(
    shutil.which("Xvfb") is None, reason="no Xvfb (apt-get install xvfb) to open a window on"
)
def test_human_mode_shows_each_step_in_a_window() -> None:
    server = subprocess.Popen(
        ["Xvfb", "-displayfd", "1", "-screen", "0", "800x600x24", "-nolisten", "tcp"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert server.stdout is not None
        display = server.stdout.readline().strip()  # written once the server accepts clients
        assert display, "Xvfb did not start"
        environment = {k: v for k, v in os.environ.items() if k != "MPLBACKEND"}
        result = subprocess.run(
            [sys.executable, "-c", _HUMAN_WINDOW],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env={**environment, "DISPLAY": f":{display}"},
            timeout=120,
            check=False,
        )
    finally:
        server.terminate()
        server.wait(timeout=30)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "FigureCanvasTkAgg"


def test_unknown_render_mode_names_the_setting() -> None:
    with pytest.raises(ConfigError, match="render_mode 'ansi'"):
        NavEnv(render_mode="ansi")


def test_render_before_reset_says_so() -> None:
    with pytest.raises(RuntimeError, match="before reset"):
        NavEnv(render_mode="rgb_array").render()
