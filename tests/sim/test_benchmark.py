"""BARN's protocol: one run per world, its clock, its metric, and loops."""

from dataclasses import replace

import numpy as np
import pytest

from qnav.contracts.motion import Outcome
from qnav.sim.benchmark import looped, run_benchmark, score, top_speed_mps
from qnav.sim.config import scenario
from qnav.sim.evaluate import GoToTargetAgent
from qnav.sim.layouts import layouts_of


def test_a_path_that_comes_back_after_going_away_loops() -> None:
    t = np.linspace(0, 2 * np.pi, 200)
    circle = np.stack([np.cos(t), np.sin(t)], axis=1)  # a 1 m circle in 40 s
    assert looped(circle, 0.2)
    line = np.stack([np.linspace(0, 10, 200), np.zeros(200)], axis=1)
    assert not looped(line, 0.2)
    turning_in_place = np.zeros((200, 2))
    assert not looped(turning_in_place, 0.2)
    # Back where it was, but sooner than 10 s (the circle in 8 s): not a loop.
    assert not looped(circle[::5], 0.2)


def test_the_clock_starts_when_the_robot_has_moved_a_tenth_of_a_metre() -> None:
    config = scenario("barn")
    layouts = layouts_of(replace(config.layout, worlds=2))
    assert layouts is not None
    start = layouts.start_pose[0, :2]
    # World 0 waits 10 steps, then drives 100 steps to the goal; world 1 collides at once.
    path = [start] * 10 + [start + np.array([0.0, 0.1 * k]) for k in range(1, 101)]
    result = score(
        config,
        layouts=layouts,
        label="test",
        outcomes=np.array([Outcome.SUCCESS, Outcome.COLLISION]),
        lengths=np.array([110, 3]),
        paths={0: path, 1: [start] * 3},
    )
    first, second = result.runs
    assert first.time_s == pytest.approx(100 * 0.2)
    optimal = layouts.path_length_m[0] / top_speed_mps(config)
    assert first.metric == pytest.approx(round(optimal / max(20.0, 2 * optimal), 4))
    assert (second.outcome, second.metric) == ("collision", 0.0)
    assert result.success == 0.5 and result.collision == 0.5


def test_every_world_of_the_set_is_run_once_in_order() -> None:
    config = replace(scenario("barn"), layout=replace(scenario("barn").layout, worlds=10))
    result = run_benchmark(config, GoToTargetAgent(), "goto", num_worlds=4)
    assert [run.world for run in result.runs] == list(range(10))
    assert result.success + result.collision + result.timeout == pytest.approx(1.0)
