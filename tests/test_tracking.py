"""The controller's look ahead on simulated cars: the shield it puts over a policy, and eval's
refusal of a shield without one, and go-to-target shielded as a policy."""

import json
import subprocess
import sys

import numpy as np

from qnav.contracts.lookahead import shielded_actions
from qnav.controller.lookahead import LookaheadSettings
from qnav.controller.perception import TrackerSettings
from qnav.sim.config import SCENARIOS
from qnav.sim.evaluate import EvalSettings, GoToTargetAgent, evaluate, go_to_target
from qnav.sim.world import BatchedWorld
from qnav.tracking import GoToTargetValues, LookaheadAgent

INERTIA = SCENARIOS["obstacles-inertia"]


def test_the_shield_takes_the_best_valued_of_the_least_risky_actions() -> None:
    q = np.array([[3.0, 2.0, 1.0], [3.0, 2.0, 1.0], [3.0, 2.0, 1.0]])
    shares = np.array([[0.0, 0.0, 0.0], [1.0, 0.2, 0.2], [1.0, 0.5, 0.2]])
    assert shielded_actions(q, shares, 0.0).tolist() == [0, 1, 2]


def test_the_shield_keeps_the_policys_action_below_the_overrule_share() -> None:
    q = np.array([[3.0, 2.0, 1.0], [3.0, 2.0, 1.0], [1.0, 2.0, 3.0]])
    shares = np.array([[0.29, 0.0, 0.0], [0.3, 0.2, 0.1], [0.0, 0.0, 1.0]])
    assert shielded_actions(q, shares, 0.3).tolist() == [0, 2, 1]
    assert shielded_actions(q, shares, 0.0).tolist() == [1, 2, 1]
    assert shielded_actions(q, shares, 1.0).tolist() == [0, 0, 1]


def test_the_shield_turns_the_blind_controller_into_one_that_dodges() -> None:
    episodes = 32
    settings = EvalSettings(episodes=episodes, num_worlds=episodes, seed=77, max_episode_steps=100)
    blind = evaluate(INERTIA, GoToTargetAgent(), settings)
    shield = LookaheadAgent(
        GoToTargetValues(episodes),
        INERTIA,
        episodes,
        tracker=TrackerSettings(),
        lookahead=LookaheadSettings(mode="shield"),
        seed=77,
    )
    shielded = evaluate(INERTIA, shield, settings)
    # The blind controller collides in about a third of the episodes (0.656 success over 2000;
    # 9 of these 32); the shield must remove most of those collisions, not a lucky one or two.
    assert blind.collision * episodes >= 6
    assert shielded.collision * episodes <= blind.collision * episodes / 2
    assert 0.0 < shield.overruled_share < 0.5


def test_eval_rejects_a_shield_without_a_policy_naming_the_option() -> None:
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "qnav",
            "eval",
            "--scenario",
            "obstacles-inertia",
            "--lookahead",
            "shield",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode != 0
    assert "--lookahead" in result.stderr


def test_eval_shields_go_to_target_as_a_policy() -> None:
    command = [sys.executable, "-m", "qnav", "eval", "--scenario", "obstacles-inertia"]
    options = ["--agent", "goto", "--lookahead", "shield", "--episodes", "4", "--json"]
    result = subprocess.run(
        [*command, *options], capture_output=True, text=True, timeout=120, check=False
    )
    assert result.returncode == 0, result.stderr
    fractions = json.loads(result.stdout)
    assert sum(fractions[k] for k in ("success", "collision", "unfinished")) == 1.0


def test_go_to_target_values_its_own_choice_only() -> None:
    agent = GoToTargetValues(2)
    observation = BatchedWorld(INERTIA, 2, seed=5).reset(5)
    action = agent.act(observation)
    assert action.tolist() == go_to_target(observation.target_features()).tolist()
    assert agent.last_q.argmax(axis=1).tolist() == action.tolist()
    assert agent.last_q.sum(axis=1).tolist() == [1.0, 1.0]


def test_the_shield_keeps_the_policys_chosen_action_not_only_its_highest_valued() -> None:
    q = np.array([[3.0, 2.0, 1.0]])
    shares = np.array([[0.0, 0.0, 0.0]])
    assert shielded_actions(q, shares, 0.3, np.array([2])).tolist() == [2]
    risky = np.array([[0.0, 0.0, 0.9]])
    assert shielded_actions(q, risky, 0.3, np.array([2])).tolist() == [0]


def test_the_shipped_proximity_field_is_the_paper_robots_and_fits_each_worlds_robot() -> None:
    from qnav.controller.proximity import ProximitySettings
    from qnav.sim.config import scenario
    from qnav.tracking import fitted_proximity

    assert fitted_proximity(scenario("obstacles-inertia")) == ProximitySettings()
    barn = fitted_proximity(scenario("barn"))
    assert (barn.footprint_m, barn.travel_m) == (0.3, 0.3)
