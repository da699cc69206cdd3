"""A short look ahead: play candidate action sequences forward with the shared motion model and
score them, knowing (or believing) where the obstacles are and how fast they move.

The simulator's oracle planner (`lab.oracle`) runs it on the world's true state; the onboard
controller (`controller.lookahead`) runs the same code on what its obstacle tracker perceives.
Candidates are the structured sequences (one action held for a while, then another) plus random
ones held three steps at a time, which each caller draws its own way.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.actions import NUM_ACTIONS, forward_command, turn_command
from qnav.contracts.motion import (
    Dynamics,
    InertiaDynamics,
    Outcome,
    distance_to_segments,
    move_obstacles,
    step_robot,
    wrap_angle,
)

F64 = NDArray[np.float64]

HOLDS = (1, 3, 6, 10)
"""Steps the first action of a structured sequence is held before the second takes over."""
RANDOM_HOLD_STEPS = 3
"""Steps each action of a random candidate sequence is held."""
SCORED_CLEARANCE_M = 1.0
"""Clearance from surfaces beyond which a sequence that survives scores no better."""
_WALL_MARGIN_M = 1e-6
"""Slack on the walls' lower bound against rounding (`simulate` skips walls farther than the
clearance that counts by at least this)."""
_RUNNING, _SUCCESS, _COLLISION = int(Outcome.RUNNING), int(Outcome.SUCCESS), int(Outcome.COLLISION)
"""The outcomes as plain ints (an enum member's lookup costs more than the arithmetic here)."""


class LookaheadModel(NamedTuple):
    """What the look ahead knows of the world it forecasts."""

    dynamics: Dynamics
    """The robot's motion model (the training world's)."""
    control_period_s: float
    """Time each action of a sequence is held."""
    robot_radius_m: float
    """The paper's l: reaching within it of the target succeeds, of a surface collides."""
    obstacle_radius_m: float
    """Radius of the (cylindrical) obstacles."""
    room_size_m: float
    """Side of the square room [0, size]^2 the obstacles bounce around in."""
    wall_start: F64
    """(K, 2) start points of the solid wall segments."""
    wall_end: F64
    """(K, 2) end points of the solid wall segments."""


class Situation(Protocol):
    """The state a look ahead starts from, for N worlds (`sim.world.WorldState` is one)."""

    @property
    def pose(self) -> F64:
        """(N, 3) x, y, heading."""

    @property
    def velocity(self) -> F64:
        """(N, 2) forward speed and turn rate (zero under increment dynamics)."""

    @property
    def target_xy(self) -> F64:
        """(N, 2) the target."""

    @property
    def obstacle_xy(self) -> F64:
        """(N, M, 2) obstacle centres."""

    @property
    def obstacle_velocity(self) -> F64:
        """(N, M, 2) obstacle velocities."""


class ObstacleFutures(NamedTuple):
    """Where the obstacles go in each of several futures (a forecast's motion hypotheses), in
    place of straight lines from a `Situation`'s obstacles."""

    xy: F64
    """(H, N, K, M, 2) each obstacle's centre after each of H steps in each of K futures; a
    candidate sequence c of a world meets future c mod K."""
    radius_m: F64
    """(N, M) each obstacle's radius."""


class Rollouts(NamedTuple):
    """How each candidate sequence of each world played out."""

    outcome: NDArray[np.int8]
    """(N, S) SUCCESS, COLLISION, or RUNNING (neither within the horizon)."""
    end_step: NDArray[np.int64]
    """(N, S) the step (1-based) at which the sequence reached the target or collided; the
    horizon where it did neither."""
    score: NDArray[np.float64]
    """(N, S) the planner's score: early success best, late collision better than early,
    otherwise close to the target and clear of surfaces."""


def structured_sequences(horizon: int) -> NDArray[np.int64]:
    """(S, horizon) sequences: action a held, then action b, for every a, b and hold."""
    structured = [
        [a] * hold + [b] * (horizon - hold)
        for a in range(NUM_ACTIONS)
        for hold in (*HOLDS, horizon)
        for b in range(NUM_ACTIONS)
        if hold <= horizon
    ]
    return np.array(structured, dtype=np.int64)[:, :horizon]


def held(blocks: NDArray[np.int64], horizon: int) -> NDArray[np.int64]:
    """(..., horizon) sequences of the random actions `blocks` (..., B), each held
    `RANDOM_HOLD_STEPS` steps."""
    return blocks.repeat(RANDOM_HOLD_STEPS, axis=-1)[..., :horizon]


def candidate_sequences(random_blocks: NDArray[np.int64], horizon: int) -> NDArray[np.int64]:
    """(..., S, horizon): the structured sequences, then the random actions `random_blocks`
    (..., R, B) held `RANDOM_HOLD_STEPS` steps each."""
    shared = structured_sequences(horizon)
    structured = np.broadcast_to(shared, (*random_blocks.shape[:-2], *shared.shape))
    return np.concatenate([structured, held(random_blocks, horizon)], axis=-2)


def random_blocks_needed(horizon: int) -> int:
    """Random actions that fill a sequence of `horizon` steps, each held `RANDOM_HOLD_STEPS`."""
    return -(-horizon // RANDOM_HOLD_STEPS)


def simulate(
    model: LookaheadModel,
    state: Situation,
    sequences: NDArray[np.int64],
    futures: ObstacleFutures | None = None,
) -> Rollouts:
    """Play every candidate sequence, (S, H) shared by all worlds or (N, S, H) per world, from
    each world of `state`, the obstacles moving straight on and bouncing off the room's walls
    (or along `futures`, candidate c of a world in its future c mod K: S must be a multiple
    of K).

    A few things keep it cheap without changing a bit of the result. The obstacles' motion does
    not depend on the robot's, so it is computed once per world, not once per candidate. A wall
    only matters to a candidate within `SCORED_CLEARANCE_M` of it (nearer, it caps the score's
    clearance or collides), which a candidate that started `d` from every wall and has driven a
    path of length `s` cannot be while `d - s` is at least that: the walls are measured only for
    the candidates that may be (a robot larger than that clearance widens it). And the robots
    move by `robot_paths`, the motion model's own arithmetic with fewer calls.
    """
    worlds = state.pose.shape[0]
    if sequences.ndim == 2:
        sequences = np.broadcast_to(sequences, (worlds, *sequences.shape))
    candidates, horizon = sequences.shape[1:]
    actions = sequences.reshape(worlds * candidates, horizon)  # world-major like the states
    pose = np.repeat(state.pose, candidates, axis=0)
    velocity = np.repeat(state.velocity, candidates, axis=0)
    obstacles, obstacle_velocity = state.obstacle_xy, state.obstacle_velocity
    target_x, target_y = np.ascontiguousarray(np.repeat(state.target_xy, candidates, axis=0).T)
    count = worlds * candidates
    result = np.full(count, _RUNNING, dtype=np.int8)
    end_step = np.full(count, horizon, dtype=np.int64)
    score = np.zeros(count)
    alive = np.ones(count, dtype=bool)
    distance = gap = np.zeros(count)
    start_wall_m = np.repeat(
        distance_to_segments(state.pose[:, :2], model.wall_start, model.wall_end), candidates
    )
    driven_m = np.zeros(count)
    x, y = pose[:, 0], pose[:, 1]
    radius = model.robot_radius_m
    paths = robot_paths(model.dynamics, model.control_period_s, pose, velocity, actions)
    for h, (next_x, next_y) in enumerate(paths):
        driven_m = driven_m + np.hypot(next_x - x, next_y - y)
        x, y = next_x, next_y
        dx, dy = target_x - x, target_y - y
        distance = np.sqrt(dx * dx + dy * dy)  # np.linalg.norm's sum of squares, bit for bit
        if futures is None:
            obstacles, obstacle_velocity = move_obstacles(
                obstacles,
                obstacle_velocity,
                model.obstacle_radius_m,
                model.room_size_m,
                model.control_period_s,
            )
            gap = _clearance(model, x, y, obstacles, start_wall_m - driven_m)
        else:
            gap = _clearance_among(
                model, x, y, futures, step=h, wall_bound_m=start_wall_m - driven_m
            )
        success = distance < radius  # `motion.outcome`: reaching the target comes first
        won, lost = alive & success, alive & (gap < radius) & ~success
        result[won], result[lost] = _SUCCESS, _COLLISION
        ended = won | lost
        end_step[ended] = h + 1
        score[won], score[lost] = 1000.0 - h, -1000.0 + h
        alive &= ~ended
    score[alive] = -10.0 * distance[alive] + np.minimum(gap[alive], SCORED_CLEARANCE_M)
    shape = (worlds, candidates)
    return Rollouts(result.reshape(shape), end_step.reshape(shape), score.reshape(shape))


def robot_paths(
    dynamics: Dynamics, period_s: float, pose: F64, velocity: F64, actions: NDArray[np.int64]
) -> Iterator[tuple[F64, F64]]:
    """The (x, y) of every robot (C,) after each step of its actions (C, H), bit for bit those
    of `motion.step_robot` step after step. Under inertia the physics substeps of
    `motion.step_velocity_lag` are written out here with the same operations on the same values,
    but the commanded velocities of every step are computed once, before the first, and the
    lags' errors once per substep: a step costs half the calls (the controller's one car pays
    for calls more than for arithmetic)."""
    if not isinstance(dynamics, InertiaDynamics):
        for h in range(actions.shape[1]):
            pose, velocity = step_robot(pose, velocity, actions[:, h], dynamics, period_s)
            yield pose[:, 0], pose[:, 1]
        return
    substeps = max(1, round(period_s / dynamics.physics_dt_s))
    dt = period_s / substeps
    tau_v, tau_w = dynamics.linear_time_constant_s, dynamics.angular_time_constant_s
    decay_v, decay_w = math.exp(-dt / tau_v), math.exp(-dt / tau_w)
    gain_v, gain_w = 1.0 - decay_v, 1.0 - decay_w
    # The commanded speed and turn rate of every step (H, C), and their products with dt.
    by_step = np.ascontiguousarray(actions.T)  # each step's actions contiguous
    speed_targets = forward_command(by_step) * dynamics.max_speed_mps
    rate_targets = turn_command(by_step) * dynamics.max_turn_rate_radps
    speed_targets_dt, rate_targets_dt = speed_targets * dt, rate_targets * dt
    x, y, heading = pose[:, 0], pose[:, 1], pose[:, 2]
    speed, rate = velocity[:, 0], velocity[:, 1]
    for h in range(actions.shape[1]):
        speed_target, rate_target = speed_targets[h], rate_targets[h]
        speed_target_dt, rate_target_dt = speed_targets_dt[h], rate_targets_dt[h]
        for _ in range(substeps):
            # step_velocity_lag: the exact integrals over the substep, then the end values.
            speed_error, rate_error = speed - speed_target, rate - rate_target
            distance = speed_target_dt + speed_error * tau_v * gain_v
            turned = rate_target_dt + rate_error * tau_w * gain_w
            mid_heading = heading + 0.5 * turned
            x = x + distance * np.cos(mid_heading)
            y = y + distance * np.sin(mid_heading)
            heading = heading + turned
            speed = speed_target + speed_error * decay_v
            rate = rate_target + rate_error * decay_w
        heading = wrap_angle(heading)
        yield x, y


def _clearance(model: LookaheadModel, x: F64, y: F64, obstacles: F64, wall_bound_m: F64) -> F64:
    """Each candidate's (C = N * S) distance from (x, y) to the nearest surface, its world's
    obstacles (N, M, 2) and the walls where `wall_bound_m` (C,), a lower bound of its wall
    distance, does not put them beyond `SCORED_CLEARANCE_M` (there the walls are left out, which
    changes neither the score nor the outcome: `simulate`)."""
    worlds = obstacles.shape[0]
    gap = np.full(x.shape[0], np.inf)
    if obstacles.shape[1]:
        # Obstacles first (M, N, S): the minimum over them runs along whole rows of candidates,
        # where a reduction over a short last axis would loop per candidate.
        centres = obstacles.transpose(1, 0, 2)[:, :, None]
        ox = centres[..., 0] - x.reshape(worlds, -1)
        oy = centres[..., 1] - y.reshape(worlds, -1)
        nearest = np.sqrt((ox * ox + oy * oy).min(axis=0)) - model.obstacle_radius_m
        gap = nearest.reshape(-1)
    reach_m = max(SCORED_CLEARANCE_M, model.robot_radius_m) + _WALL_MARGIN_M
    near = np.flatnonzero(wall_bound_m < reach_m)
    if near.size:
        points = np.stack([x[near], y[near]], axis=1)
        walls = distance_to_segments(points, model.wall_start, model.wall_end)
        gap[near] = np.minimum(walls, gap[near])
    return gap


def _clearance_among(
    model: LookaheadModel, x: F64, y: F64, futures: ObstacleFutures, *, step: int, wall_bound_m: F64
) -> F64:
    """`_clearance` among the obstacles of `futures` after `step`: each candidate (C = N * S)
    against its own future's obstacles, each of its own radius."""
    centres = futures.xy[step]  # (N, K, M, 2)
    worlds, futures_count = centres.shape[:2]
    gap = np.full(x.shape[0], np.inf)
    if centres.shape[2]:
        # Obstacles first (M, N, 1, K) against candidates (N, S / K, K): the minimum over the
        # obstacles runs along whole rows of candidates.
        ordered = centres.transpose(2, 0, 1, 3)[:, :, None]
        ox = ordered[..., 0] - x.reshape(worlds, -1, futures_count)
        oy = ordered[..., 1] - y.reshape(worlds, -1, futures_count)
        radius = futures.radius_m.T[:, :, None, None]
        gap = (np.sqrt(ox * ox + oy * oy) - radius).min(axis=0).reshape(-1)
    reach_m = max(SCORED_CLEARANCE_M, model.robot_radius_m) + _WALL_MARGIN_M
    near = np.flatnonzero(wall_bound_m < reach_m)
    if near.size:
        points = np.stack([x[near], y[near]], axis=1)
        walls = distance_to_segments(points, model.wall_start, model.wall_end)
        gap[near] = np.minimum(walls, gap[near])
    return gap


def best_first_actions(
    model: LookaheadModel,
    state: Situation,
    sequences: NDArray[np.int64],
    futures: ObstacleFutures | None = None,
) -> NDArray[np.int64]:
    """(N,) the first action of the best-scoring candidate sequence, (S, H) shared or (N, S, H)
    per world, for each world in `state` (among `futures`' obstacles where given)."""
    worlds = state.pose.shape[0]
    if sequences.ndim == 2:
        sequences = np.broadcast_to(sequences, (worlds, *sequences.shape))
    best = np.argmax(simulate(model, state, sequences, futures).score, axis=1)
    return np.asarray(sequences[np.arange(worlds), best, 0], dtype=np.int64)


def collision_shares(
    model: LookaheadModel,
    state: Situation,
    tails: NDArray[np.int64],
    futures: ObstacleFutures | None = None,
) -> NDArray[np.float64]:
    """(N, A): the share of the continuations `tails` (N, T, H-1) that collide within H steps
    after taking each action first (1 where the action is doomed). The same continuations follow
    every first action, so actions are judged alike; with `futures` (K dividing T), continuation
    t meets the obstacles of future t mod K after every first action."""
    worlds, tail_count = tails.shape[:2]
    rollouts = simulate(model, state, first_action_sequences(tails), futures)
    collided = rollouts.outcome == Outcome.COLLISION
    return np.asarray(collided.reshape(worlds, NUM_ACTIONS, tail_count).mean(axis=2))


def first_action_sequences(tails: NDArray[np.int64]) -> NDArray[np.int64]:
    """(N, A * T, H) every first action followed by each continuation of `tails` (N, T, H-1),
    action by action: row a * T + t is action a, then continuation t."""
    worlds, tail_count = tails.shape[:2]
    first = np.repeat(np.arange(NUM_ACTIONS), tail_count)
    return np.concatenate(
        [
            np.broadcast_to(first[None, :, None], (worlds, first.size, 1)),
            np.tile(tails, (1, NUM_ACTIONS, 1)),
        ],
        axis=2,
    )


def shielded_actions(
    q: NDArray[np.floating],
    collision_share: NDArray[np.floating],
    overrule_share: float,
    chosen: NDArray[np.integer] | None = None,
) -> NDArray[np.int64]:
    """(N,) the policy's action (`chosen`; by default the highest-valued), unless at least
    `overrule_share` of the continuations after it collide: then the highest-valued among the
    least colliding. (0 overrules whenever a safer action exists; a band below which the
    policy's own action stands does better, as an overruled policy drives where it was not
    trained: docs/controller.md.)"""
    rows = np.arange(len(q))
    preferred = np.asarray(q).argmax(axis=1) if chosen is None else np.asarray(chosen)
    least = collision_share <= collision_share.min(axis=1, keepdims=True)
    safest = np.where(least, q, -np.inf).argmax(axis=1)
    keep = collision_share[rows, preferred] < overrule_share
    return np.asarray(np.where(keep, preferred, safest), dtype=np.int64)
