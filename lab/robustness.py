"""What a room that is not the simulator's does to the controller (issue 53): the test protocol
in the paper's obstacle world with one thing changed at a time, and in the realistic room with
everything changed, for the blind go-to-target controller, the policy alone and the policy as
the shipped controller runs it (the shield and the proximity stop: `qnav.tracking.shipped_agent`).

`qnav lab robustness` prints the table of docs/lookahead.md, "A room that is not the
simulator's"; `forward_collisions` counts what the proximity stop lets an always-forward driver
hit.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from qnav.contracts.motion import Outcome, action_velocities
from qnav.controller.policy import Expectation, PolicyRuntime
from qnav.controller.proximity import (
    ProximitySettings,
    allowed_actions,
    blocked_parts,
    field_ranges,
    guarded_action,
)
from qnav.sim.config import WorldConfig, changed_world, scenario
from qnav.sim.evaluate import (
    Agent,
    EvalResult,
    EvalSettings,
    GoToTargetAgent,
    StreamPolicyAgent,
    evaluate,
)
from qnav.sim.room import room_clearance
from qnav.sim.world import observe, reset, scatter, step
from qnav.tracking import fitted_proximity, shipped_agent


@dataclass(frozen=True)
class Row:
    """One row of the table: a world, changed by settings (one cell per variant)."""

    label: str
    """What the room does."""
    base: str
    """The scenario."""
    variants: tuple[tuple[str, ...], ...]
    """World settings (`--set` strings) of each variant, shown side by side in a cell."""


ROWS = (
    Row("as simulated", "obstacles-inertia", ((),)),
    Row(
        "range noise 3 cm / 5 cm / 10 cm",
        "obstacles-inertia",
        (
            ("sensor.range_noise_m=0.03",),
            ("sensor.range_noise_m=0.05",),
            ("sensor.range_noise_m=0.1",),
        ),
    ),
    Row("obstacles of radius 0.3 m", "obstacles-inertia", (("obstacles.radius_m=0.3",),)),
    Row(
        "rear 90 degrees of the lidar blocked",
        "obstacles-inertia",
        (("sensor.blocked_width_rad=1.5707963267948966",),),
    ),
    Row("10 obstacles instead of 5", "obstacles-inertia", (("obstacles.count=10",),)),
    Row(
        "obstacles turn: heading random walk 0.1 rad per 0.2 s",
        "obstacles-inertia",
        (("obstacles.heading_walk_rad=0.1",),),
    ),
    Row("... 0.3 rad per 0.2 s", "obstacles-inertia", (("obstacles.heading_walk_rad=0.3",),)),
    Row("realistic room (every setting on)", "realistic-room", ((),)),
)
"""The issue's rows, in its order, and the realistic room."""

COLUMNS = ("blind", "alone", "shipped")
"""Blind go-to-target, the policy alone, the policy as shipped (shield and proximity stop)."""


def row_worlds(row: Row) -> list[WorldConfig]:
    """The worlds of a row's variants."""
    return [changed_world(scenario(row.base), None, list(v)) for v in row.variants]


def policy_agent(policy: Path, world: WorldConfig, worlds: int) -> StreamPolicyAgent:
    """A policy file through the onboard runtime, `worlds` streams."""
    expect = Expectation(
        num_beams=world.lidar.num_beams if world.lidar else 0,
        control_period_s=world.control_period_s,
    )
    runtime = PolicyRuntime(policy, num_streams=worlds, expect=expect)
    return StreamPolicyAgent(runtime, worlds)


def agent_of(column: str, policy: Path, world: WorldConfig, settings: EvalSettings) -> Agent:
    """The agent of a column in `world`."""
    worlds = min(settings.num_worlds, settings.episodes)
    if column == "blind":
        return GoToTargetAgent()
    inner = policy_agent(policy, world, worlds)
    if column == "alone":
        return inner
    return shipped_agent(inner, world, worlds, seed=settings.seed)


def measure(
    rows: list[Row],
    columns: list[str],
    policy: Path,
    settings: EvalSettings,
    *,
    room_policy: Path | None = None,
    progress: bool = False,
) -> dict[tuple[str, str], list[EvalResult]]:
    """Each (row, column)'s results, one per variant (the realistic room's policy columns with
    `room_policy` where given)."""
    results: dict[tuple[str, str], list[EvalResult]] = {}
    for row in rows:
        chosen = room_policy if room_policy is not None and row.base == "realistic-room" else policy
        for column in columns:
            results[(row.label, column)] = [
                evaluate(world, agent_of(column, chosen, world, settings), settings, progress)
                for world in row_worlds(row)
            ]
    return results


def table(
    rows: list[Row], columns: list[str], results: dict[tuple[str, str], list[EvalResult]]
) -> str:
    """The results as a Markdown table: success per cell, variants separated by /."""
    names = {"blind": "blind go-to-target", "alone": "DQN alone", "shipped": "DQN + shield"}
    lines = [
        "| what the room does | " + " | ".join(names[c] for c in columns) + " |",
        "|---" * (len(columns) + 1) + "|",
    ]
    for row in rows:
        cells = [" / ".join(f"{r.success:.3f}" for r in results[(row.label, c)]) for c in columns]
        lines.append(f"| {row.label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class ForwardCount:
    """How episodes of an always-forward driver under the proximity stop ended."""

    episodes: int
    """Episodes run."""
    success: int
    """Reached the target."""
    static_collisions: int
    """Collisions with a static surface (walls, clutter: what the lidar sees standing)."""
    moving_collisions: int
    """Collisions with a moving obstacle."""
    unfinished: int
    """Still running at the step limit."""
    stops: int
    """Decisions where the field forbade every action (the daemon would stop the car; the
    simulator has no stop, so the car turned left)."""


def forward_collisions(
    world: WorldConfig, settings: EvalSettings, proximity: ProximitySettings | None = None
) -> ForwardCount:
    """The proximity stop below a driver that always drives forward (and turns left where the
    field forbids it), over the test protocol's episodes of `world`: each collision told static
    or moving by which surface was within the robot's radius."""
    proximity = proximity or fitted_proximity(world)
    world = replace(world, max_episode_steps=settings.max_episode_steps)
    assert world.lidar is not None
    angles = world.lidar.beam_angles_rad()
    linear = np.array([v for v, _ in action_velocities(world.dynamics, world.control_period_s)])
    values = np.array([1.0, 0.5, 0.0])  # forward first, then left
    worlds = min(settings.num_worlds, settings.episodes)
    episode = np.arange(worlds, dtype=np.int64)
    seed = np.full(worlds, settings.seed, dtype=np.int64)
    state = reset(world, seed, episode)
    observation = observe(world, state)
    counts = dict(success=0, static=0, moving=0, unfinished=0, stops=0)
    active, next_episode = np.ones(worlds, dtype=bool), worlds
    while active.any():
        assert observation.scan_m is not None
        action = np.zeros(worlds, dtype=np.int64)
        for row in range(worlds):
            ranges = field_ranges(observation.scan_m[row], 0.0, np.inf, False)
            blocked = blocked_parts(angles, ranges, proximity.footprint_m, proximity.travel_m)
            choice = guarded_action(0, allowed_actions(linear, blocked), values)
            counts["stops"] += int(choice is None and active[row])
            action[row] = 1 if choice is None else choice
        state, observation, transition = step(world, state, action)
        done = (transition.terminated | transition.truncated) & active
        static, _ = room_clearance(world, state)
        for ended in np.flatnonzero(done).tolist():
            outcome = int(transition.outcome[ended])
            if outcome == Outcome.COLLISION:
                counts["static" if static[ended] < world.robot_radius_m else "moving"] += 1
            else:
                counts["success" if outcome == Outcome.SUCCESS else "unfinished"] += 1
        index = np.flatnonzero(done)
        count = min(index.size, settings.episodes - next_episode)
        active[index[count:]] = False
        index = index[:count]
        if count:
            episode[index] = np.arange(next_episode, next_episode + count)
            next_episode += count
            fresh = reset(world, seed[index], episode[index])
            state = scatter(state, index, fresh)
            observation = scatter(observation, index, observe(world, fresh))
    return ForwardCount(
        settings.episodes,
        counts["success"],
        counts["static"],
        counts["moving"],
        counts["unfinished"],
        counts["stops"],
    )
