"""The paper's test protocol: run a fixed list of episodes and count how each one ended.

Episode g of an evaluation with seed s has the layout of (seed s, episode g), whichever world of
the batch runs it, so results do not depend on the batch size.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from qnav.contracts.actions import NUM_ACTIONS, Action
from qnav.contracts.motion import Outcome
from qnav.contracts.settings import check_range
from qnav.sim import rng
from qnav.sim.config import WorldConfig
from qnav.sim.world import Observation, WorldState, observe, reset, scatter, step, take_rows

TEST_EPISODE_STEPS = 500
"""Longest test episode of the paper's protocol."""

_ACTION_STREAM = 101


class Agent(Protocol):
    """Something that acts in a batch of worlds."""

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        """Episodes with these indices begin in these worlds: forget what came before there."""

    def act(self, observation: Observation) -> NDArray[np.int64]:
        """One action per world."""


class RandomAgent:
    """A uniformly random action at every step (the paper's Random rows).

    Its draws depend only on (seed, episode, step), like the worlds' layouts.
    """

    def __init__(self, num_worlds: int, seed: int = 0) -> None:
        self.seed = seed
        self.keys = np.zeros(num_worlds, dtype=np.uint64)
        self.steps = np.zeros(num_worlds, dtype=np.int64)

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        self.keys[worlds] = rng.episode_keys(np.full(worlds.size, self.seed), episodes)
        self.steps[worlds] = 0

    def act(self, observation: Observation) -> NDArray[np.int64]:
        draw = rng.uniform_at(self.keys, _ACTION_STREAM, self.steps)
        self.steps += 1
        return np.minimum((draw * NUM_ACTIONS).astype(np.int64), NUM_ACTIONS - 1)


GO_TO_TARGET_ALIGNED_COS = 0.97
"""`GoToTargetAgent` drives forward when the cosine of the target's bearing is at least this."""


class GoToTargetAgent:
    """A hand-written baseline: turn towards the target, drive when facing it; blind to obstacles.

    It shows what target seeking alone achieves in a world, so a learned agent can be judged
    against it.
    """

    def __init__(self, aligned_cos: float = GO_TO_TARGET_ALIGNED_COS) -> None:
        self.aligned_cos = aligned_cos

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        """No memory to reset."""

    def act(self, observation: Observation) -> NDArray[np.int64]:
        return go_to_target(observation.target_features(), self.aligned_cos)


def go_to_target(
    target_features: NDArray[np.floating], aligned_cos: float = GO_TO_TARGET_ALIGNED_COS
) -> NDArray[np.int64]:
    """`GoToTargetAgent`'s choice from (..., 3) target features (d_g, sin phi, cos phi): forward
    when cos phi >= aligned_cos, else a turn towards the target."""
    left, ahead = target_features[..., 1], target_features[..., 2]
    turn = np.where(left > 0, Action.LEFT, Action.RIGHT)
    return np.where(ahead >= aligned_cos, Action.FORWARD, turn).astype(np.int64)


class ExplorationHold:
    """Epsilon-greedy over a greedy choice, each random choice held for `hold_steps` steps.

    The paper explores this way in training (holding random choices for five steps); with
    `hold_steps` = 1 it is the test of a policy with a chance of a random action at every step.
    """

    def __init__(self, num_worlds: int, epsilon: float, hold_steps: int, seed: int = 0) -> None:
        self.epsilon = np.full(num_worlds, epsilon)
        self.hold_steps = hold_steps
        self.held_action = np.zeros(num_worlds, dtype=np.int64)
        self.held_for = np.zeros(num_worlds, dtype=np.int64)
        self.rng = np.random.default_rng(seed)

    def start(self, worlds: NDArray[np.intp]) -> None:
        """New episodes in these worlds: no random choice is held any more."""
        self.held_for[worlds] = 0

    def __call__(self, greedy: NDArray[np.int64]) -> NDArray[np.int64]:
        """The action of each world: the greedy one, or a random one drawn or held."""
        holding = self.held_for > 0
        draw = ~holding & (self.rng.random(greedy.size) < self.epsilon)
        self.held_action[draw] = self.rng.integers(0, NUM_ACTIONS, int(draw.sum()))
        self.held_for[draw] = self.hold_steps
        random = self.held_for > 0
        self.held_for[random] -= 1
        return np.where(random, self.held_action, greedy)


class WanderingGoToTarget:
    """Go-to-target with held random actions, the perception probes' drive (so that windows
    show turns and stops too): each world holds a random action, redrawn with probability
    `redraw_probability` each step, which replaces go-to-target's with probability
    `explore_share`."""

    def __init__(
        self, num_worlds: int, explore_share: float, seed: int, redraw_probability: float = 0.2
    ) -> None:
        self.explore_share = explore_share
        self.redraw_probability = redraw_probability
        self._chance = np.random.default_rng(seed)
        self._held = self._chance.integers(0, NUM_ACTIONS, num_worlds)

    def __call__(self, target_features: NDArray[np.floating]) -> NDArray[np.int64]:
        """(N,) each world's action from its (N, 3) target features."""
        worlds = self._held.size
        redraw = self._chance.random(worlds) < self.redraw_probability
        self._held = np.where(redraw, self._chance.integers(0, NUM_ACTIONS, worlds), self._held)
        explore = self._chance.random(worlds) < self.explore_share
        return np.asarray(np.where(explore, self._held, go_to_target(target_features)))


class StreamPolicy(Protocol):
    """A policy keeping one observation window per world (the onboard `PolicyRuntime`)."""

    def reset(self, streams: NDArray[np.intp] | None = None) -> None:
        """Episodes restart in these streams."""

    def step_batch(
        self, scan_m: NDArray[np.floating] | None, target_features: NDArray[np.floating]
    ) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
        """Push one observation per stream; greedy actions and Q values."""
        ...


class StreamPolicyAgent:
    """A `StreamPolicy` acting in a batch of worlds, optionally with random test actions."""

    def __init__(
        self, policy: StreamPolicy, num_worlds: int, epsilon: float = 0.0, seed: int = 0
    ) -> None:
        self.policy = policy
        self.exploration = ExplorationHold(num_worlds, epsilon, hold_steps=1, seed=seed)
        self.last_q = np.zeros((num_worlds, NUM_ACTIONS), dtype=np.float32)
        """The Q values of the last decision (for a shield that ranks actions by them)."""

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        self.policy.reset(worlds)
        self.exploration.start(worlds)

    def act(self, observation: Observation) -> NDArray[np.int64]:
        greedy, self.last_q = self.policy.step_batch(
            observation.scan_m, observation.target_features()
        )
        return self.exploration(greedy)


@dataclass(frozen=True)
class EvalSettings:
    """How to run the test protocol."""

    SECTION = "eval"

    episodes: int = 200
    """Test episodes (paper: 200; use 1000 or more to tell hundredths apart)."""
    max_episode_steps: int = TEST_EPISODE_STEPS
    """Steps before a test episode counts as unfinished (paper: 500)."""
    num_worlds: int = 64
    """Worlds stepped together."""
    seed: int = 12345
    """Seed of the test layouts; training uses other seeds."""

    def __post_init__(self) -> None:
        check_range(self, "episodes", self.episodes, 1, 10_000_000)
        check_range(self, "max_episode_steps", self.max_episode_steps, 1, 10_000_000)
        check_range(self, "num_worlds", self.num_worlds, 1, 100_000)


@dataclass(frozen=True)
class EvalResult:
    """Fractions of test episodes by outcome, as the paper's tables give them."""

    success: float
    """Fraction that reached the target."""
    collision: float
    """Fraction that ended in a collision."""
    unfinished: float
    """Fraction still running after the step limit."""
    episodes: int
    """Number of episodes."""
    mean_steps: float
    """Mean episode length in steps."""

    @classmethod
    def of_outcomes(cls, outcomes: NDArray[np.integer], steps: NDArray[np.integer]) -> EvalResult:
        """The fractions of each episode's `Outcome` (RUNNING: unfinished) and the mean of its
        steps."""
        return cls(
            success=float(np.mean(outcomes == Outcome.SUCCESS)),
            collision=float(np.mean(outcomes == Outcome.COLLISION)),
            unfinished=float(np.mean(outcomes == Outcome.RUNNING)),
            episodes=int(outcomes.size),
            mean_steps=float(np.mean(steps)),
        )

    def fractions(self) -> dict[str, float]:
        """Success, collision and unfinished shares and the episode count, as results files
        and `qnav eval --json` give them (without the mean length)."""
        return {k: v for k, v in asdict(self).items() if k != "mean_steps"}

    def standard_error(self, fraction: float) -> float:
        """Binomial sampling error of one of the fractions."""
        return math.sqrt(max(fraction * (1 - fraction), 1e-12) / self.episodes)


def evaluate(
    config: WorldConfig, agent: Agent, settings: EvalSettings, progress: bool = False
) -> EvalResult:
    """Run `settings.episodes` episodes and count outcomes."""
    return EvalResult.of_outcomes(*episode_outcomes(config, agent, settings, progress))


WorldWatch = Callable[[WorldState, NDArray[np.bool_]], None]
"""Shown the worlds' whole state before each of an agent's decisions, and which worlds still run
an episode that counts (the lab's audits label the states an agent drives into)."""


def episode_outcomes(
    config: WorldConfig,
    agent: Agent,
    settings: EvalSettings,
    progress: bool = False,
    watch: WorldWatch | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Run `settings.episodes` episodes: each one's `Outcome` and steps, by episode index (the
    same index is the same layout for every agent); `watch`, where given, sees each decision's
    state first."""
    config = replace(config, max_episode_steps=settings.max_episode_steps)
    worlds = min(settings.num_worlds, settings.episodes)
    episode = np.arange(worlds, dtype=np.int64)
    seed = np.full(worlds, settings.seed, dtype=np.int64)
    state = reset(config, seed, episode)
    observation = observe(config, state)
    agent.start(np.arange(worlds), episode)
    active = np.ones(worlds, dtype=bool)
    outcomes = np.full(settings.episodes, -1, dtype=np.int64)
    lengths = np.zeros(settings.episodes, dtype=np.int64)
    next_episode = worlds
    with tqdm(
        total=settings.episodes, desc=f"eval {config.name}", unit="ep", disable=not progress
    ) as bar:
        while active.any():
            if watch is not None:
                watch(state, active)
            state, next_observation, transition = step(config, state, agent.act(observation))
            observation = next_observation
            done = (transition.terminated | transition.truncated) & active
            if not done.any():
                continue
            index = np.flatnonzero(done)
            outcomes[episode[index]] = transition.outcome[index]
            lengths[episode[index]] = state.steps[index]
            bar.update(index.size)
            count = min(index.size, settings.episodes - next_episode)
            active[index[count:]] = False
            index = index[:count]
            if count:
                episode[index] = np.arange(next_episode, next_episode + count)
                next_episode += count
                fresh = reset(config, seed[index], episode[index])
                state = scatter(state, index, fresh)
                observation = scatter(observation, index, observe(config, fresh))
                agent.start(index, episode[index])
    return outcomes, lengths


StateAct = Callable[[WorldState, Observation], NDArray[np.int64]]
"""An action per world from the worlds' whole state (for agents that are not the robot's own:
the oracle planner, or a copy of it given the state)."""


def drive(
    config: WorldConfig,
    seed: int,
    episodes: NDArray[np.int64],
    act: StateAct,
    record: Callable[[WorldState, Observation, NDArray[np.int64]], None] | None = None,
) -> tuple[NDArray[np.int8], NDArray[np.int64]]:
    """Run the episodes (seed, e) for e in `episodes` together to their ends, `act` choosing
    every action, `record` shown each step's (state, observation, action) of the running
    worlds; each episode's outcome (RUNNING: cut at `config.max_episode_steps`) and steps."""
    state = reset(config, np.full(episodes.size, seed), episodes)
    observation = observe(config, state)
    running = np.arange(episodes.size)
    outcomes = np.full(episodes.size, Outcome.RUNNING, dtype=np.int8)
    steps = np.zeros(episodes.size, dtype=np.int64)
    while running.size:
        action = act(state, observation)
        if record is not None:
            record(state, observation, action)
        state, observation, transition = step(config, state, action)
        ended = transition.terminated | transition.truncated
        outcomes[running[ended]] = transition.outcome[ended]
        steps[running[ended]] = state.steps[ended]
        going = np.flatnonzero(~ended)
        running = running[going]
        state, observation = take_rows(state, going), take_rows(observation, going)
    return outcomes, steps
