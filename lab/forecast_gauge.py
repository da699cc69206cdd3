"""The shield's forecast against the truth, in minutes (issue 53, section 3): before a long
evaluation, how far the tracked obstacles' futures land from where the obstacles went, whether
the truth lies among the futures, what the tracker misses or makes up, and how each collision
came about.

`qnav lab forecast --row N --episodes E --set lookahead.turn_std_rad=0.3` drives the shipped
controller (`qnav.tracking.shipped_agent`, with the settings changed) through a row of the
robustness table (`lab.robustness.ROWS`) and blind go-to-target through the same episodes, and
prints one line of figures:

- success, collisions (a count), and blind go-to-target's success on the same layouts;
- exposure: mean steps of the episodes that reached the target, the shield's and blind's, and
  collisions per minute driven, the shield's and blind's (a slower car meets more movers);
- found: of the true obstacles whose surface is within `NEAR_M` of the robot, the share with a
  track within `MATCH_M` of its centre (plus the track's radius);
- phantoms: moving tracks per decision with no obstacle within `MATCH_M` plus their radii;
- turn, counted: the forecast's heading spread (rad over one second) and the horizon over which
  the shield counted collisions (s), means over the decisions (`lookahead.measure_turning`
  measures them; else the settings');
- error at 1 / 2 / 4 s: the straight-line forecast's distance from the truth (median, p90) for
  the found obstacles, where the episode lasted that long;
- covered at 1 / 2 / 4 s: the share of those truths within `COVER_M` of one of the futures;
- of all collisions, the shares: static (a wall or clutter was nearer than any mover at the last
  decision), unseen (with a mover, and the last decision's risk for the action taken was below
  `lookahead.overrule_share`: the forecast did not see it), stopped (the robot drove slower than
  `SLOW_MPS` at its last decision: it was hit, it did not hit), flank (the nearest mover came
  from more than `FLANK_RAD` off the robot's heading);
- alarm lead: seconds before the collision since the policy's own action last became too risky
  (its risk reached `overrule_share` and stayed there; median over the collisions that had an
  alarm), and the share of collisions with no alarm in the last `LEAD_STEPS`;
- escape lead: seconds before the collision of the last decision from which some candidate
  sequence (the structured ones and `ESCAPE_RANDOM` random ones) stays clear of the true
  obstacles up to `AFTER_STEPS` after the collision's step (after the truth ends, each obstacle
  goes straight on), median; and the share of collisions with no escape within `LEAD_STEPS`;
- late: the share of collisions whose alarm came after the last escape (or never came while one
  existed): the forecast was too late; the rest of the escapable ones were seen in time, and
  the choice (the rule, or a forecast that pointed the wrong way) did not escape.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.lookahead import (
    LookaheadModel,
    ObstacleFutures,
    candidate_sequences,
    random_blocks_needed,
    simulate,
)
from qnav.contracts.motion import Outcome, wrap_angle
from qnav.contracts.settings import parse_assignments, with_overrides
from qnav.controller.futures import random_futures, walked_futures
from qnav.controller.lookahead import LookaheadSettings
from qnav.controller.perception import TrackerSettings
from qnav.lab.robustness import ROWS, policy_agent, row_worlds
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalSettings, GoToTargetAgent, episode_outcomes
from qnav.sim.room import room_clearance
from qnav.sim.world import Observation, WorldState
from qnav.tracking import LookaheadAgent, QAgent, fitted_proximity

F64 = NDArray[np.float64]

NEAR_M = 3.0
"""Obstacles whose surface is this near the robot are the ones the forecast must find."""
MATCH_M = 0.3
"""A track within this (plus its radius) of an obstacle's centre found it."""
COVER_M = 0.3
"""A future within this of where the obstacle went covers the truth."""
HORIZONS_S = (1.0, 2.0, 4.0)
"""Forecast horizons measured."""
GAUGE_FUTURES = 32
"""Futures drawn per decision for the coverage (the gauge's own generator)."""
SLOW_MPS = 0.1
"""A robot slower than this at its last decision was standing when it was hit."""
FLANK_RAD = math.pi / 3
"""A mover nearer than any other at the last decision, more than this off the heading, came
from the side or behind."""
LEAD_STEPS = 30
"""How many decisions before a collision its alarm and escape are looked for."""
AFTER_STEPS = 5
"""Steps past the collision's an escape must stay clear for (the obstacles straight on)."""
ESCAPE_RANDOM = 64
"""Random candidate sequences tried for an escape, beside the structured ones."""
STORY_FIGURES = (
    "static", "unseen", "stopped", "flank", "alarm_lead_s", "no_alarm", "escape_lead_s",
    "no_escape", "late",
)  # fmt: skip
"""The collisions' figures (`story_figures`), in the order printed."""


class Moment(NamedTuple):
    """One world's true state at one decision."""

    pose: F64
    """(3,) the robot's x, y, heading."""
    velocity: F64
    """(2,) its forward speed and turn rate."""
    obstacle_xy: F64
    """(M, 2) the obstacles' centres."""
    obstacle_velocity: F64
    """(M, 2) their velocities."""
    static_m: float
    """Distance to the nearest wall or clutter."""
    moving_m: float
    """Distance to the nearest mover's surface."""


class Choice(NamedTuple):
    """What one decision believed of its actions."""

    taken: int
    """The action taken (after the shield and the proximity stop)."""
    greedy: int
    """The policy's best-valued action."""
    risks: F64
    """(A,) each action's forecast risk."""


class Story(NamedTuple):
    """How one collision came about (`collision_story`)."""

    static: bool
    """A wall or clutter was nearer than any mover at the last decision."""
    unseen: bool
    """With a mover, and the last decision's risk for the action taken was below the share."""
    stopped: bool
    """The robot was slower than `SLOW_MPS` at its last decision."""
    flank: bool
    """The nearest mover was more than `FLANK_RAD` off the heading at the last decision."""
    alarm_lead: int
    """Decisions since the policy's action last became too risky (0: no alarm)."""
    escape_lead: int
    """Decisions before the collision of the last one with an escape (0: none)."""


@dataclass
class Record:
    """What one decision of one world believed, kept until the truth arrives."""

    episode: int
    step: int
    true_index: NDArray[np.int64]
    """Indices of the true obstacles found (near the robot, matched by a track)."""
    futures: F64
    """(len(HORIZONS_S), K, found, 2) the matched tracks' futures at each horizon (K = 0: the
    straight line)."""


@dataclass
class Tally:
    """The gauge's counts."""

    near: int = 0
    found: int = 0
    phantoms: int = 0
    decisions: int = 0
    turn_rad: float = 0.0
    """Sum over the decisions of the forecast's heading spread (`Lookahead.turn_std`)."""
    counted_s: float = 0.0
    """Sum over the decisions of the horizon the shield counted collisions over."""
    errors: dict[float, list[float]] = field(default_factory=lambda: {h: [] for h in HORIZONS_S})
    covered: dict[float, list[bool]] = field(default_factory=lambda: {h: [] for h in HORIZONS_S})


class GaugedShield(LookaheadAgent):
    """The shipped controller, its beliefs compared with the world's state before each decision
    (`episode_outcomes`' watch)."""

    def __init__(
        self, inner: QAgent, world: WorldConfig, num_worlds: int, **kwargs: object
    ) -> None:
        super().__init__(inner, world, num_worlds, **kwargs)  # type: ignore[arg-type]
        self.tally = Tally()
        self.state: WorldState | None = None
        self.counting = np.zeros(num_worlds, dtype=bool)
        self.pending: list[Record] = []
        self.truth: dict[tuple[int, int], Moment] = {}
        self.choices: dict[tuple[int, int], Choice] = {}
        self._random = np.random.default_rng(7)
        self.decide_s: list[float] = []

    def watch(self, state: WorldState, counting: NDArray[np.bool_]) -> None:
        self.state, self.counting = state, counting.copy()
        static, moving = room_clearance(self.world, state)
        for row in np.flatnonzero(counting).tolist():
            key = (int(state.episode[row]), int(state.steps[row]))
            self.truth[key] = Moment(
                state.pose[row].copy(),
                state.velocity[row].copy(),
                state.obstacle_xy[row].copy(),
                state.obstacle_velocity[row].copy(),
                float(static[row]),
                float(moving[row]),
            )

    def act(self, observation: Observation) -> NDArray[np.int64]:
        started = time.perf_counter()
        action = super().act(observation)
        self.decide_s.append((time.perf_counter() - started) / len(action))
        assert self.state is not None
        for row in np.flatnonzero(self.counting).tolist():
            self._record(row, observation, int(action[row]))
        return action

    def _record(self, row: int, observation: Observation, action: int) -> None:
        """Compare world `row`'s belief with its state; keep its futures for the truth."""
        assert self.state is not None
        state, car, tally = self.state, self.cars[row], self.tally
        belief = car.belief(observation.target_xy[row])
        episode = int(state.episode[row])
        if self.last_risks is not None:
            greedy = int(np.argmax(self.inner.last_q[row]))
            key = (episode, int(state.steps[row]))
            self.choices[key] = Choice(action, greedy, self.last_risks[row].copy())
        tracks, velocity = belief.obstacle_xy[0], belief.obstacle_velocity[0]
        radius = belief.obstacle_radius[0]
        true_xy = state.obstacle_xy[row]
        gap = np.linalg.norm(true_xy[:, None] - tracks[None], axis=-1)  # (true, tracks)
        near = np.linalg.norm(true_xy - state.pose[row, :2], axis=1) < NEAR_M
        matched = (
            near & (gap - radius[None] <= MATCH_M).any(axis=1) if len(tracks) else near & False
        )
        tally.near += int(near.sum())
        tally.found += int(matched.sum())
        tally.decisions += 1
        tally.turn_rad += car.turn_std()
        tally.counted_s += car.counted_steps() * self.world.control_period_s
        moving = np.linalg.norm(velocity, axis=1) > 0
        lonely = (gap - radius[None] > MATCH_M).all(axis=0) if len(true_xy) else moving
        tally.phantoms += int((moving & lonely).sum())
        index = np.flatnonzero(matched)
        if not index.size:
            return
        nearest = gap[index].argmin(axis=1)
        steps = [round(h / self.world.control_period_s) for h in HORIZONS_S]
        futures = random_futures(
            tracks[nearest],
            velocity[nearest],
            radius[nearest],
            steps=max(steps),
            period_s=self.world.control_period_s,
            futures=GAUGE_FUTURES,
            spread=(car.turn_std(), self.settings.speed_std_mps),
            box=car.box,
            random=self._random,
        ).xy[:, 0]  # (H, K, found, 2)
        picked = np.stack([futures[s - 1] for s in steps])
        self.pending.append(Record(episode, int(state.steps[row]), index, picked))

    def settle(self) -> None:
        """Score every kept forecast against the truth that arrived (episodes that ended before
        a horizon leave it unscored)."""
        steps = [round(h / self.world.control_period_s) for h in HORIZONS_S]
        for record in self.pending:
            for horizon, ahead, futures in zip(HORIZONS_S, steps, record.futures, strict=True):
                truth = self.truth.get((record.episode, record.step + ahead))
                if truth is None:
                    continue
                went = truth.obstacle_xy[record.true_index]  # (found, 2)
                miss = np.linalg.norm(futures - went[None], axis=-1)  # (K, found)
                self.tally.errors[horizon] += miss[0].tolist()
                self.tally.covered[horizon] += (miss.min(axis=0) <= COVER_M).tolist()


def alarm_lead(choices: Sequence[Choice | None], overrule_share: float) -> int:
    """Decisions before the end of `choices` (oldest first, the last one the collision's) since
    the policy's own action last became too risky and stayed so (0: the last one was not)."""
    lead = 0
    for choice in reversed(choices):
        if choice is None or choice.risks[choice.greedy] < overrule_share:
            break
        lead += 1
    return lead


def true_path(moments: list[Moment], box: tuple[F64, F64], radius_m: F64, period_s: float) -> F64:
    """(len(moments) - 1 + AFTER_STEPS + 1, M, 2) where the obstacles were at each decision after
    the first of `moments`, then, from the last, straight on (bouncing in `box`) through the
    collision's step and `AFTER_STEPS` more."""
    last = moments[-1]
    draws = np.zeros((2, 1, 1, len(radius_m), AFTER_STEPS + 1))
    straight = walked_futures(
        last.obstacle_xy[None],
        last.obstacle_velocity[None],
        radius_m[None],
        draws,
        period_s=period_s,
        box=box,
    ).xy[:, 0, 0]  # (AFTER_STEPS + 1, M, 2)
    seen = [m.obstacle_xy for m in moments[1:]]
    return np.concatenate([np.array(seen).reshape(-1, *radius_m.shape, 2), straight])


class _Start(NamedTuple):
    """One robot's true state as a `contracts.lookahead.Situation` of one world."""

    pose: F64
    velocity: F64
    target_xy: F64
    obstacle_xy: F64
    obstacle_velocity: F64


def escapes(
    model: LookaheadModel, start: Moment, path: F64, radius_m: F64, random: np.random.Generator
) -> bool:
    """Whether some candidate sequence from the robot's true state `start` stays clear of the
    obstacles along `path` (H, M, 2), each of `radius_m` (M,), and of the walls, for H steps."""
    horizon = path.shape[0]
    blocks = random.integers(0, 3, size=(1, ESCAPE_RANDOM, random_blocks_needed(horizon)))
    sequences = candidate_sequences(blocks, horizon)
    situation = _Start(
        start.pose[None],
        start.velocity[None],
        np.full((1, 2), 1e4),  # a target out of reach: only surviving counts
        start.obstacle_xy[None],
        start.obstacle_velocity[None],
    )
    futures = ObstacleFutures(path[:, None, None], radius_m[None])
    outcome = simulate(model, situation, sequences, futures).outcome
    return bool((outcome != Outcome.COLLISION).any())


def escape_lead(
    model: LookaheadModel,
    moments: list[Moment],
    box: tuple[F64, F64],
    radius_m: F64,
    random: np.random.Generator,
) -> int:
    """Decisions before the collision (`moments` oldest first, the last one the collision's
    last decision) of the last one from which a candidate sequence escapes (0: none)."""
    for lead in range(1, len(moments) + 1):
        since = moments[len(moments) - lead :]
        path = true_path(since, box, radius_m, model.control_period_s)
        if escapes(model, since[0], path, radius_m, random):
            return lead
    return 0


def collision_story(
    agent: GaugedShield, episode: int, length: int, overrule_share: float, radius_m: float
) -> Story:
    """How `episode`'s collision at step `length` came about (`Story`), from what the gauge
    kept of its last `LEAD_STEPS` decisions."""
    steps = range(max(0, length - LEAD_STEPS), length)
    moments = [agent.truth[(episode, s)] for s in steps]
    choices = [agent.choices.get((episode, s)) for s in steps]
    last, choice = moments[-1], choices[-1]
    static = last.static_m < last.moving_m
    offset = last.obstacle_xy - last.pose[:2]
    nearest = int(np.argmin(np.linalg.norm(offset, axis=1))) if len(offset) else 0
    bearing = math.atan2(offset[nearest, 1], offset[nearest, 0]) if len(offset) else 0.0
    car = agent.cars[0]
    radii = np.full(len(last.obstacle_xy), radius_m)
    random = np.random.default_rng([episode, 53])
    return Story(
        static=static,
        unseen=not static and (choice is None or choice.risks[choice.taken] < overrule_share),
        stopped=abs(float(last.velocity[0])) < SLOW_MPS,
        flank=abs(float(wrap_angle(np.array(bearing - last.pose[2])))) > FLANK_RAD,
        alarm_lead=alarm_lead(choices, overrule_share),
        escape_lead=escape_lead(car.model, moments, car.box, radii, random),
    )


def story_figures(stories: list[Story], period_s: float) -> dict[str, float]:
    """The collisions' shares and leads of the module docstring (NaN without collisions)."""
    count = len(stories)
    if not count:
        return dict.fromkeys(STORY_FIGURES, math.nan)
    alarms = [s.alarm_lead * period_s for s in stories if s.alarm_lead]
    escapes_s = [s.escape_lead * period_s for s in stories if s.escape_lead]
    late = [s for s in stories if s.escape_lead and s.alarm_lead < s.escape_lead]
    return {
        "static": sum(s.static for s in stories) / count,
        "unseen": sum(s.unseen for s in stories) / count,
        "stopped": sum(s.stopped for s in stories) / count,
        "flank": sum(s.flank for s in stories) / count,
        "alarm_lead_s": float(np.median(alarms)) if alarms else math.nan,
        "no_alarm": sum(not s.alarm_lead for s in stories) / count,
        "escape_lead_s": float(np.median(escapes_s)) if escapes_s else math.nan,
        "no_escape": sum(not s.escape_lead for s in stories) / count,
        "late": len(late) / count,
    }


def exposure(outcomes: NDArray[np.int64], lengths: NDArray[np.int64], period_s: float) -> F64:
    """(3,) success, mean steps of the episodes that reached the target, collisions per minute
    driven."""
    success = outcomes == Outcome.SUCCESS
    steps = float(lengths[success].mean()) if success.any() else math.nan
    minutes = lengths.sum() * period_s / 60.0
    return np.array([success.mean(), steps, (outcomes == Outcome.COLLISION).sum() / minutes])


def gauge(
    world: WorldConfig,
    policy: str,
    settings: EvalSettings,
    lookahead: LookaheadSettings,
    tracker: TrackerSettings,
) -> dict[str, float]:
    """The figures of the module docstring for `world`'s episodes under the shipped controller
    with `lookahead` and `tracker`, and blind go-to-target's on the same layouts."""
    worlds = min(settings.num_worlds, settings.episodes)
    agent = GaugedShield(
        policy_agent(Path(policy), world, worlds),
        world,
        worlds,
        tracker=tracker,
        lookahead=lookahead,
        seed=settings.seed,
        proximity=fitted_proximity(world),
    )
    outcomes, lengths = episode_outcomes(world, agent, settings, watch=agent.watch)
    blind = exposure(*episode_outcomes(world, GoToTargetAgent(), settings), world.control_period_s)
    agent.settle()
    shield = exposure(outcomes, lengths, world.control_period_s)
    stories = [
        collision_story(
            agent, e, int(lengths[e]), lookahead.overrule_share, world.obstacles.radius_m
        )
        for e in np.flatnonzero(outcomes == Outcome.COLLISION).tolist()
    ]
    tally = agent.tally
    report = {
        "success": float(shield[0]),
        "collisions": float(len(stories)),
        "blind_success": float(blind[0]),
        "steps": float(shield[1]),
        "blind_steps": float(blind[1]),
        "collisions_per_min": float(shield[2]),
        "blind_collisions_per_min": float(blind[2]),
        **story_figures(stories, world.control_period_s),
        "found": tally.found / max(tally.near, 1),
        "phantoms_per_decision": tally.phantoms / max(tally.decisions, 1),
        "overruled": agent.overruled_share,
        "turn_rad": tally.turn_rad / max(tally.decisions, 1),
        "counted_s": tally.counted_s / max(tally.decisions, 1),
        "decide_ms_p50": float(np.median(agent.decide_s) * 1e3),
    }
    return report | forecast_figures(tally)


def forecast_figures(tally: Tally) -> dict[str, float]:
    """The forecast's error (median, p90) and coverage at each of `HORIZONS_S`."""
    report: dict[str, float] = {}
    for horizon in HORIZONS_S:
        errors = np.array(tally.errors[horizon]) if tally.errors[horizon] else np.full(1, np.nan)
        report[f"error_{horizon:g}s_p50"] = float(np.median(errors))
        report[f"error_{horizon:g}s_p90"] = float(np.percentile(errors, 90))
        covered = tally.covered[horizon]
        report[f"covered_{horizon:g}s"] = float(np.mean(covered)) if covered else math.nan
    return report


def changed(
    row: int, assignments: list[str]
) -> tuple[WorldConfig, LookaheadSettings, TrackerSettings]:
    """Row `row`'s first world and the shipped look ahead and tracker, each changed by the
    `lookahead.FIELD=VALUE` and `tracker.FIELD=VALUE` strings."""
    nested = parse_assignments(assignments)
    lookahead = with_overrides(LookaheadSettings(), nested.pop("lookahead", {}), "lookahead")
    tracker = with_overrides(TrackerSettings(), nested.pop("tracker", {}), "tracker")
    world = row_worlds(ROWS[row])[0]
    if nested:
        world = with_overrides(world, nested)
    return replace(world), lookahead, tracker
