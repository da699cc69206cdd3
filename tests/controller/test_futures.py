"""The forecast's motion hypotheses (`controller.futures`): the straight line where it has no
spread, bounces however many, a spread that grows with the horizon, each car's own draws."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qnav.contracts.motion import move_obstacles
from qnav.controller.futures import (
    fold,
    informative_horizon_s,
    random_futures,
    turn_from_misses,
)
from qnav.controller.lookahead import Lookahead, LookaheadSettings, risks_of
from qnav.controller.perception import TrackerSettings
from qnav.sim import world as sim_world
from qnav.sim.config import scenario
from qnav.sim.world import observe, reset
from qnav.tracking import world_lookahead

BOX = (np.zeros(2), np.full(2, 10.0))


def test_a_fold_is_the_bounce_of_a_straight_line_however_many_times() -> None:
    xy = np.array([[1.0, 9.0], [5.0, 5.0], [9.5, 0.4]])
    velocity = np.array([[-1.5, 0.7], [1.2, -1.4], [0.9, 1.3]])
    radius = np.array([0.2, 0.3, 0.25])
    futures = random_futures(
        xy, velocity, radius, steps=40, period_s=0.2, futures=1, spread=(0.0, 0.0), box=BOX,
        random=np.random.default_rng(0),
    )  # fmt: skip
    moved, moving = xy, velocity
    for step in range(40):  # one bounce per axis per step at most: the plain simulation's law
        moved, moving = move_obstacles(moved, moving, radius[:, None], 10.0, 0.2)
        np.testing.assert_allclose(futures.xy[step, 0, 0], moved, atol=1e-9)
    folded = fold(np.array([-0.3, 10.3, 21.0, -19.5]), 0.0, 10.0)
    np.testing.assert_allclose(folded, [0.3, 9.7, 1.0, 0.5], atol=1e-12)  # 21 and -19.5: twice


def test_the_first_future_is_the_straight_line_and_what_stands_stands_in_every_future() -> None:
    xy = np.array([[3.0, 3.0], [6.0, 6.0]])
    velocity = np.array([[1.0, 0.0], [0.0, 0.0]])
    futures = random_futures(
        xy, velocity, np.full(2, 0.2), steps=10, period_s=0.2, futures=50, spread=(0.6, 0.3),
        box=BOX, random=np.random.default_rng(1),
    )  # fmt: skip
    straight = xy[0] + velocity[0] * 0.2 * np.arange(1, 11)[:, None]
    np.testing.assert_allclose(futures.xy[:, 0, 0, 0], straight, atol=1e-12)
    assert np.all(futures.xy[:, 0, :, 1] == xy[1])
    assert futures.xy[:, 0, 1:, 0].std(axis=1).max() > 0.1  # the walker's futures spread


def test_the_spread_of_a_walkers_heading_grows_as_the_square_root_of_time() -> None:
    futures = random_futures(
        np.array([[5.0, 5.0]]), np.array([[1.0, 0.0]]), np.array([0.1]), steps=10,
        period_s=0.1, futures=4000, spread=(0.5, 0.0), box=(np.full(2, -100.0), np.full(2, 100.0)),
        random=np.random.default_rng(2),
    )  # fmt: skip
    step = np.diff(np.concatenate([np.full((1, 4000, 2), 5.0), futures.xy[:, 0, :, 0]]), axis=0)
    heading = np.arctan2(step[..., 1], step[..., 0])  # (H, K)
    for h in (1, 4, 9):
        assert heading[h - 1].std() == pytest.approx(0.5 * math.sqrt(0.1 * h), rel=0.06)


def test_each_car_draws_its_own_futures_as_it_would_alone() -> None:
    world = scenario("obstacles-inertia")
    settings = LookaheadSettings(turn_std_rad=0.5, speed_std_mps=0.2)
    state = reset(world, np.array([3, 4]), np.array([0, 0]))
    scan = observe(world, state).scan_m
    assert scan is not None

    def cars() -> list:  # type: ignore[type-arg]
        made = [world_lookahead(world, settings, TrackerSettings()) for _ in range(2)]
        for car, pose, ranges in zip(made, state.pose, scan, strict=True):
            car.observe(0.0, pose, 0.0, ranges)
            car.observe(0.2, pose, 0.2, ranges)
        return made

    together = risks_of(cars(), list(state.target_xy))
    alone = [risks_of([car], [target]) for car, target in zip(cars(), state.target_xy, strict=True)]
    np.testing.assert_array_equal(together, np.concatenate(alone))


def test_a_room_given_by_its_walls_as_segments_is_the_square_given_by_its_side() -> None:
    world = scenario("obstacles-inertia")
    state = reset(world, np.array([6]), np.array([2]))
    scan = observe(world, state).scan_m
    assert scan is not None
    side = LookaheadSettings(room_size_m=10.0)
    walls = LookaheadSettings(
        walls=(
            (0.0, 0.0, 10.0, 0.0),
            (10.0, 0.0, 10.0, 10.0),
            (10.0, 10.0, 0.0, 10.0),
            (0.0, 10.0, 0.0, 0.0),
        )
    )
    risks = []
    for settings in (side, walls):
        car = Lookahead(
            settings,
            TrackerSettings(),
            dynamics=world.dynamics,
            robot_radius_m=world.robot_radius_m,
            control_period_s=world.control_period_s,
            beam_angles_rad=world.lidar.beam_angles_rad() if world.lidar else np.zeros(0),
        )
        for frame in range(3):
            car.observe(0.2 * frame, state.pose[0], 0.2 * frame, scan[0])
        risks.append(car.risks(state.target_xy[0]))
    np.testing.assert_array_equal(risks[0], risks[1])


def test_the_turn_measured_from_straight_line_misses_is_the_walks_own() -> None:
    """Walkers at 1 m/s whose heading walks 0.67 rad per second (0.3 per 0.2 s, the robustness
    table's row 6): their straight-line forecasts' misses after 1 s give back the spread, to
    about the square-root-of-time law's precision; walkers that do not turn give 0."""
    random = np.random.default_rng(5)
    period_s, steps, walkers = 0.2, 5, 4000
    heading = np.cumsum(random.normal(0.0, 0.3, (walkers, steps)), axis=1)
    path = np.stack([np.cos(heading), np.sin(heading)], axis=-1).sum(axis=1) * period_s
    miss = np.linalg.norm(path - np.array([1.0, 0.0]), axis=1)
    measured = turn_from_misses(miss, np.ones(walkers), lag_s=1.0)
    assert measured == pytest.approx(0.3 / math.sqrt(period_s), rel=0.25)
    assert turn_from_misses(np.zeros(3), np.ones(3), 1.0) == 0.0
    assert turn_from_misses(np.zeros(0), np.zeros(0), 1.0) == 0.0


def test_the_informative_horizon_shortens_as_the_obstacles_turn_more() -> None:
    bounds = (2.0, 6.0)
    assert informative_horizon_s(0.0, 1.0, 1.0, bounds) == 6.0  # straight lines: all of it
    assert informative_horizon_s(0.22, 1.0, 1.0, bounds) == pytest.approx(3.96, abs=0.05)
    assert informative_horizon_s(0.67, 1.0, 1.0, bounds) == 2.0  # 1.9 s, at least 2
    assert informative_horizon_s(0.05, 1.0, 1.0, bounds) == 6.0  # 10.6 s, at most 6


def test_a_car_that_measures_turning_forecasts_straight_obstacles_straight() -> None:
    """In the simulator's own world (straight lines) the measured spread stays 0 and the shield
    counts collisions over its whole horizon: the same risks as without the measure."""
    world = scenario("obstacles-inertia")
    state = reset(world, np.array([3]), np.array([0]))
    plain = world_lookahead(world, LookaheadSettings(), TrackerSettings())
    measuring = world_lookahead(world, LookaheadSettings(measure_turning=True), TrackerSettings())
    for k in range(12):
        scan = observe(world, state).scan_m
        assert scan is not None
        for car in (plain, measuring):
            car.observe(0.2 * k, state.pose[0], 0.2 * k, scan[0])
        state, _, _ = sim_world.step(world, state, np.array([1]))  # turn in place
    assert len(measuring.misses) >= 1
    assert len(measuring.misses) >= 10 and measuring.turn_std() == 0.0
    assert measuring.counted_steps() == measuring.horizon
    target = [state.target_xy[0]]
    np.testing.assert_array_equal(risks_of([plain], target), risks_of([measuring], target))
