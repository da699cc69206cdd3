"""The decisive-state gauge: states where the choice matters, and how a policy is judged there."""

import json
from pathlib import Path

import numpy as np
import pytest

from qnav.contracts.actions import NUM_ACTIONS
from qnav.lab.decisive import (
    DRIVERS,
    DecisiveStates,
    GaugeSettings,
    cached,
    collect,
    constant_choice,
    go_to_target_choices,
    perception_ceiling,
    random_expectation,
    score,
)
from qnav.lab.oracle import StateError, doomed_actions
from qnav.sim.config import scenario
from qnav.sim.world import reset
from tests.command import run_qnav

SMALL = GaugeSettings(episodes_per_driver=6, max_episode_steps=40, num_worlds=6, seed=3)


@pytest.fixture(scope="module")
def states() -> DecisiveStates:
    return collect(scenario("obstacles-increment"), SMALL)


def test_every_kept_state_has_a_doomed_and_a_safe_action(states: DecisiveStates) -> None:
    assert len(states.doomed) > 0
    assert states.doomed.any(axis=1).all()
    assert (~states.doomed).any(axis=1).all()
    assert states.windows.shape == (len(states.doomed), SMALL.window, 720 + 3)
    assert set(np.unique(states.driver)) <= set(range(len(DRIVERS)))
    assert (states.visited >= np.bincount(states.driver, minlength=len(DRIVERS))).all()


def test_safe_and_doomed_choices_score_one_and_zero(states: DecisiveStates) -> None:
    safe_choice = np.argmin(states.doomed, axis=1)
    doomed_choice = np.argmax(states.doomed, axis=1)
    assert score(states, safe_choice).safe == 1.0
    assert score(states, doomed_choice).safe == 0.0
    expected = float((~states.doomed).sum()) / states.doomed.size
    assert random_expectation(states).safe == pytest.approx(expected)


def test_a_blind_choice_scores_one_half_balanced_whatever_the_mix_of_patterns() -> None:
    # Every doom pattern with one or two of three actions doomed, in very unequal numbers, so
    # the plain share rewards always taking the action most often safe.
    patterns = [[1, 0, 0]] * 50 + [[0, 1, 0]] * 3 + [[0, 0, 1]] * 7
    patterns += [[1, 1, 0]] * 2 + [[1, 0, 1]] * 4 + [[0, 1, 1]] * 30
    doomed = np.array(patterns, dtype=bool)
    count = len(doomed)
    world = reset(scenario("obstacles-increment"), np.zeros(count, np.int64), np.arange(count))
    states = DecisiveStates(
        windows=np.zeros((count, 1, 4), dtype=np.float32),
        collide_share=doomed.astype(np.float32),
        world=world,
        driver=np.zeros(len(doomed), dtype=np.int8),
        taken=np.zeros(len(doomed), dtype=np.int8),
        visited=np.array([len(doomed), 0]),
    )
    assert random_expectation(states).balanced == pytest.approx(0.5)
    for action in range(NUM_ACTIONS):
        assert constant_choice(states, action).balanced == pytest.approx(0.5)
    assert constant_choice(states, 0).safe != pytest.approx(0.5)
    assert score(states, np.argmin(doomed, axis=1)).balanced == 1.0
    assert score(states, np.argmax(doomed, axis=1)).balanced == 0.0


def test_an_action_is_doomed_exactly_where_all_its_continuations_collide(
    states: DecisiveStates,
) -> None:
    assert ((states.collide_share >= 0) & (states.collide_share <= 1)).all()
    np.testing.assert_array_equal(states.doomed, states.collide_share == 1.0)
    # Kept world states are the true states: doom recomputed from them is the label.
    np.testing.assert_array_equal(
        doomed_actions(scenario("obstacles-increment"), states.world), states.doomed
    )


def test_the_best_choice_knowing_the_exact_state_is_always_safe_and_errors_cost(
    states: DecisiveStates,
) -> None:
    world = scenario("obstacles-increment")
    exact = perception_ceiling(world, states, StateError(0.0, 0.0, 0.0, 0.0), draws=2)
    assert exact.safe == 1.0 and exact.balanced == 1.0
    blurred = perception_ceiling(world, states, StateError(2.0, 2.0, 0.0, 0.0), draws=4)
    assert blurred.safe < 1.0


def test_go_to_target_is_judged_on_the_newest_frames_bearing(states: DecisiveStates) -> None:
    choices = go_to_target_choices(states)
    assert choices.shape == (len(states.doomed),)
    assert set(np.unique(choices)) <= set(range(NUM_ACTIONS))


def test_the_action_taken_is_the_drivers_own(states: DecisiveStates) -> None:
    by_go_to_target = states.driver == DRIVERS.index("go-to-target")
    assert by_go_to_target.any() and (~by_go_to_target).any()
    assert (states.taken[by_go_to_target] == go_to_target_choices(states)[by_go_to_target]).all()
    # The planner mostly keeps clear of doom: its own actions are rarely the doomed ones.
    planner = ~by_go_to_target
    taken_doomed = states.doomed[np.flatnonzero(planner), states.taken[planner]]
    assert taken_doomed.mean() < 0.5


def test_a_layout_with_an_obstacle_on_the_robot_dooms_every_action() -> None:
    config = scenario("obstacles-increment")
    state = reset(config, np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64))
    ahead = state.pose[:, :2] + 0.3 * np.stack(
        [np.cos(state.pose[:, 2]), np.sin(state.pose[:, 2])], 1
    )
    state = state._replace(
        obstacle_xy=np.repeat(ahead[:, None], state.obstacle_xy.shape[1], axis=1),
        obstacle_velocity=np.zeros_like(state.obstacle_velocity),
    )
    assert doomed_actions(config, state).all()


def test_the_cache_returns_what_was_collected_and_keys_on_the_settings(tmp_path: Path) -> None:
    world = scenario("obstacles-increment")
    tiny = GaugeSettings(episodes_per_driver=2, max_episode_steps=10, num_worlds=2)
    first = cached(world, tiny, directory=tmp_path)
    again = cached(world, tiny, directory=tmp_path)
    for name in DecisiveStates._fields:
        if name != "world":
            np.testing.assert_array_equal(getattr(first, name), getattr(again, name))
    for a, b in zip(first.world, again.world, strict=True):
        np.testing.assert_array_equal(a, b)
    cached(world, GaugeSettings(episodes_per_driver=1, max_episode_steps=10), directory=tmp_path)
    assert len(list((tmp_path / "decisive").glob("*.npz"))) == 2


def test_qnav_gauge_prints_the_baselines_of_a_world() -> None:
    world = ("--scenario", "obstacles-increment")
    result = run_qnav("lab", "gauge", *world, "--episodes", "10", "--json")
    assert result.returncode == 0, result.stderr
    rows = [json.loads(line) for line in result.stdout.splitlines() if line.startswith("{")]
    assert [row["policy"] for row in rows] == [
        "random",
        "go-to-target",
        "always forward",
        "always left",
        "always right",
    ]
    assert all(0.0 <= row["safe"] <= 1.0 and 0.0 <= row["balanced"] <= 1.0 for row in rows)


def test_qnav_gauge_refuses_a_world_without_moving_obstacles() -> None:
    result = run_qnav("lab", "gauge", "--scenario", "walls-increment")
    assert result.returncode != 0
    assert "no moving obstacles" in result.stderr
