# Ad hoc measurement of issue 53, section 3 (2026-12-08): is 0.85 reachable where obstacles turn?
"""The ceiling of the turning rows: what a controller could reach that knew more than the
tracker tells it, on a row of `qnav lab robustness` (`lab.robustness.ROWS`), over the gauge's
episodes (`qnav lab forecast`: seed 12345, 500 steps, 64 worlds at a time).

Usage (from the repository's root): turning_ceiling.py ROW EPISODES AGENT [AGENT ...], e.g.
`OMP_NUM_THREADS=1 .venv/bin/python docs/log/scripts/turning_ceiling.py 6 100 clairvoyant:4
truth-shield:3:true` (records: docs/log/forecast-turning.md, "2026-12-08: the ceiling").

AGENT:
- "blind": go-to-target; "shipped": the committed policy as shipped (tracker, shield, proximity
  stop: `qnav.tracking.shipped_agent`).
- "clairvoyant:H[:R[:F]]": the simulator's oracle planner (`lab.oracle`: the structured and R
  random candidate sequences, 128 by default, drawn per (seed, episode, step), the best one's
  first action, H seconds ahead) among the obstacles' TRUE future: the world's own obstacle
  step (`sim.world._moved_obstacles`: the heading walk's draws are keyed by seed, episode,
  step and obstacle, and no obstacle reacts to the robot, so stepping the world's obstacles
  ahead replays exactly where they will be). With F, the truth is known only F seconds ahead,
  the obstacles going straight on from there (F = 0: straight lines from the true present).
- "truth-shield:H:TURN": the shipped controller (policy, shield, proximity stop) with the
  tracker replaced by the true present state (every obstacle's centre, velocity and radius,
  the robot's own velocity), the shield forecasting H seconds with futures whose heading walks
  TURN rad over one second (`lookahead.turn_std_rad`; "true" gives the row's own walk,
  heading_walk_rad * sqrt(1 / control_period_s)).
- "truth-plan:H": the same controller in plan mode (`lookahead.mode = "plan"`, straight lines
  from the true present state, H seconds).
- "truth-expect:H:K" / "truth-hindsight:H:K": a planner on the true present state among K
  futures drawn from the row's true heading walk (`controller.futures.walked_futures`, fresh
  draws each decision), every candidate sequence (the structured ones and 64 random) played in
  every future; "expect" takes the first action of the sequence with the best mean score over
  the futures (open loop: it cannot react later, so it is pessimistic), "hindsight" the first
  action whose best sequence in each future scores best on average (it reacts as if it knew
  each future after the first step, so it is hopeful). Neither is an exact bound; together
  they show roughly what a planner on a perfect present state can do.

Prints one line per agent: success, collision, unfinished, mean steps, overruled share, and the
run's wall time.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from qnav.contracts import lookahead as contract
from qnav.contracts.lookahead import ObstacleFutures, candidate_sequences, random_blocks_needed
from qnav.controller.futures import walked_futures
from qnav.controller.lookahead import Belief, Lookahead, LookaheadSettings
from qnav.controller.perception import TrackerSettings, Tracks
from qnav.lab.oracle import keyed_sequences, lookahead_model
from qnav.lab.robustness import ROWS, policy_agent, row_worlds
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalResult, EvalSettings, GoToTargetAgent, episode_outcomes
from qnav.sim.world import Observation, WorldState, _moved_obstacles
from qnav.tracking import LookaheadAgent, fitted_proximity, room_of, shipped_agent

F64 = NDArray[np.float64]
POLICY = Path("tests/data/stack/obstacles-inertia.onnx")


def true_future(
    world: WorldConfig, state: WorldState, steps: int, known: int | None = None
) -> ObstacleFutures:
    """The obstacles' true centres after each of the next `steps` periods, as one future (after
    the first `known`, where given, straight on from where the truth left them)."""
    straight = replace(world, obstacles=replace(world.obstacles, heading_walk_rad=0.0))
    xy = []
    for step in range(steps):
        ahead = world if known is None or step < known else straight
        moved, velocity, motion = _moved_obstacles(ahead, state)
        state = state._replace(
            obstacle_xy=moved,
            obstacle_velocity=velocity,
            obstacle_motion=motion,
            steps=state.steps + 1,
        )
        xy.append(moved)
    radius = np.full(state.obstacle_xy.shape[:2], world.obstacles.radius_m)
    return ObstacleFutures(np.stack(xy)[:, :, None], radius)


class Watched:
    """Keeps the world's state from `episode_outcomes`' watch, for agents that need it."""

    state: WorldState | None = None

    def watch(self, state: WorldState, counting: NDArray[np.bool_]) -> None:
        self.state = state


class Clairvoyant(Watched):
    """The oracle planner among the obstacles' true future."""

    def __init__(
        self, world: WorldConfig, seed: int, horizon: int, random: int, known: int | None
    ) -> None:
        self.world, self.seed, self.horizon, self.random = world, seed, horizon, random
        self.known = known
        self.model = lookahead_model(world)

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        """No memory."""

    def act(self, observation: Observation) -> NDArray[np.int64]:
        assert self.state is not None
        sequences = keyed_sequences(self.state, self.horizon, self.random, self.seed)
        futures = true_future(self.world, self.state, self.horizon, self.known)
        return contract.best_first_actions(self.model, self.state, sequences, futures)


class _TrueTracks:
    """Stands in for a car's tracker: its tracks are what the agent sets (the truth)."""

    def __init__(self) -> None:
        self.now = Tracks(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))

    def update(self, *args: object) -> Tracks:
        return self.now

    def tracks(self) -> Tracks:
        return self.now


class TrueLookahead(Lookahead):
    """The controller's look ahead believing the true present state."""

    own_velocity: F64 = np.zeros(2)

    def restart(self) -> None:
        super().restart()
        self.tracker = _TrueTracks()  # type: ignore[assignment]

    def belief(self, target_xy: F64) -> Belief:
        return super().belief(target_xy)._replace(velocity=self.own_velocity[None])


class TruthAgent(Watched, LookaheadAgent):
    """The shipped controller with the true present state in place of the tracker's."""

    def __init__(self, world: WorldConfig, worlds: int, lookahead: LookaheadSettings) -> None:
        LookaheadAgent.__init__(
            self,
            policy_agent(POLICY, world, worlds),
            world,
            worlds,
            tracker=TrackerSettings(),
            lookahead=lookahead,
            proximity=fitted_proximity(world),
        )
        assert world.lidar is not None
        self.cars = [
            TrueLookahead(
                room_of(world, lookahead),
                TrackerSettings(),
                dynamics=world.dynamics,
                robot_radius_m=world.robot_radius_m,
                control_period_s=world.control_period_s,
                beam_angles_rad=world.lidar.beam_angles_rad(),
            )
            for _ in range(worlds)
        ]

    def act(self, observation: Observation) -> NDArray[np.int64]:
        state = self.state
        assert state is not None
        radius = np.full(state.obstacle_xy.shape[1], self.world.obstacles.radius_m)
        for row, car in enumerate(self.cars):
            assert isinstance(car, TrueLookahead) and isinstance(car.tracker, _TrueTracks)
            car.tracker.now = Tracks(state.obstacle_xy[row], state.obstacle_velocity[row], radius)
            car.own_velocity = state.velocity[row]
        return LookaheadAgent.act(self, observation)


class FuturesPlanner(Watched):
    """A planner on the true present state among futures of the row's true heading walk."""

    def __init__(self, world: WorldConfig, horizon: int, futures: int, hindsight: bool) -> None:
        self.world, self.horizon, self.futures, self.hindsight = world, horizon, futures, hindsight
        self.model = lookahead_model(world)
        self.turn_step_rad = world.obstacles.heading_walk_rad
        self.random = np.random.default_rng(53)
        size = world.arena.size_m
        self.box = (np.zeros(2), np.full(2, size))

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        """No memory."""

    def act(self, observation: Observation) -> NDArray[np.int64]:
        state = self.state
        assert state is not None
        worlds, obstacles = state.obstacle_xy.shape[:2]
        blocks = self.random.integers(0, 3, (worlds, 64, random_blocks_needed(self.horizon)))
        sequences = candidate_sequences(blocks, self.horizon)  # (N, S, H)
        count = sequences.shape[1]
        draws = np.zeros((2, worlds, self.futures, obstacles, self.horizon))
        draws[0] = self.turn_step_rad * self.random.standard_normal(draws.shape[1:])
        radius = np.full((worlds, obstacles), self.world.obstacles.radius_m)
        futures = walked_futures(
            state.obstacle_xy,
            state.obstacle_velocity,
            radius,
            draws,
            period_s=self.world.control_period_s,
            box=self.box,
        )
        tiled = np.repeat(sequences, self.futures, axis=1)  # candidate s * K + k meets future k
        score = contract.simulate(self.model, state, tiled, futures).score
        score = score.reshape(worlds, count, self.futures)
        first = sequences[:, :, 0]  # (N, S)
        if not self.hindsight:
            best = score.mean(axis=2).argmax(axis=1)
            return np.asarray(first[np.arange(worlds), best], dtype=np.int64)
        value = np.stack(
            [np.where((first == a)[..., None], score, -np.inf).max(axis=1) for a in range(3)],
            axis=1,
        )  # (N, A, K): each first action's best sequence in each future
        return np.asarray(value.mean(axis=2).argmax(axis=1), dtype=np.int64)


def agent_of(name: str, world: WorldConfig, settings: EvalSettings) -> object:
    """The agent named `name` (module docstring) in `world`."""
    worlds = min(settings.num_worlds, settings.episodes)
    kind, *args = name.split(":")
    if kind == "blind":
        return GoToTargetAgent()
    if kind == "shipped":
        return shipped_agent(policy_agent(POLICY, world, worlds), world, worlds, seed=settings.seed)
    horizon_s = float(args[0])
    steps = max(1, round(horizon_s / world.control_period_s))
    if kind == "clairvoyant":
        random = int(args[1]) if len(args) > 1 else 128
        known = round(float(args[2]) / world.control_period_s) if len(args) > 2 else None
        return Clairvoyant(world, settings.seed, steps, random, known)
    if kind == "truth-plan":
        return TruthAgent(world, worlds, LookaheadSettings(mode="plan", plan_horizon_s=horizon_s))
    if kind == "truth-shield":
        true_turn = world.obstacles.heading_walk_rad / math.sqrt(world.control_period_s)
        turn = true_turn if args[1] == "true" else float(args[1])
        lookahead = LookaheadSettings(shield_horizon_s=horizon_s, turn_std_rad=turn)
        return TruthAgent(world, worlds, lookahead)
    if kind in ("truth-expect", "truth-hindsight"):
        return FuturesPlanner(world, steps, int(args[1]), kind == "truth-hindsight")
    raise SystemExit(f"unknown agent {name!r}")


def main() -> None:
    row, episodes = int(sys.argv[1]), int(sys.argv[2])
    world = replace(row_worlds(ROWS[row])[0])
    settings = EvalSettings(episodes=episodes, seed=12345)
    for name in sys.argv[3:]:
        agent = agent_of(name, world, settings)
        started = time.perf_counter()
        watch = agent.watch if isinstance(agent, Watched) else None
        outcomes, lengths = episode_outcomes(world, agent, settings, watch=watch)  # type: ignore[arg-type]
        result = EvalResult.of_outcomes(outcomes, lengths)
        overruled = agent.overruled_share if isinstance(agent, LookaheadAgent) else math.nan
        print(
            f"row {row} {name}: success {result.success:.3f} collision {result.collision:.3f} "
            f"unfinished {result.unfinished:.3f} steps {result.mean_steps:.1f} "
            f"overruled {overruled:.3f} ({time.perf_counter() - started:.0f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
