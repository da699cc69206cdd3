"""The decisive-state gauge: does a policy pick a safe action where the choice matters?

Most decisions in an obstacle world do not matter: every action is safe, or none is. A state
is *decisive* when some first action is doomed (every continuation the oracle planner knows
collides within `lab.oracle.DOOM_HORIZON_S`) and another is not. A policy that only seeks the
target passes the ordinary states and fails exactly these, so test success over a few hundred
episodes hears about them only through noise; the share of a fixed set of decisive states where
a policy's greedy action is safe measures them directly, in seconds.

The set is collected once from seeded episodes driven by the planner (states a good policy
visits) and by the blind go-to-target controller (states where target seeking runs into
obstacles, as today's learners do), each kept with the window of encoded frames the policy
would have seen there. `qnav lab gauge` builds and caches it; `qnav lab diagnose RUN` and training
progress report it.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from qnav.contracts.observation import (
    FrameWindow,
    distance_scale_m,
)
from qnav.contracts.settings import check_range, to_toml
from qnav.lab.oracle import OracleDriver, StateError, collision_shares, doomed_actions, with_error
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import go_to_target
from qnav.sim.world import (
    Observation,
    WorldState,
    concatenate_rows,
    observe,
    reset,
    step,
    take_rows,
)

StateAct = Callable[[WorldState, Observation], NDArray[np.int64]]


@dataclass(frozen=True)
class GaugeSettings:
    """Which episodes the decisive states are collected from."""

    SECTION = "gauge"

    episodes_per_driver: int = 400
    """Episodes driven by each of the planner and the go-to-target controller."""
    max_episode_steps: int = 200
    """Steps of each collecting episode at most (the training episodes' length)."""
    num_worlds: int = 100
    """Episodes driven together."""
    seed: int = 31_337
    """Seed of the layouts (apart from training's, validation's and the test's)."""
    window: int = 5
    """Frames per window (the paper's k)."""
    ordinary_share: float = 0.0
    """Share of the other states (every action safe, or every one doomed) kept as well, drawn
    from the seed: the gauge keeps none."""

    def __post_init__(self) -> None:
        check_range(self, "episodes_per_driver", self.episodes_per_driver, 1, 10**7)
        check_range(self, "max_episode_steps", self.max_episode_steps, 1, 10**7)
        check_range(self, "num_worlds", self.num_worlds, 1, 100_000)
        check_range(self, "window", self.window, 1, 1000)
        check_range(self, "ordinary_share", self.ordinary_share, 0.0, 1.0)


DRIVERS = ("planner", "go-to-target", "a run's stored path")
"""Who drove the episodes a state comes from, by `DecisiveStates.driver` index (the last:
a training run's own episodes among re-drawn obstacles, drawn by the retired `lab.redrawn`)."""


class DecisiveStates(NamedTuple):
    """States where some action is doomed and another is not, with what a policy sees there
    (and, where `GaugeSettings.ordinary_share` asks, some where none or all are)."""

    windows: NDArray[np.float32]
    """(K, k, F) the last k encoded frames (scan and target features), oldest first."""
    collide_share: NDArray[np.float32]
    """(K, A) the share of the planner's continuations after each action that collide (1 where
    doomed): how close to doom each action is."""
    world: WorldState
    """The true state of the world there, one row per state (for probes given exact state)."""
    driver: NDArray[np.int8]
    """(K,) index into `DRIVERS` of who drove to this state."""
    taken: NDArray[np.int8]
    """(K,) the action that driver took there: the only one whose outcome its own experience
    shows."""
    visited: NDArray[np.int64]
    """(len(DRIVERS),) states visited by each driver, decisive or not."""

    @property
    def doomed(self) -> NDArray[np.bool_]:
        """(K, A) the actions that are doomed there (every continuation collides)."""
        return np.asarray(self.collide_share == 1.0)

    def save(self, path: Path) -> None:
        """Write to an .npz file (atomically)."""
        save_with_world(path, self._asdict())

    @classmethod
    def load(cls, path: Path) -> DecisiveStates:
        """Read what `save` wrote."""
        return cls(**load_with_world(path))

    def policy_windows(self) -> NDArray[np.float32]:
        """(K, k, F) the windows a network sees."""
        return self.windows

    def subset(self, keep: NDArray[np.bool_] | NDArray[np.intp]) -> DecisiveStates:
        """The states `keep` selects (a mask or indices), with the visit counts unchanged."""
        return self._replace(
            windows=self.windows[keep],
            collide_share=self.collide_share[keep],
            world=take_rows(self.world, np.arange(len(self.doomed))[keep]),
            driver=self.driver[keep],
            taken=self.taken[keep],
        )


def save_with_world(path: Path, fields: dict[str, Any]) -> None:
    """Write arrays by name, one of them (`world`) a `WorldState`, to an .npz file atomically: a
    run killed while writing leaves the old file or the new one, never half of one."""
    arrays = {name: value for name, value in fields.items() if name != "world"}
    world = fields["world"]._asdict().items()
    arrays.update({f"world_{name}": value for name, value in world if value is not None})
    partial = path.with_suffix(".partial.npz")
    np.savez_compressed(partial, **arrays)
    partial.replace(path)


def load_with_world(path: Path) -> dict[str, Any]:
    """The arrays `save_with_world` wrote, by name, `world` a `WorldState` again (a field it
    left out, being None, None again)."""
    with np.load(path) as data:
        fields: dict[str, Any] = {
            name: data[name] for name in data.files if not name.startswith("world_")
        }
        world = {
            name[len("world_") :]: data[name] for name in data.files if name.startswith("world_")
        }
        fields["world"] = WorldState(**world)
    return fields


def collect(config: WorldConfig, settings: GaugeSettings, progress: bool = False) -> DecisiveStates:
    """Drive the settings' episodes with the planner and with go-to-target, keeping every
    decisive state visited and its window (and `settings.ordinary_share` of the others)."""
    planner = OracleDriver(config, seed=settings.seed)
    drivers: list[StateAct] = [
        lambda state, _: planner.act(state),
        lambda _, observation: go_to_target(observation.target_features()),
    ]
    parts = []
    visited = []
    for index, act in enumerate(drivers):
        *found, seen = _drive_and_keep(config, settings, act, index, progress)
        parts.append(found)
        visited.append(seen)
    windows, share, world, driver, taken = zip(*parts, strict=True)
    collide_share = np.concatenate(share)
    return DecisiveStates(
        windows=np.concatenate(windows),
        collide_share=collide_share,
        world=concatenate_rows(world),
        driver=np.concatenate(driver),
        taken=np.concatenate(taken),
        visited=np.array(visited + [0] * (len(DRIVERS) - len(visited)), dtype=np.int64),
    )


_FORMAT = "6"
"""Version of the cached file's layout (2: collision shares and world states kept; 3: the
obstacles' windows; 4: the action taken; 5: a world state's None fields left out, which 4 wrote
as arrays it could not read back; 6: no obstacle windows, for networks given obstacle inputs
(retired))."""


def cache_dir() -> Path:
    """Where collected state sets are kept: `$QNAV_CACHE`, else `$XDG_CACHE_HOME/qnav`, else
    `~/.cache/qnav`; each file is named by a hash of the world's and the gauge's settings."""
    if "QNAV_CACHE" in os.environ:
        return Path(os.environ["QNAV_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "qnav"


def cached(
    config: WorldConfig,
    settings: GaugeSettings = GaugeSettings(),
    progress: bool = False,
    directory: Path | None = None,
) -> DecisiveStates:
    """The decisive states of this world, collected once and then read from the cache (about
    a minute of CPU for the default 800 episodes; a changed setting makes a new set)."""
    # The world's own episode length plays no part: the settings' governs collection.
    config = replace(config, max_episode_steps=settings.max_episode_steps)
    key = hashlib.sha256((_FORMAT + to_toml(config) + to_toml(settings)).encode()).hexdigest()[:16]
    path = (directory or cache_dir()) / "decisive" / f"{config.name}-{key}.npz"
    if path.exists():
        return DecisiveStates.load(path)
    states = collect(config, settings, progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    states.save(path)
    return states


def _drive_and_keep(
    config: WorldConfig,
    settings: GaugeSettings,
    act: StateAct,
    index: int,
    progress: bool,
) -> tuple[
    NDArray[np.float32],
    NDArray[np.float32],
    WorldState,
    NDArray[np.int8],
    NDArray[np.int8],
    int,
]:
    max_range_m = distance_scale_m(config.lidar)
    plain = _frame_size(config)  # the scan and the target
    chance = np.random.default_rng([settings.seed, index])
    windows, shares, worlds, taken = [], [], [], []
    visited = 0
    episodes = np.arange(settings.episodes_per_driver, dtype=np.int64)
    batches = np.array_split(episodes, -(-episodes.size // settings.num_worlds))
    for batch in tqdm(batches, desc=f"gauge {DRIVERS[index]}", disable=not progress):
        state = reset(config, np.full(batch.size, settings.seed), batch)
        observation = observe(config, state)
        window = FrameWindow(batch.size, plain, settings.window)
        running = np.arange(batch.size)
        for _ in range(settings.max_episode_steps):
            frames = window.advance(observation.frames(max_range_m))
            share = collision_shares(config, state)
            keep = is_decisive(share == 1.0)
            if settings.ordinary_share:
                keep |= chance.random(keep.size) < settings.ordinary_share
            windows.append(frames[keep])
            shares.append(share[keep].astype(np.float32))
            worlds.append(take_rows(state, np.flatnonzero(keep)))
            actions = act(state, observation)
            taken.append(actions[keep].astype(np.int8))
            visited += running.size
            state, observation, transition = step(config, state, actions)
            going = np.flatnonzero(~(transition.terminated | transition.truncated))
            if going.size == 0:
                break
            running = running[going]
            state, observation = take_rows(state, going), take_rows(observation, going)
            window.frames = window.frames[going]
            window.fresh = window.fresh[going]
    count = sum(len(w) for w in windows)
    world = concatenate_rows(worlds)
    return (
        np.concatenate(windows),
        np.concatenate(shares),
        world,
        np.full(count, index, dtype=np.int8),
        np.concatenate(taken),
        visited,
    )


def _frame_size(config: WorldConfig) -> int:
    beams = config.lidar.num_beams if config.lidar is not None else 0
    return beams + 3


class GaugeResult(NamedTuple):
    """How often a policy picks a safe action in decisive states."""

    safe: float
    """Share of all decisive states where the chosen action is not doomed."""
    balanced: float
    """The safe share averaged over the doom patterns (which of the actions are doomed), each
    pattern weighted alike: a choice that ignores the scan (random, or always the same action)
    scores 1/2 here, whatever the mix of patterns, so only perception lifts it."""
    by_driver: dict[str, float]
    """The safe share over the states each driver visited."""
    states: int
    """Decisive states judged."""


def score(states: DecisiveStates, actions: NDArray[np.integer]) -> GaugeResult:
    """Judge one action per decisive state (a policy's greedy choices on `states.windows`)."""
    if actions.size == 0:
        return GaugeResult(math.nan, math.nan, {}, 0)
    safe = ~states.doomed[np.arange(actions.size), actions]
    return _result(states, safe.astype(np.float64))


def random_expectation(states: DecisiveStates) -> GaugeResult:
    """What a uniformly random choice scores on average (the share of safe actions)."""
    if len(states.doomed) == 0:
        return GaugeResult(math.nan, math.nan, {}, 0)
    return _result(states, (~states.doomed).mean(axis=1))


def constant_choice(states: DecisiveStates, action: int) -> GaugeResult:
    """What always taking one action scores: the gauge's plain share rewards a prior (in
    obstacles-inertia, always driving forward is safe in four decisive states of five)."""
    return score(states, np.full(len(states.doomed), action, dtype=np.int64))


def is_decisive(doomed: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """(K,) True where some action of a (K, A) doom table is doomed and another is not."""
    return np.asarray(doomed.any(axis=1) & ~doomed.all(axis=1))


def doom_patterns(doomed: NDArray[np.bool_]) -> NDArray[np.int64]:
    """(K,) each state's set of doomed actions as a bit mask (bit a set where action a is)."""
    return doomed.astype(np.int64) @ (1 << np.arange(doomed.shape[1], dtype=np.int64))


def _result(states: DecisiveStates, safe: NDArray[np.float64]) -> GaugeResult:
    by_driver = {
        name: float(safe[states.driver == i].mean())
        for i, name in enumerate(DRIVERS)
        if np.any(states.driver == i)
    }
    patterns = doom_patterns(states.doomed)
    balanced = np.mean([safe[patterns == p].mean() for p in np.unique(patterns)])
    return GaugeResult(float(safe.mean()), float(balanced), by_driver, len(safe))


def perception_ceiling(
    config: WorldConfig,
    states: DecisiveStates,
    error: StateError,
    draws: int = 16,
    seed: int = 0,
) -> GaugeResult:
    """What the best policy that knows the state only up to `error` scores: in each state it
    takes the action doomed least often over `draws` noisy copies of the true state (the
    Bayes choice). If this is near 1 for a perception error the window allows, the doom labels
    are learnable from what the policy sees, however knife-edged each label is."""
    random = np.random.default_rng(seed)
    doomed_count = np.zeros(states.doomed.shape)
    for _ in range(draws):
        doomed_count += doomed_actions(config, with_error(states.world, error, random))
    tie_break = random.random(doomed_count.shape) * 1e-3
    return score(states, np.argmin(doomed_count + tie_break, axis=1))


def go_to_target_choices(states: DecisiveStates) -> NDArray[np.int64]:
    """The blind go-to-target controller's choice in each state, from the newest frame's target
    features (sin and cos of the bearing are encoded as they are)."""
    return go_to_target(states.windows[:, -1, -3:])
