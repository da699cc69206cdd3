"""Worlds of static layouts: BARN's start and goal, its reach, collisions with cylinders."""

import numpy as np

from qnav.contracts.actions import Action
from qnav.contracts.motion import Outcome
from qnav.sim import barn
from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings, episode_outcomes
from qnav.sim.mapplan import MapPlanner
from qnav.sim.world import BatchedWorld, reset, step


def test_barn_episodes_start_at_barns_start_in_the_benchmarks_order() -> None:
    config = scenario("barn")
    state = reset(config, np.full(4, 9), np.array([0, 1, 299, 300]))
    assert state.layout is not None
    assert state.layout.tolist() == [0, 1, 299, 0]
    np.testing.assert_allclose(state.pose, np.tile(barn.START_POSE, (4, 1)))
    np.testing.assert_allclose(state.target_xy, np.tile([-2.25, 13.0], (4, 1)))


def test_the_goal_counts_within_a_metre_and_a_cylinder_ends_the_episode() -> None:
    config = scenario("barn")
    state = reset(config, np.zeros(2, np.int64), np.zeros(2, np.int64))
    # World 0: 1.1 m short of the goal, then 0.95 m; world 1: touching a wall cylinder.
    pose = np.array([[-2.25, 11.9, np.pi / 2], [-0.40, 3.0, 0.0]])
    state = state._replace(pose=pose)
    state, observation, transition = step(config, state, np.full(2, Action.LEFT))
    assert transition.outcome.tolist() == [Outcome.RUNNING, Outcome.COLLISION]
    assert observation.clearance_m[1] < 0.3
    state = state._replace(pose=np.array([[-2.25, 12.05, np.pi / 2], [-2.25, 3.0, 0.0]]))
    _, _, transition = step(config, state, np.full(2, Action.LEFT))
    assert transition.outcome.tolist() == [Outcome.SUCCESS, Outcome.RUNNING]


def test_the_lidar_sees_the_corridor_and_nothing_beyond_the_field() -> None:
    world = BatchedWorld(scenario("barn"), 1)
    observation = world.reset(seed=0)
    assert observation.scan_m is not None
    scan = observation.scan_m[0]
    # Facing +y from x = -2.25 between walls at -4.425 and -0.075: about 2.1 m to each side.
    left, right = scan[180], scan[540]
    assert 1.9 < left < 2.2 and 1.9 < right < 2.2
    assert np.isfinite(scan).mean() > 0.5


def test_the_planner_given_the_map_reaches_the_goal() -> None:
    config = scenario("clutter")
    config = config.__class__(
        **{
            **config.__dict__,
            "layout": config.layout.__class__(
                source="cave+rooms", split="validation", worlds=8, order="cycle"
            ),
        }
    )
    outcomes, _ = episode_outcomes(
        config, MapPlanner(config), EvalSettings(episodes=8, num_worlds=8)
    )
    assert (outcomes == Outcome.SUCCESS).sum() >= 7
