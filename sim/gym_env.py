"""Gymnasium faces of the simulator: one world as a `gymnasium.Env`, N worlds as a `VectorEnv`,
registered ids, and the paper's window of k encoded frames as a finite Box.

Observations are in physical units: `scan` in metres and `target` = (distance m, sin, cos of
bearing). Every bound is finite, so checkers and libraries that reject infinities (SB3's
`check_env`) accept them: a beam with no return reads as the lidar's maximum range, which is what
`contracts.observation.encode_scan` turns +inf into for the policy anyway, so the policy's input
is the same whichever of the two a driver reports. The pose, the exact clearance, the outcome and,
at an episode's end, `is_success` are in `info`.

Importing this module registers one id per scenario: `gymnasium.make("qnav/WallsInertia-v0")`
(or, without importing it first, `gymnasium.make("qnav.sim.gym_env:qnav/WallsInertia-v0")`).
"""

from __future__ import annotations

import math
import os
import sys
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space
from numpy.typing import NDArray

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import IncrementDynamics, Outcome
from qnav.contracts.observation import (
    TARGET_FEATURES,
    WINDOW_LENGTH,
    FrameWindow,
    distance_scale_m,
    encode_frame,
)
from qnav.sim.config import SCENARIOS, WorldConfig, scenario
from qnav.sim.render import EpisodeCanvas, EpisodeRecorder
from qnav.sim.world import (
    BatchedWorld,
    Observation,
    Transition,
    observe,
    reset,
    step,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure
    from matplotlib.image import AxesImage

ObsDict = dict[str, NDArray[Any]]

NAMESPACE = "qnav"
"""The namespace of the registered ids: `qnav/<Scenario>-v0`."""

RENDER_MODES = ("rgb_array", "human")
"""What `render_mode` accepts; "human" only where a display exists."""


def env_id(scenario_name: str) -> str:
    """The registered id of a scenario: "obstacles-inertia" -> "qnav/ObstaclesInertia-v0"."""
    camel = "".join(part.capitalize() for part in scenario_name.split("-"))
    return f"{NAMESPACE}/{camel}-v0"


def max_step_m(config: WorldConfig) -> float:
    """The farthest the robot moves in one control period."""
    if isinstance(config.dynamics, IncrementDynamics):
        return config.dynamics.forward_step_m
    # The speed relaxes from below towards its steady value, never past it.
    return config.dynamics.max_speed_mps * config.control_period_s


def max_target_distance_m(config: WorldConfig) -> float:
    """An upper bound on the target distance: the target lies in the arena, and the robot starts
    every step inside it (a step that leaves it collides and ends the episode, as long as the
    openings are narrower than the robot, as in every scenario), so both are within the arena
    grown by one step."""
    return math.sqrt(2.0) * (config.arena.size_m + max_step_m(config))


def observation_space(config: WorldConfig) -> spaces.Dict:
    """The space of one world's observation (finite bounds)."""
    target = spaces.Box(
        low=np.array([0.0, -1.0, -1.0], dtype=np.float32),
        high=np.array([max_target_distance_m(config), 1.0, 1.0], dtype=np.float32),
        dtype=np.float32,
    )
    members: dict[str, spaces.Space[Any]] = {"target": target}
    if config.lidar is not None:
        members["scan"] = spaces.Box(
            0.0, config.lidar.max_range_m, shape=(config.lidar.num_beams,), dtype=np.float32
        )
    return spaces.Dict(members)


def as_dict(config: WorldConfig, observation: Observation) -> ObsDict:
    """The gymnasium observation (rows of N worlds) of the simulator's: no return (+inf) reads as
    the lidar's maximum range."""
    values: ObsDict = {"target": observation.target_features().astype(np.float32)}
    if observation.scan_m is not None and config.lidar is not None:
        values["scan"] = np.fmin(observation.scan_m, np.float32(config.lidar.max_range_m))
    return values


def _info(observation: Observation, transition: Transition | None) -> dict[str, Any]:
    info: dict[str, Any] = {"pose": observation.pose, "clearance_m": observation.clearance_m}
    if transition is not None:
        info["outcome"] = transition.outcome
    return info


def _config(world: str | WorldConfig) -> WorldConfig:
    return scenario(world) if isinstance(world, str) else world


def display_available() -> bool:
    """Whether a window can be opened: always on macOS and Windows, else with X11 or Wayland."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def render_modes_here() -> list[str]:
    """The render modes this machine supports."""
    return list(RENDER_MODES) if display_available() else ["rgb_array"]


def _check_render_mode(render_mode: str | None) -> None:
    if render_mode is None:
        return
    if render_mode not in RENDER_MODES:
        raise ConfigError(f"render_mode {render_mode!r}: choose one of {RENDER_MODES} or None")
    if render_mode == "human" and not display_available():
        raise ConfigError(
            "render_mode 'human' needs a display (neither DISPLAY nor WAYLAND_DISPLAY is set): "
            "use render_mode='rgb_array' and save or show the frames yourself"
        )
    if render_mode == "human":
        _check_interactive_backend()


def _check_interactive_backend() -> None:
    """A display is not enough: matplotlib falls back to drawing off screen without a GUI
    toolkit (tkinter, Qt, GTK), and the window would silently never open."""
    import matplotlib
    import matplotlib.pyplot  # settles the backend: a GUI one where a toolkit and display exist
    from matplotlib.backends.registry import BackendFilter, backend_registry

    backend = str(matplotlib.get_backend()).lower()
    interactive = backend_registry.list_builtin(BackendFilter.INTERACTIVE)  # type: ignore[no-untyped-call]
    if backend not in interactive:
        raise ConfigError(
            f"render_mode 'human' needs an interactive matplotlib backend, not {backend!r}: "
            "install a GUI toolkit (python3-tk) or set MPLBACKEND, or use render_mode='rgb_array'"
        )


class NavEnv(gym.Env[ObsDict, np.int64]):
    """One world. `reset(seed=s)` starts episode 0 of seed s; later resets continue with 1, 2, ...

    World i of `NavVectorEnv(seed=s)` runs exactly the episodes of `NavEnv` reset with seed s + i.
    `render_mode="rgb_array"` returns the picture `sim.render` draws of the episode so far;
    "human" shows it in a window (matplotlib) after every step.
    """

    metadata: dict[str, Any] = {"render_modes": list(RENDER_MODES), "render_fps": 5}  # noqa: RUF012 - gymnasium's convention

    def __init__(
        self, world: str | WorldConfig = "walls-inertia", render_mode: str | None = None
    ) -> None:
        self.config = _config(world)
        _check_render_mode(render_mode)
        self.render_mode = render_mode
        # Per instance: the modes this machine can show, at the simulator's own pace.
        self.metadata = {
            "render_modes": render_modes_here(),
            "render_fps": 1.0 / self.config.control_period_s,
        }
        self.observation_space = observation_space(self.config)  # type: ignore[assignment]
        self.action_space = spaces.Discrete(NUM_ACTIONS)
        self._seed: int | None = None
        self._episode = 0
        self._state = reset(self.config, np.zeros(1, np.int64), np.zeros(1, np.int64))
        self._recorder: EpisodeRecorder | None = None  # kept only to draw the episode
        self._canvas: EpisodeCanvas | None = None
        self._window: tuple[Figure, AxesImage] | None = None  # the 'human' mode's figure
        if render_mode is not None:
            self._canvas = EpisodeCanvas()  # fails here, with the install hint, without `viz`

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
        if self.render_mode is not None:
            self._recorder = EpisodeRecorder(self._state, observation)
        if self._canvas is not None:
            self._canvas.restart()
        if self.render_mode == "human":
            self._show()
        return _single(as_dict(self.config, observation)), _single(_info(observation, None))

    def step(self, action: np.int64) -> tuple[ObsDict, float, bool, bool, dict[str, Any]]:
        self._state, observation, transition = step(
            self.config, self._state, np.array([int(action)], dtype=np.int64)
        )
        if self._recorder is not None:
            self._recorder.add(self._state, observation, transition, int(action))
        info = _single(_info(observation, transition))
        result = Outcome(int(info["outcome"]))
        info["outcome"] = result.name.lower()
        terminated, truncated = bool(transition.terminated[0]), bool(transition.truncated[0])
        if terminated or truncated:
            info["is_success"] = result is Outcome.SUCCESS
        if self.render_mode == "human":
            self._show()
        return (
            _single(as_dict(self.config, observation)),
            float(transition.reward[0]),
            terminated,
            truncated,
            info,
        )

    def render(self) -> NDArray[np.uint8] | None:
        """The episode so far as an (H, W, 3) picture ("rgb_array"), or shown in a window."""
        if self.render_mode is None:
            gym.logger.warn("render() without a render_mode: pass render_mode='rgb_array'")
            return None
        if self.render_mode == "human":
            self._show()
            return None
        return self._picture()

    def _picture(self) -> NDArray[np.uint8]:
        if self._canvas is None or self._recorder is None:
            raise RuntimeError("render() before reset(): there is no episode to draw yet")
        return self._canvas.draw(self._recorder.record(self.config))

    def _show(self) -> None:
        import matplotlib.pyplot as plt

        picture = self._picture()
        if self._window is None or not plt.fignum_exists(self._window[0].number):
            figure, axes = plt.subplots()
            axes.set_axis_off()
            figure.subplots_adjust(left=0, right=1, bottom=0, top=1)
            self._window = (figure, axes.imshow(picture))
            plt.show(block=False)
        else:
            self._window[1].set_data(picture)
        plt.pause(1.0 / float(self.metadata["render_fps"]))

    def close(self) -> None:
        if self._window is not None:
            import matplotlib.pyplot as plt

            plt.close(self._window[0])
            self._window = None


def _single(values: dict[str, Any]) -> dict[str, Any]:
    return {key: value[0] for key, value in values.items()}


class NavVectorEnv(VectorEnv[ObsDict, NDArray[np.int64], NDArray[Any]]):
    """N worlds stepped as one array program, resetting in the same step an episode ends.

    Where an episode ended, the returned observation starts the next episode,
    `info["final_obs"]` holds the observations the step led to (one row per world, meaningful
    where `info["_final_obs"]`), and `info["is_success"]` whether it ended at the target (where
    `info["_is_success"]`): gymnasium's SAME_STEP mode.
    """

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.SAME_STEP}  # noqa: RUF012

    def __init__(
        self, world: str | WorldConfig = "walls-inertia", num_envs: int = 16, seed: int = 0
    ) -> None:
        self.config = _config(world)
        self.num_envs = num_envs
        self.world = BatchedWorld(self.config, num_envs, seed)
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
        return as_dict(self.config, observation), _info(observation, None)

    def step(
        self, actions: NDArray[np.int64]
    ) -> tuple[ObsDict, NDArray[Any], NDArray[Any], NDArray[Any], dict[str, Any]]:
        result = self.world.step(np.asarray(actions, dtype=np.int64))
        transition = result.transition
        info = _info(result.next_observation, transition)
        done = transition.terminated | transition.truncated
        if done.any():
            info["final_obs"] = as_dict(self.config, result.next_observation)
            info["_final_obs"] = done
            info["is_success"] = transition.outcome == Outcome.SUCCESS
            info["_is_success"] = done
        return (
            as_dict(self.config, result.observation),
            transition.reward,
            transition.terminated,
            transition.truncated,
            info,
        )


# The paper's network input: a window of k encoded frames.


def frame_size(config: WorldConfig) -> int:
    """Values per encoded frame: the beams, then the target's three features."""
    return (config.lidar.num_beams if config.lidar else 0) + TARGET_FEATURES


def window_space(config: WorldConfig, length: int = WINDOW_LENGTH) -> spaces.Box:
    """The space of one window (k, F) of encoded frames: scan in [0, 1], target distance over the
    lidar's range, sin and cos in [-1, 1]."""
    scale_m = distance_scale_m(config.lidar)
    beams = frame_size(config) - TARGET_FEATURES
    low = np.concatenate([np.zeros(beams), [0.0, -1.0, -1.0]]).astype(np.float32)
    high = np.concatenate([np.ones(beams), [max_target_distance_m(config) / scale_m, 1.0, 1.0]])
    return spaces.Box(
        low=np.tile(low, (length, 1)),
        high=np.tile(high.astype(np.float32), (length, 1)),
        dtype=np.float32,
    )


def encode(config: WorldConfig, observation: ObsDict) -> NDArray[np.float32]:
    """Frames (..., F) of gymnasium observations, by the policy's own `encode_frame`."""
    return encode_frame(
        observation.get("scan"), observation["target"], distance_scale_m(config.lidar)
    )


def _check_window(length: int) -> None:
    if length < 1:
        raise ConfigError(f"window length = {length} is out of range: allowed [1, inf)")


# gymnasium types a wrapper's inner env with the wrapper's own observation type, hence Any.
class EncodedWindow(gym.Wrapper[Any, np.int64, ObsDict, np.int64], gym.utils.RecordConstructorArgs):
    """A `NavEnv` seen as the paper's network sees it: the last k encoded frames (k, F), oldest
    first, the first frame repeated at an episode's start (`contracts.observation.FrameWindow`)."""

    def __init__(self, env: gym.Env[ObsDict, np.int64], length: int = WINDOW_LENGTH) -> None:
        # Recorded in the env's spec, so `env.spec.make()` rebuilds the same window.
        gym.utils.RecordConstructorArgs.__init__(self, length=length)
        gym.Wrapper.__init__(self, env)
        _check_window(length)
        config: WorldConfig = env.unwrapped.config  # type: ignore[attr-defined]
        self.config = config
        self.observation_space = window_space(config, length)
        self._window = FrameWindow(1, frame_size(config), length)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        observation, info = self.env.reset(seed=seed, options=options)
        self._window.restart()
        return self._advance(observation), info

    def step(
        self, action: np.int64
    ) -> tuple[NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        observation, reward, terminated, truncated, info = self.env.step(action)
        return self._advance(observation), float(reward), terminated, truncated, info

    def _advance(self, observation: ObsDict) -> NDArray[np.float32]:
        frame = encode(self.config, observation)[None, :]
        window: NDArray[np.float32] = self._window.advance(frame)[0].copy()
        return window


class EncodedWindowVector(VectorWrapper):
    """`EncodedWindow` over N worlds of a `NavVectorEnv`: windows (N, k, F), and in
    `info["final_obs"]` the window each ended episode's last step led to."""

    def __init__(self, env: NavVectorEnv, length: int = WINDOW_LENGTH) -> None:
        super().__init__(env)
        _check_window(length)
        self.config = env.config
        self.single_observation_space = window_space(env.config, length)
        self.observation_space = batch_space(self.single_observation_space, env.num_envs)
        self._window = FrameWindow(env.num_envs, frame_size(env.config), length)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        observation, info = self.env.reset(seed=seed, options=options)
        self._window.restart()
        return self._window.advance(encode(self.config, observation)).copy(), info

    def step(
        self, actions: NDArray[Any]
    ) -> tuple[NDArray[np.float32], NDArray[Any], NDArray[Any], NDArray[Any], dict[str, Any]]:
        observation, reward, terminated, truncated, info = self.env.step(actions)
        if "final_obs" in info:
            done = info["_final_obs"]
            last = encode(self.config, info["final_obs"])
            info = {
                **info,
                "final_obs": np.concatenate([self._window.frames[:, 1:], last[:, None, :]], axis=1),
            }
            self._window.restart(np.flatnonzero(done))
        windows = self._window.advance(encode(self.config, observation)).copy()
        return windows, reward, terminated, truncated, info


def register_envs() -> None:
    """Register `qnav/<Scenario>-v0` for every scenario (once; later calls change nothing).

    `gymnasium.make(id)` gives a `NavEnv`, `gymnasium.make_vec(id, n, vectorization_mode=
    "vector_entry_point")` a `NavVectorEnv`. The env truncates at the scenario's own step limit,
    so no TimeLimit is registered on top.
    """
    for name in SCENARIOS:
        if env_id(name) in gym.registry:
            continue
        gym.register(
            id=env_id(name),
            entry_point=_make_env,
            vector_entry_point=_make_vector_env,
            kwargs={"world": name},
        )


def _make_env(**kwargs: Any) -> NavEnv:
    return NavEnv(**kwargs)


def _make_vector_env(**kwargs: Any) -> NavVectorEnv:
    return NavVectorEnv(**kwargs)


register_envs()
