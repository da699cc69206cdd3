"""BARN's test protocol in the simulator: one run per world, scored as the challenge scores it.

Every layout of a world's set is run once, in order (episode e in layout e, `LayoutConfig.order`
"cycle"), up to BARN's 100 s (500 steps of 0.2 s). A run ends in success (within the reach of
the goal), collision, or timeout; its time counts from the moment the robot has moved 0.1 m
(`run.py`), and BARN's metric divides the reference path's time at the robot's top speed by it
(`sim.barn.metric`). A run "loops" when it comes back within `LOOP_RADIUS_M` of a place it left
more than `LOOP_AWAY_M` behind at least `LOOP_AFTER_S` earlier: the circling of a robot that has
lost its way, which memory should prevent (the paper's claim for its recurrent agent).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import Outcome, action_velocities
from qnav.sim import barn
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import Agent, EvalSettings, episode_outcomes
from qnav.sim.layouts import Layouts, layouts_of
from qnav.sim.world import WorldState

F64 = NDArray[np.float64]

LOOP_RADIUS_M = 0.3
"""A loop returns within this of a place it was."""
LOOP_AWAY_M = 1.0
"""... after going at least this far from it ..."""
LOOP_AFTER_S = 10.0
"""... at least this long before."""

OUTCOMES = {Outcome.SUCCESS: "success", Outcome.COLLISION: "collision", Outcome.RUNNING: "timeout"}


@dataclass(frozen=True)
class WorldRun:
    """How the run in one world went."""

    world: int
    """The world's number in its set (BARN's world index)."""
    outcome: str
    """success, collision or timeout."""
    time_s: float
    """From the robot's first 0.1 m to the run's end."""
    metric: float
    """BARN's score of the run (0 unless it succeeded)."""
    loop: bool
    """The robot came back to a place it had left (`LOOP_*`)."""


@dataclass(frozen=True)
class BenchmarkResult:
    """A set of worlds run once each."""

    agent: str
    """What drove."""
    worlds: str
    """Which set of worlds."""
    success: float
    """Share of runs that reached the goal."""
    collision: float
    """Share that ended in a collision."""
    timeout: float
    """Share still going after the time limit."""
    metric: float
    """Mean of BARN's score over all runs."""
    loops: float
    """Share of runs that looped."""
    runs: tuple[WorldRun, ...]
    """Each world's run."""

    def summary(self) -> dict[str, float | str]:
        """Everything but the runs."""
        return {k: v for k, v in asdict(self).items() if k != "runs"}


def top_speed_mps(config: WorldConfig) -> float:
    """The robot's fastest forward speed (BARN's metric takes its time at that speed)."""
    return max(speed for speed, _ in action_velocities(config.dynamics, config.control_period_s))


def looped(path_xy: F64, period_s: float) -> bool:
    """Whether a path (T, 2) comes back within LOOP_RADIUS_M of a point it was at least
    LOOP_AFTER_S before, having been LOOP_AWAY_M or more from it in between."""
    gap = max(1, math.ceil(LOOP_AFTER_S / period_s))
    if path_xy.shape[0] <= gap:
        return False
    distance = np.linalg.norm(path_xy[:, None, :] - path_xy[None, :, :], axis=-1)
    # farthest[i, j]: the farthest the path got from point i between steps i and j.
    upper = np.triu(distance)
    farthest = np.maximum.accumulate(upper, axis=1)
    later = np.triu(np.ones_like(distance, dtype=bool), k=gap)
    return bool((later & (distance < LOOP_RADIUS_M) & (farthest >= LOOP_AWAY_M)).any())


class _PathRecorder:
    """Keeps each episode's path from the states shown before every decision."""

    def __init__(self) -> None:
        self.paths: dict[int, list[F64]] = {}

    def __call__(self, state: WorldState, active: NDArray[np.bool_]) -> None:
        for row in np.flatnonzero(active):
            self.paths.setdefault(int(state.episode[row]), []).append(state.pose[row, :2].copy())


def run_benchmark(
    config: WorldConfig, agent: Agent, label: str, num_worlds: int = 64, progress: bool = False
) -> BenchmarkResult:
    """Run `agent` once in each layout of `config` (in order) under BARN's protocol."""
    layouts = layouts_of(config.layout)
    if layouts is None:
        raise ValueError("a benchmark needs a world of layouts (layout.source)")
    config = replace(config, layout=replace(config.layout, order="cycle"))
    steps = math.ceil(barn.TIME_LIMIT_S / config.control_period_s)
    settings = EvalSettings(episodes=len(layouts), max_episode_steps=steps, num_worlds=num_worlds)
    recorder = _PathRecorder()
    outcomes, lengths = episode_outcomes(config, agent, settings, progress, watch=recorder)
    return score(
        config,
        layouts=layouts,
        label=label,
        outcomes=outcomes,
        lengths=lengths,
        paths=recorder.paths,
    )


def score(
    config: WorldConfig,
    *,
    layouts: Layouts,
    label: str,
    outcomes: NDArray[np.int64],
    lengths: NDArray[np.int64],
    paths: dict[int, list[F64]],
) -> BenchmarkResult:
    """The benchmark's result from each run's outcome, length in steps and path."""
    period = config.control_period_s
    runs = []
    for index in range(len(layouts)):
        path = np.array(paths.get(index, [layouts.start_pose[index, :2]]))
        moved = np.linalg.norm(path - layouts.start_pose[index, :2], axis=1) >= barn.MOVED_M
        started = int(np.argmax(moved)) if moved.any() else int(lengths[index])
        time_s = (int(lengths[index]) - started) * period
        success = outcomes[index] == Outcome.SUCCESS
        value = barn.metric(
            np.array([success]),
            np.array([time_s]),
            layouts.path_length_m[index : index + 1],
            top_speed_mps(config),
        )
        runs.append(
            WorldRun(
                world=int(layouts.world_id[index]),
                outcome=OUTCOMES[Outcome(int(outcomes[index]))],
                time_s=round(time_s, 3),
                metric=round(float(value[0]), 4),
                loop=looped(path, period),
            )
        )
    count = len(runs)
    return BenchmarkResult(
        agent=label,
        worlds=layouts.name,
        success=sum(r.outcome == "success" for r in runs) / count,
        collision=sum(r.outcome == "collision" for r in runs) / count,
        timeout=sum(r.outcome == "timeout" for r in runs) / count,
        metric=float(np.mean([r.metric for r in runs])),
        loops=sum(r.loop for r in runs) / count,
        runs=tuple(runs),
    )
