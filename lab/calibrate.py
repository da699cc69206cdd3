"""The world against every number the paper gives: its Random rows, and what its agents reached.

A world is acceptable when, over many test episodes,
- a uniformly random agent lands within two standard errors of the paper's 200-episode Random
  row (success and collision) in each scenario: that pins the robot's size and the spawn law;
- the oracle planner that knows the obstacles' future reaches at least the paper's best
  recurrent seed in each obstacle scenario: what the paper's agents did must be possible here;
and the blind go-to-target controller and the share of layouts that are lost from the start
(every first action doomed) show how much room the world leaves above target seeking.
`qnav lab calibrate` prints the table; docs/simulator.md gives the choices it supports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from tqdm import tqdm

from qnav.lab.oracle import doomed_actions, run_oracle
from qnav.sim import paper
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalResult, EvalSettings, GoToTargetAgent, RandomAgent, evaluate
from qnav.sim.world import reset

PAPER_EPISODES = 200
"""Test episodes behind each of the paper's figures."""


def paper_standard_error(fraction: float) -> float:
    """Binomial sampling error of a fraction the paper measured over 200 episodes."""
    return math.sqrt(max(fraction * (1 - fraction), 1e-12) / PAPER_EPISODES)


def doomed_at_start(config: WorldConfig, settings: EvalSettings, progress: bool = False) -> float:
    """Share of the test layouts where every first action is doomed (`lab.oracle`): lost before
    the robot moves, whatever it does."""
    lost = 0
    batches = np.array_split(
        np.arange(settings.episodes), -(-settings.episodes // settings.num_worlds)
    )
    for batch in tqdm(batches, desc=f"doomed {config.name}", disable=not progress):
        state = reset(config, np.full(batch.size, settings.seed), batch)
        lost += int(doomed_actions(config, state).all(axis=1).sum())
    return lost / settings.episodes


@dataclass(frozen=True)
class Calibration:
    """One scenario measured against the paper."""

    scenario: str
    """Scenario name."""
    random: EvalResult
    """A uniformly random action at every step."""
    goto: EvalResult
    """The go-to-target controller, blind to obstacles."""
    oracle: EvalResult | None
    """The planner that knows the obstacles' future (obstacle scenarios)."""
    doomed_at_start: float | None
    """Share of layouts lost from the start (obstacle scenarios)."""

    def random_within_two_errors(self) -> bool:
        """Random success and collision each within two of the paper's standard errors."""
        theirs = paper.RANDOM[self.scenario]
        return all(
            abs(ours - expected) <= 2 * paper_standard_error(expected)
            for ours, expected in (
                (self.random.success, theirs.success),
                (self.random.collision, theirs.collision),
            )
        )

    def oracle_reaches_best_seed(self) -> bool | None:
        """The planner reaches the paper's best recurrent seed (None without a planner run)."""
        if self.oracle is None:
            return None
        return self.oracle.success >= paper.RECURRENT_BEST[self.scenario].success

    def as_dict(self) -> dict[str, object]:
        """The row as `qnav lab calibrate --json` prints it (fractions without the mean length)."""

        return {
            "scenario": self.scenario,
            "random": self.random.fractions(),
            "go_to_target": self.goto.fractions(),
            "oracle": None if self.oracle is None else self.oracle.fractions(),
            "doomed_at_start": self.doomed_at_start,
            "random_within_two_errors": self.random_within_two_errors(),
            "oracle_reaches_best_seed": self.oracle_reaches_best_seed(),
        }


def calibrate(
    worlds: dict[str, WorldConfig],
    *,
    episodes: int,
    oracle_episodes: int,
    seed: int,
    progress: bool = False,
) -> list[Calibration]:
    """Random, go-to-target and (where obstacles move) oracle and doomed share, per scenario."""
    rows = []
    for name, world in worlds.items():
        # Up to 250 worlds side by side; fewer episodes than that run as many worlds as episodes.
        worlds_at_once = min(250, episodes)
        settings = EvalSettings(episodes=episodes, num_worlds=worlds_at_once, seed=seed)
        random = evaluate(world, RandomAgent(worlds_at_once, seed=seed), settings, progress)
        goto = evaluate(world, GoToTargetAgent(), settings, progress)
        oracle = doomed = None
        if world.obstacles.count and oracle_episodes:
            planner_settings = replace(
                settings, episodes=oracle_episodes, num_worlds=min(50, oracle_episodes)
            )
            oracle = run_oracle(world, planner_settings, progress=progress)
            doomed = doomed_at_start(world, planner_settings, progress)
        rows.append(Calibration(name, random, goto, oracle, doomed))
    return rows


def table(rows: list[Calibration]) -> str:
    """The calibration as a Markdown table, the paper's rows beside ours."""
    lines = [
        "| table | scenario | random (paper) | random | within 2 SE | go-to-target | oracle "
        "| doomed at start | paper recurrent mean / best | oracle >= best |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        theirs = paper.RANDOM[row.scenario]
        mean, best = paper.RECURRENT[row.scenario][0], paper.RECURRENT_BEST[row.scenario]
        oracle = "-" if row.oracle is None else f"{row.oracle.success:.3f}"
        doomed = "-" if row.doomed_at_start is None else f"{row.doomed_at_start:.3f}"
        reaches = {None: "-", True: "yes", False: "**no**"}[row.oracle_reaches_best_seed()]
        lines.append(
            f"| {paper.TABLES[row.scenario]} | {row.scenario} "
            f"| {theirs.success:.3f} / {theirs.collision:.3f} "
            f"| {row.random.success:.3f} / {row.random.collision:.3f} "
            f"| {'yes' if row.random_within_two_errors() else '**no**'} "
            f"| {row.goto.success:.3f} | {oracle} | {doomed} "
            f"| {mean.success:.3f} / {best.success:.3f} | {reaches} |"
        )
    return "\n".join(lines)
