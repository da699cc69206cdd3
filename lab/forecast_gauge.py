"""The shield's forecast against the truth, in minutes (issue 53, section 3): before a long
evaluation, how far the tracked obstacles' futures land from where the obstacles went, whether
the truth lies among the futures, what the tracker misses or makes up, and which collisions the
forecast did not see coming.

`qnav lab forecast --row N --episodes E --set lookahead.turn_std_rad=0.3` drives the shipped
controller (`qnav.tracking.shipped_agent`, with the settings changed) through a row of the
robustness table (`lab.robustness.ROWS`) and prints one line of figures:

- found: of the true obstacles whose surface is within `NEAR_M` of the robot, the share with a
  track within `MATCH_M` of its centre (plus the track's radius);
- phantoms: moving tracks per decision with no obstacle within `MATCH_M` plus their radii;
- error at 1 / 2 / 4 s: the straight-line forecast's distance from the truth (median, p90) for
  the found obstacles, where the episode lasted that long;
- covered at 1 / 2 / 4 s: the share of those truths within `COVER_M` of one of the futures;
- unseen: collisions with a moving obstacle whose last decision's risk for the action taken was
  below `lookahead.overrule_share` (the forecast did not see it), of all collisions.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import Outcome
from qnav.contracts.settings import parse_assignments, with_overrides
from qnav.controller.futures import random_futures
from qnav.controller.lookahead import LookaheadSettings
from qnav.controller.perception import TrackerSettings
from qnav.controller.proximity import ProximitySettings
from qnav.lab.robustness import ROWS, policy_agent, row_worlds
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalSettings, episode_outcomes
from qnav.sim.room import room_clearance
from qnav.sim.world import Observation, WorldState
from qnav.tracking import LookaheadAgent, QAgent

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
    errors: dict[float, list[float]] = field(default_factory=lambda: {h: [] for h in HORIZONS_S})
    covered: dict[float, list[bool]] = field(default_factory=lambda: {h: [] for h in HORIZONS_S})
    unseen: int = 0
    collisions: int = 0
    static_collisions: int = 0


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
        self.truth: dict[tuple[int, int], F64] = {}
        self.last_risk: dict[int, float] = {}
        self.last_clearance: dict[int, tuple[float, float]] = {}
        self._random = np.random.default_rng(7)
        self.decide_s: list[float] = []

    def watch(self, state: WorldState, counting: NDArray[np.bool_]) -> None:
        self.state, self.counting = state, counting.copy()
        static, moving = room_clearance(self.world, state)
        for row in np.flatnonzero(counting).tolist():
            episode = int(state.episode[row])
            self.truth[(episode, int(state.steps[row]))] = state.obstacle_xy[row].copy()
            self.last_clearance[episode] = (float(static[row]), float(moving[row]))

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
            self.last_risk[episode] = float(self.last_risks[row, action])
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
            spread=(self.settings.turn_std_rad, self.settings.speed_std_mps),
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
                went = truth[record.true_index]  # (found, 2)
                miss = np.linalg.norm(futures - went[None], axis=-1)  # (K, found)
                self.tally.errors[horizon] += miss[0].tolist()
                self.tally.covered[horizon] += (miss.min(axis=0) <= COVER_M).tolist()


def gauge(
    world: WorldConfig,
    policy: str,
    settings: EvalSettings,
    lookahead: LookaheadSettings,
    tracker: TrackerSettings,
) -> dict[str, float]:
    """The figures of the module docstring for `world`'s episodes under the shipped controller
    with `lookahead` and `tracker`."""
    from pathlib import Path

    worlds = min(settings.num_worlds, settings.episodes)
    agent = GaugedShield(
        policy_agent(Path(policy), world, worlds),
        world,
        worlds,
        tracker=tracker,
        lookahead=lookahead,
        seed=settings.seed,
        proximity=ProximitySettings(),
    )
    outcomes, _ = episode_outcomes(world, agent, settings, watch=agent.watch)
    agent.settle()
    tally = agent.tally
    for episode in np.flatnonzero(outcomes == Outcome.COLLISION).tolist():
        static, moving = agent.last_clearance.get(episode, (np.inf, np.inf))
        tally.collisions += 1
        if static < moving:
            tally.static_collisions += 1
        elif agent.last_risk.get(episode, 1.0) < lookahead.overrule_share:
            tally.unseen += 1
    report = {
        "success": float(np.mean(outcomes == Outcome.SUCCESS)),
        "collision": float(np.mean(outcomes == Outcome.COLLISION)),
        "static_collisions": float(tally.static_collisions),
        "unseen": float(tally.unseen),
        "found": tally.found / max(tally.near, 1),
        "phantoms_per_decision": tally.phantoms / max(tally.decisions, 1),
        "overruled": agent.overruled_share,
        "decide_ms_p50": float(np.median(agent.decide_s) * 1e3),
    }
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
