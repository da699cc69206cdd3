"""The onboard look ahead: obstacles tracked in each scan, every action's risk forecast a few
seconds ahead, and the policy overruled where its choice is riskier than another action.

The paper's network does not perceive moving obstacles (docs/learner.md, "Why: perception and
the doom function's appetite for data"); a tracker (`controller.perception`) and a short
forecast with the training world's own motion model (`contracts.lookahead`, the same code the
simulator's oracle plans with) do. Each decision:

1. a new scan updates the obstacle tracks (room frame, from the motion-capture pose);
2. the car's own speed and turn rate come from its last three poses;
3. every first action is followed by the same continuations (the structured ones and random ones
   drawn from a seeded generator restarted with the tracking) over `shield_horizon_s`, and the
   share of them that collide is that action's risk;
4. the policy's best-valued action is taken unless its risk reaches `overrule_share`, then its
   best-valued among the least risky (`shielded_actions`);
   or, in "plan" mode, the first action of the best-scoring candidate sequence over
   `plan_horizon_s` (the simulator's oracle planner, on the perceived state), whatever the
   policy's values.

`Lookahead` holds one car's state; the controller (`controller.decision`) calls it, and the
simulator's in-process evaluation runs the same class (`qnav.tracking.LookaheadAgent`). Step 1
runs on every scan, decision or not: a car waiting at rest keeps tracking, so its first
decision after a stop already knows how the obstacles move (a track's velocity needs a second
scan). Tracking restarts only when the scans break off (`max_scan_gap_s`): tracks and poses
from before a gap are no longer where the room is.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.errors import ConfigError
from qnav.contracts.lookahead import (
    LookaheadModel,
    ObstacleFutures,
    best_first_actions,
    candidate_sequences,
    collision_shares,
    first_action_sequences,
    random_blocks_needed,
    simulate,
)
from qnav.contracts.motion import Dynamics, InertiaDynamics, Outcome
from qnav.contracts.settings import check_range
from qnav.controller.futures import (
    informative_horizon_s,
    turn_from_misses,
    walk_draws,
    walked_futures,
)
from qnav.controller.perception import (
    ObstacleTracker,
    TrackerSettings,
    beam_poses,
    box_walls,
    own_velocity,
)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class LookaheadSettings:
    """Whether and how the controller forecasts each action's risk before acting."""

    SECTION = "lookahead"

    mode: Literal["off", "shield", "plan"] = "shield"
    """"off": the policy decides alone (a lidar-less policy needs it). "shield": the policy's
    best-valued action, unless at least `overrule_share` of the continuations after it collide:
    then its best-valued among the least likely to collide. "plan": the first action of the
    best-scoring candidate sequence (reach the target early, collide late or never, else end
    near the target and clear of surfaces), the policy's values reported but not used."""
    room_size_m: float = 0.0
    """Side of the square room [0, size]^2 in the motion-capture frame: its walls are known (a
    lidar return on them is not an obstacle, and obstacles bounce off them). 0: not set, and a
    look ahead refuses to start unless `walls` are given: measure the room (the simulator's is
    10 m)."""
    walls: tuple[tuple[float, float, float, float], ...] = ()
    """The room's walls as segments [x0, y0, x1, y1] in metres in the motion-capture frame, as
    measured, for a room that is not that square (they replace it; obstacles bounce inside the
    box that bounds them)."""
    shield_horizon_s: float = 6.0
    """How far ahead the shield forecasts each action's risk (6 s against the oracle's 4 s doom
    horizon, with `overrule_share` 0.3: 0.900 against 0.882 success in obstacles-inertia, 0.885
    against 0.852 in obstacles-increment; docs/controller.md)."""
    plan_horizon_s: float = 10.0
    """How far ahead the planner's candidate sequences run (10 s against 4 s: 0.957 against
    0.933 success in obstacles-inertia, 0.940 against 0.900 in obstacles-increment, 300 test
    episodes each, 2026-12-03; docs/controller.md)."""
    random_sequences: int = 64
    """Random continuations tried after each first action, beside the structured ones."""
    overrule_share: float = 0.3
    """In mode "shield", the forecast overrules the policy only where at least this share of
    the continuations after its action collide (0: wherever a safer action exists; 0.3 against
    0, forecasting 4 s: 0.882 against 0.854 success in obstacles-inertia, 0.852 against 0.829 in
    obstacles-increment, docs/controller.md)."""
    seed: int = 0
    """Seed of the random continuations (the generator restarts with the tracking: a new episode,
    or the scans broke off)."""
    turn_std_rad: float = 0.0
    """How much a moving obstacle may turn in the shield's forecast: the standard deviation of
    its heading's change over one second (a random walk: over t seconds, this times the square
    root of t), each continuation meeting its own future (`controller.futures`); 0: every
    obstacle forecast in a straight line."""
    speed_std_mps: float = 0.0
    """How much a moving obstacle's speed may change in the shield's forecast: the standard
    deviation of its change over one second, as `turn_std_rad`."""
    measure_turning: bool = False
    """Measure how much the obstacles turn from how far each moving track lands from its own
    straight-line forecast `TURN_LAG_S` earlier (`controller.futures.turn_from_misses`), forecast
    with that spread (at least `turn_std_rad`), and let the shield count only the collisions
    within the time its forecast stays informative (`informative_m`): where obstacles turn 0.3
    rad per 0.2 s, 0.540 -> 0.710 success, as simulated 0.920 either way (100 episodes each),
    but in the realistic room it measures 1.3 rad and costs time (docs/lookahead.md); false:
    straight lines over the whole horizon."""
    informative_m: float = 1.0
    """With `measure_turning`: the shield counts collisions up to the time a walker at the
    measured speeds strays this far (root mean square) from its straight line, between
    `min_horizon_s` and `shield_horizon_s` (`controller.futures.informative_horizon_s`)."""
    min_horizon_s: float = 2.0
    """With `measure_turning`: the shortest horizon the shield counts collisions over, however
    much the obstacles turn."""

    def __post_init__(self) -> None:
        if self.mode not in ("off", "shield", "plan"):
            raise ConfigError(f"lookahead.mode = {self.mode!r}: choose off, shield or plan")
        check_range(self, "room_size_m", self.room_size_m, 0.0, 1000.0)
        for wall in self.walls:
            if len(wall) != 4:
                raise ConfigError(f"lookahead.walls: {wall!r} is not a segment [x0, y0, x1, y1]")
        check_range(self, "shield_horizon_s", self.shield_horizon_s, 0.0, 60.0, exclusive_low=True)
        check_range(self, "plan_horizon_s", self.plan_horizon_s, 0.0, 60.0, exclusive_low=True)
        check_range(self, "random_sequences", self.random_sequences, 0, 100_000)
        check_range(self, "overrule_share", self.overrule_share, 0.0, 1.0)
        check_range(self, "turn_std_rad", self.turn_std_rad, 0.0, 100.0)
        check_range(self, "speed_std_mps", self.speed_std_mps, 0.0, 100.0)
        check_range(self, "informative_m", self.informative_m, 0.0, 100.0, exclusive_low=True)
        check_range(self, "min_horizon_s", self.min_horizon_s, 0.0, 60.0, exclusive_low=True)


TURN_LAG_S = 1.0
"""How long after a track's straight-line forecast `measure_turning` compares it with where
the track is (long enough for a turn to show, short enough that few bounce off a wall)."""
TURN_GATE_M = 1.0
"""A track this far or farther from a forecast is another obstacle's, not a miss."""
TURN_MISSES_KEPT = 200
"""The latest misses `measure_turning` keeps (kept across restarts: the room's obstacles)."""
TURN_MISSES_NEEDED = 10
"""Misses before `measure_turning` trusts its measure (until then: `turn_std_rad`)."""
TURN_FLOOR_RAD = 0.1
"""A measured spread below this is the tracker's own error, not turning: straight lines (the
paper's walkers measure about 1e-6; the robustness table's least turning row, 0.22)."""
MOVING_MPS = 0.3
"""Tracks slower than this are not measured for turning (their heading is noise)."""

FAR_AWAY_M = 1e4
"""Where a padding obstacle is put when beliefs with different numbers of tracks are stacked:
out of every rollout's reach."""


class Belief(NamedTuple):
    """What the car believes of its world now: one world of a `contracts.lookahead.Situation`."""

    pose: F64
    """(1, 3) x, y, heading (motion capture)."""
    velocity: F64
    """(1, 2) forward speed and turn rate, from the last poses (zero under increments)."""
    target_xy: F64
    """(1, 2) the target."""
    obstacle_xy: F64
    """(1, M, 2) the tracked obstacles' centres."""
    obstacle_velocity: F64
    """(1, M, 2) their velocities (zero for those that stand)."""
    obstacle_radius: F64
    """(1, M) their radii, from their points."""


class Lookahead:
    """One car's tracker, pose history and forecast (module docstring: the steps)."""

    def __init__(
        self,
        settings: LookaheadSettings,
        tracker: TrackerSettings,
        *,
        dynamics: Dynamics,
        robot_radius_m: float,
        control_period_s: float,
        beam_angles_rad: F64,
        max_scan_gap_s: float = math.inf,
    ) -> None:
        self.settings = settings
        self.max_scan_gap_s = max_scan_gap_s
        """A scan taken longer than this after the last tracked one (or before it) restarts the
        tracking (the controller's scan timeout: the span after which it stops the car)."""
        self.tracker_settings = tracker
        if settings.room_size_m <= 0 and not settings.walls:
            raise ConfigError(
                f"lookahead.room_size_m is not set: lookahead.mode = {settings.mode!r} needs the "
                "room's walls (the side of the square room [0, size]^2 in the motion-capture "
                "frame, e.g. --set lookahead.room_size_m=10, or its walls as segments, "
                'lookahead.walls); or set lookahead.mode = "off" to drive on the policy alone'
            )
        walls = room_walls(settings)
        self.walls = walls
        corners = walls.reshape(-1, 2)
        self.box = (corners.min(axis=0), corners.max(axis=0))
        """The box that bounds the walls, inside which the forecast's obstacles bounce."""
        self.model = LookaheadModel(
            dynamics=dynamics,
            control_period_s=control_period_s,
            robot_radius_m=robot_radius_m,
            obstacle_radius_m=0.0,  # each track has its own (`Belief.obstacle_radius`)
            room_size_m=float(walls.max()),
            wall_start=walls[:, :2],
            wall_end=walls[:, 2:],
        )
        self.beam_angles_rad = beam_angles_rad
        horizon_s = (
            settings.plan_horizon_s if settings.mode == "plan" else settings.shield_horizon_s
        )
        self.horizon = max(1, round(horizon_s / control_period_s))
        """Control periods each candidate sequence runs."""
        self.misses: deque[tuple[float, float]] = deque(maxlen=TURN_MISSES_KEPT)
        """(miss, speed) of the latest straight-line forecasts `measure_turning` checked."""
        self.restart()

    def restart(self) -> None:
        """Forget the tracks and poses and restart the continuations' generator: a new episode,
        or the scans broke off."""
        self.tracker = ObstacleTracker(self.tracker_settings, self.walls, self.beam_angles_rad)
        self._random = np.random.default_rng(self.settings.seed)
        self._poses: list[F64] = []
        self._pose_times_s: list[float] = []
        self._scan_time_s: float | None = None
        self._forecasts: deque[tuple[float, F64, F64]] = deque()
        """(time, centres, velocities) of moving tracks, until `TURN_LAG_S` later."""

    def observe(
        self,
        pose_time_s: float,
        pose: F64,
        scan_time_s: float,
        scan_m: NDArray[np.floating],
        beam_delays_s: F64 | None = None,
    ) -> None:
        """Take in the newest pose (x, y, heading) and scan (ranges along `beam_angles_rad`),
        with the times they were taken: a scan already tracked is not tracked again, a pose no
        newer than the last is not kept, and a scan after a gap (`max_scan_gap_s`) restarts the
        tracking first. A rotating lidar's scan, whose beams were taken `beam_delays_s` (B,)
        after its stamp (`controller.scan.Resampled.delays_s`), is placed beam by beam from the
        car's pose at each beam's time, on the line through its last two poses."""
        last_s = self._scan_time_s
        if last_s is not None and not 0.0 <= scan_time_s - last_s <= self.max_scan_gap_s:
            self.restart()
        if not self._pose_times_s or pose_time_s > self._pose_times_s[-1]:
            self._poses = [*self._poses[-2:], np.asarray(pose, dtype=np.float64)]
            self._pose_times_s = [*self._pose_times_s[-2:], pose_time_s]
        if scan_time_s != self._scan_time_s:
            if beam_delays_s is not None and len(self._poses) > 1:
                beam_times_s = scan_time_s + beam_delays_s
                poses = beam_poses(
                    np.array(self._poses[-2:]), np.array(self._pose_times_s[-2:]), beam_times_s
                )
                self.tracker.update(scan_time_s, scan_m, poses, beam_times_s)
            else:
                self.tracker.update(scan_time_s, scan_m, pose)
            self._scan_time_s = scan_time_s
            if self.settings.measure_turning:
                self._check_forecasts(scan_time_s)

    def _check_forecasts(self, now_s: float) -> None:
        """Check the moving tracks' straight-line forecasts of `TURN_LAG_S` ago against where
        the tracks are now (`misses`), and keep this scan's for later."""
        tracks = self.tracker.tracks()
        while self._forecasts and now_s - self._forecasts[0][0] >= TURN_LAG_S - 1e-9:
            then_s, xy, velocity = self._forecasts.popleft()
            self.misses.extend(straight_misses(xy, velocity, now_s - then_s, tracks.xy_m, self.box))
        speed = np.hypot(tracks.velocity_mps[:, 0], tracks.velocity_mps[:, 1])
        moving = speed >= MOVING_MPS
        self._forecasts.append((now_s, tracks.xy_m[moving], tracks.velocity_mps[moving]))

    def turn_std(self) -> float:
        """The heading spread the forecast's futures walk with: `turn_std_rad`, or with
        `measure_turning` what the misses measure, if more."""
        if not self.settings.measure_turning or len(self.misses) < TURN_MISSES_NEEDED:
            return self.settings.turn_std_rad
        miss, speed = np.array(self.misses).T
        measured = turn_from_misses(miss, speed, TURN_LAG_S)
        return max(self.settings.turn_std_rad, measured if measured >= TURN_FLOOR_RAD else 0.0)

    def counted_steps(self) -> int:
        """Control periods within which the shield counts a continuation's collision: the
        horizon, or with `measure_turning` the time its forecast stays informative."""
        s = self.settings
        if not s.measure_turning or len(self.misses) < TURN_MISSES_NEEDED:
            return self.horizon
        speed = float(np.median([v for _, v in self.misses]))
        bounds_s = (min(s.min_horizon_s, s.shield_horizon_s), s.shield_horizon_s)
        horizon_s = informative_horizon_s(self.turn_std(), speed, s.informative_m, bounds_s)
        return max(1, min(self.horizon, round(horizon_s / self.model.control_period_s)))

    def belief(self, target_xy: F64) -> Belief:
        """The state the forecast starts from (after at least one `observe`)."""
        tracks = self.tracker.tracks()
        velocity = np.zeros(2)
        if isinstance(self.model.dynamics, InertiaDynamics):
            velocity = own_velocity(np.array(self._poses), np.diff(self._pose_times_s))
        return Belief(
            pose=self._poses[-1][None],
            velocity=velocity[None],
            target_xy=np.asarray(target_xy, dtype=np.float64).reshape(1, 2),
            obstacle_xy=tracks.xy_m[None],
            obstacle_velocity=tracks.velocity_mps[None],
            obstacle_radius=tracks.radius_m[None],
        )

    def walks(self, obstacles: int, count: int) -> F64 | None:
        """(2, K, M, H) this decision's random walks of `obstacles` obstacles in `count`
        futures (`controller.futures.walk_draws`), drawn after the continuations; None where
        the forecast has no spread or one future is asked for (the straight line)."""
        s = self.settings
        spread = (self.turn_std(), s.speed_std_mps)
        if count < 2 or not any(spread):
            return None
        return walk_draws(
            self._random,
            futures=count,
            obstacles=obstacles,
            steps=self.horizon,
            spread=spread,
            period_s=self.model.control_period_s,
        )

    def candidates(self) -> NDArray[np.int64]:
        """(1, S, H) this decision's candidate sequences: the structured ones and
        `random_sequences` fresh random ones."""
        size = (1, self.settings.random_sequences, random_blocks_needed(self.horizon))
        random = self._random.integers(0, NUM_ACTIONS, size=size)
        return candidate_sequences(random, self.horizon)

    def continuations(self) -> NDArray[np.int64]:
        """(1, T, H - 1) the continuations that follow every first action this decision."""
        return self.candidates()[:, :, : self.horizon - 1]

    def plan(self, target_xy: F64) -> int:
        """The first action of the best-scoring candidate sequence over the horizon."""
        return int(plans_of([self], [target_xy])[0])

    def risks(self, target_xy: F64) -> F64:
        """(A,) each first action's share of colliding continuations within the horizon."""
        return np.asarray(risks_of([self], [target_xy])[0])


def risks_of(lookaheads: list[Lookahead], targets_xy: list[F64]) -> F64:
    """(N, A) `Lookahead.risks` of several cars at once (one forecast over all of them; their
    models must be alike): each draws its own continuations, then one future of its obstacles
    per continuation (`Lookahead.walks`), as it would alone."""
    if not lookaheads:
        return np.zeros((0, NUM_ACTIONS))
    tails = np.concatenate([car.continuations() for car in lookaheads])
    belief = beliefs_of(lookaheads, targets_xy)
    futures = futures_of(lookaheads, belief, tails.shape[1])
    counted = np.array([car.counted_steps() for car in lookaheads])
    if (counted >= lookaheads[0].horizon).all():
        return collision_shares(lookaheads[0].model, belief, tails, futures)
    return shares_within(lookaheads[0].model, belief, tails, futures, counted)


def shares_within(
    model: LookaheadModel,
    belief: Belief,
    tails: NDArray[np.int64],
    futures: ObstacleFutures,
    counted: NDArray[np.int64],
) -> F64:
    """(N, A) `contracts.lookahead.collision_shares`, counting only the collisions within
    each world's first `counted` (N,) steps (the rollouts stop at the most of them)."""
    steps = int(counted.max())
    tails = tails[:, :, : steps - 1]
    futures = ObstacleFutures(futures.xy[:steps], futures.radius_m)
    worlds, tail_count = tails.shape[:2]
    rollouts = simulate(model, belief, first_action_sequences(tails), futures)
    early = (rollouts.outcome == Outcome.COLLISION) & (rollouts.end_step <= counted[:, None])
    return np.asarray(early.reshape(worlds, NUM_ACTIONS, tail_count).mean(axis=2))


def plans_of(lookaheads: list[Lookahead], targets_xy: list[F64]) -> NDArray[np.int64]:
    """(N,) `Lookahead.plan` of several cars at once (their models must be alike): the
    obstacles on their straight lines."""
    if not lookaheads:
        return np.zeros(0, dtype=np.int64)
    sequences = np.concatenate([car.candidates() for car in lookaheads])
    belief = beliefs_of(lookaheads, targets_xy)
    futures = futures_of(lookaheads, belief, 1)
    return best_first_actions(lookaheads[0].model, belief, sequences, futures)


def futures_of(lookaheads: list[Lookahead], belief: Belief, count: int) -> ObstacleFutures:
    """The futures of the cars' stacked `belief`: `count` per car, each car's walks from its
    own generator (`Lookahead.walks`); the straight line alone where they have none."""
    most = belief.obstacle_xy.shape[1]
    first = lookaheads[0]
    tracked = [len(car.tracker.tracks().xy_m) for car in lookaheads]
    walks = [car.walks(m, count) for car, m in zip(lookaheads, tracked, strict=True)]
    if all(w is None for w in walks):
        draws = np.zeros((2, len(lookaheads), 1, most, first.horizon))
    else:  # a car without spread walks its `count` futures on its straight lines
        straight = np.zeros((2, count, most, first.horizon))
        draws = np.stack([straight if w is None else _padded(w, most, 0.0, 2) for w in walks], 1)
    return walked_futures(
        belief.obstacle_xy,
        belief.obstacle_velocity,
        belief.obstacle_radius,
        draws,
        period_s=first.model.control_period_s,
        box=first.box,
    )


def beliefs_of(lookaheads: list[Lookahead], targets_xy: list[F64]) -> Belief:
    """Each car's belief, stacked as one state of N worlds."""
    return stacked([car.belief(t) for car, t in zip(lookaheads, targets_xy, strict=True)])


def _padded(values: F64, most: int, fill: float, axis: int) -> F64:
    """`values` with `fill` appended along `axis` up to `most` entries."""
    shape = list(values.shape)
    shape[axis] = most - values.shape[axis]
    return np.concatenate([values, np.full(shape, fill)], axis=axis)


def stacked(beliefs: list[Belief]) -> Belief:
    """Several cars' beliefs as one state of N worlds, the obstacles padded far away."""
    most = max(b.obstacle_xy.shape[1] for b in beliefs)
    return Belief(
        pose=np.concatenate([b.pose for b in beliefs]),
        velocity=np.concatenate([b.velocity for b in beliefs]),
        target_xy=np.concatenate([b.target_xy for b in beliefs]),
        obstacle_xy=np.concatenate([_padded(b.obstacle_xy, most, FAR_AWAY_M, 1) for b in beliefs]),
        obstacle_velocity=np.concatenate(
            [_padded(b.obstacle_velocity, most, 0.0, 1) for b in beliefs]
        ),
        obstacle_radius=np.concatenate([_padded(b.obstacle_radius, most, 0.0, 1) for b in beliefs]),
    )


def room_walls(settings: LookaheadSettings) -> F64:
    """(W, 4) the room's walls: `settings.walls`, else the square of `room_size_m`."""
    if settings.walls:
        return np.array(settings.walls, dtype=np.float64).reshape(-1, 4)
    return box_walls(settings.room_size_m)


def beam_angles(num_beams: int) -> F64:
    """(B,) the policy's beam angles: beam i at i * 2 pi / B from the heading, counter-clockwise
    (`contracts.policy_file.BEAM_CONVENTION`)."""
    return np.arange(num_beams, dtype=np.float64) * (2 * math.pi / num_beams)


def straight_misses(
    xy: F64, velocity: F64, lag_s: float, now_xy: F64, box: tuple[F64, F64]
) -> list[tuple[float, float]]:
    """(miss, speed) of each moving track at `xy` (M, 2) with `velocity` (M, 2), forecast in
    a straight line `lag_s` ahead, against the nearest track now (`now_xy` (K, 2)); forecasts
    that leave the `box` less a metre (a bounce, not a turn) or land `TURN_GATE_M` from every
    track (another obstacle, or none) are left out."""
    if not len(xy) or not len(now_xy):
        return []
    forecast = xy + velocity * lag_s
    inside = ((forecast > box[0] + 1.0) & (forecast < box[1] - 1.0)).all(axis=1)
    miss = np.linalg.norm(forecast[:, None] - now_xy[None], axis=-1).min(axis=1)
    speed = np.hypot(velocity[:, 0], velocity[:, 1])
    kept = inside & (miss < TURN_GATE_M)
    return list(zip(miss[kept].tolist(), speed[kept].tolist(), strict=True))
