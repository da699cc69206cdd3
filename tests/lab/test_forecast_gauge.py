"""The forecast gauge (`lab.forecast_gauge`): its collision figures are shares of the collisions
(they were counts: "unseen 2.000"), an alarm's lead counts the decisions the policy's action
stayed too risky, an escape is found where one exists and not where none does, and a short run
gives figures in range."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qnav.controller.lookahead import LookaheadSettings
from qnav.controller.perception import TrackerSettings
from qnav.lab.forecast_gauge import (
    STORY_FIGURES,
    Choice,
    Moment,
    Story,
    alarm_lead,
    changed,
    escapes,
    gauge,
    story_figures,
    true_path,
)
from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings
from qnav.tracking import world_lookahead

POLICY = "tests/data/stack/obstacles-inertia.onnx"


def story(
    *,
    static: bool = False,
    unseen: bool = False,
    stopped: bool = False,
    flank: bool = False,
    alarm_lead: int = 0,
    escape_lead: int = 0,
) -> Story:
    return Story(static, unseen, stopped, flank, alarm_lead, escape_lead)


def test_the_collision_figures_are_shares_of_the_collisions_not_counts() -> None:
    stories = [
        story(static=True),
        story(unseen=True, stopped=True),
        story(unseen=True, flank=True, alarm_lead=2, escape_lead=5),  # seen while escapable
        story(alarm_lead=3, escape_lead=8),  # the alarm came after the last escape: late
    ]
    figures = story_figures(stories, period_s=0.2)
    assert figures["static"] == 0.25
    assert figures["unseen"] == 0.5
    assert figures["stopped"] == figures["flank"] == 0.25
    assert figures["no_alarm"] == figures["no_escape"] == 0.5
    assert figures["late"] == 0.5
    assert figures["alarm_lead_s"] == pytest.approx(0.5)  # median of 0.4 and 0.6 s
    assert figures["escape_lead_s"] == pytest.approx(1.3)
    assert all(0.0 <= figures[k] <= 1.0 for k in ("static", "unseen", "stopped", "late"))
    assert set(story_figures([], 0.2)) == set(STORY_FIGURES)
    assert all(math.isnan(v) for v in story_figures([], 0.2).values())


def test_an_alarm_lasts_while_the_policys_own_action_stays_too_risky() -> None:
    def choice(greedy_risk: float) -> Choice:
        return Choice(taken=1, greedy=0, risks=np.array([greedy_risk, 0.0, 0.0]))

    choices = [choice(0.9), choice(0.1), choice(0.4), choice(0.3), choice(0.8)]
    assert alarm_lead(choices, overrule_share=0.3) == 3
    assert alarm_lead([*choices, choice(0.2)], overrule_share=0.3) == 0
    assert alarm_lead([None, choice(0.5)], overrule_share=0.3) == 1  # before the first: none


def moment(robot_xy: tuple[float, float], obstacle_xy: list[tuple[float, float]]) -> Moment:
    count = len(obstacle_xy)
    return Moment(
        np.array([*robot_xy, 0.0]),
        np.zeros(2),
        np.array(obstacle_xy, dtype=np.float64).reshape(count, 2),
        np.zeros((count, 2)),
        static_m=5.0,
        moving_m=5.0,
    )


def test_an_escape_is_found_where_one_exists_and_not_where_none_does() -> None:
    world = scenario("obstacles-inertia")
    car = world_lookahead(world, LookaheadSettings(room_size_m=10.0), TrackerSettings())
    radius = np.full(1, 0.2)
    random = np.random.default_rng(0)
    # An obstacle passing 1 m ahead from the left: standing still lets it pass.
    passing = np.array([[[6.0, 8.0 - 0.5 * k]] for k in range(1, 12)])
    assert escapes(car.model, moment((5.0, 5.0), [(6.0, 8.0)]), passing, radius, random)
    # One that comes straight at the robot from behind, faster than it drives: none escapes.
    chasing = np.array([[[3.0 + 0.3 * k, 5.0]] for k in range(1, 12)])
    assert not escapes(car.model, moment((5.0, 5.0), [(3.0, 5.0)]), chasing, radius, random)


def test_the_true_path_is_the_truth_then_straight_on() -> None:
    box = (np.zeros(2), np.full(2, 10.0))
    moments = [moment((1.0, 1.0), [(2.0, 2.0 + k)]) for k in range(3)]
    last = moments[-1]._replace(obstacle_velocity=np.array([[1.0, 0.0]]))
    path = true_path([*moments[:-1], last], box, np.full(1, 0.2), period_s=0.2)
    assert path.shape[0] == 2 + 5 + 1  # two seen, the collision's step and five more
    np.testing.assert_allclose(path[:2, 0], [[2.0, 3.0], [2.0, 4.0]])
    np.testing.assert_allclose(path[2:, 0, 0], 2.0 + 0.2 * np.arange(1, 7))


def test_a_short_run_gives_figures_in_range() -> None:
    world, lookahead, tracker = changed(6, ["lookahead.turn_std_rad=0.3"])
    assert world.obstacles.heading_walk_rad == 0.3 and lookahead.turn_std_rad == 0.3
    report = gauge(world, POLICY, EvalSettings(episodes=4, seed=12345), lookahead, tracker)
    assert report["collisions"] == round(report["collisions"]) <= 4
    for key in ("success", "blind_success", "found", "covered_1s"):
        assert 0.0 <= report[key] <= 1.0
    for key in STORY_FIGURES:  # shares in [0, 1], leads in seconds (NaN: no collision)
        limit = math.inf if key.endswith("_s") else 1.0
        assert math.isnan(report[key]) or 0.0 <= report[key] <= limit
    assert report["steps"] > 0 and report["blind_steps"] > 0
