"""The controller's look ahead on simulated cars: the shield it puts over a policy, and eval's
refusal of a shield without one."""

import subprocess
import sys

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.lookahead import shielded_actions
from qnav.controller.lookahead import LookaheadSettings
from qnav.controller.perception import TrackerSettings
from qnav.sim.config import SCENARIOS
from qnav.sim.evaluate import EvalSettings, GoToTargetAgent, evaluate, go_to_target
from qnav.sim.world import Observation
from qnav.tracking import LookaheadAgent

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


class _GoToTargetValues:
    """Go-to-target as a Q agent: its action valued 1, the others 0 (a policy to shield)."""

    def __init__(self, worlds: int) -> None:
        self.last_q = np.zeros((worlds, NUM_ACTIONS), dtype=np.float32)

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        pass

    def act(self, observation: Observation) -> NDArray[np.int64]:
        action = go_to_target(observation.target_features())
        self.last_q = np.eye(NUM_ACTIONS, dtype=np.float32)[action]
        return action


def test_the_shield_turns_the_blind_controller_into_one_that_dodges() -> None:
    episodes = 32
    settings = EvalSettings(episodes=episodes, num_worlds=episodes, seed=77, max_episode_steps=100)
    blind = evaluate(INERTIA, GoToTargetAgent(), settings)
    shield = LookaheadAgent(
        _GoToTargetValues(episodes),
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


def test_the_shield_keeps_the_policys_chosen_action_not_only_its_highest_valued() -> None:
    q = np.array([[3.0, 2.0, 1.0]])
    shares = np.array([[0.0, 0.0, 0.0]])
    assert shielded_actions(q, shares, 0.3, np.array([2])).tolist() == [2]
    risky = np.array([[0.0, 0.0, 0.9]])
    assert shielded_actions(q, risky, 0.3, np.array([2])).tolist() == [0]
