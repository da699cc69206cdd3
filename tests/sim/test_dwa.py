"""The DWA baseline: admissible rollouts only, turns held against oscillation."""

from dataclasses import replace

import numpy as np

from qnav.contracts.actions import Action
from qnav.contracts.motion import Outcome
from qnav.sim.config import scenario
from qnav.sim.dwa import DwaAgent, rollout_sequences
from qnav.sim.evaluate import EvalSettings, episode_outcomes
from qnav.sim.world import Observation


def _observation(scan: np.ndarray, target: tuple[float, float]) -> Observation:
    pose = np.array([[0.0, 0.0, 0.0]])
    empty = np.zeros((1, 0, 2))
    return Observation(
        pose, np.array([target]), scan[None].astype(np.float32), np.ones(1), empty, empty
    )


def test_the_candidates_hold_each_action_or_turn_then_drive() -> None:
    sequences = rollout_sequences(4)
    assert sequences.shape == (3 + 2 * 3, 4)
    assert [Action.LEFT, Action.FORWARD, Action.FORWARD, Action.FORWARD] in sequences.tolist()


def test_it_never_drives_into_a_wall_that_stands_before_the_goal() -> None:
    config = scenario("barn")
    agent = DwaAgent(config, 1)
    scan = np.full(720, np.inf)
    scan[np.r_[0:60, 660:720]] = 0.6  # a wall 0.6 m ahead, the goal behind it
    action = agent.act(_observation(scan, (5.0, 0.0)))
    assert action[0] != Action.FORWARD
    # Held: the opposite turn is ruled out until the robot has moved.
    again = agent.act(_observation(scan, (5.0, 0.0)))
    assert again[0] == action[0]


def test_it_drives_straight_to_a_goal_in_the_open() -> None:
    agent = DwaAgent(scenario("barn"), 1)
    action = agent.act(_observation(np.full(720, np.inf), (5.0, 0.0)))
    assert action[0] == Action.FORWARD


def test_it_crosses_some_generated_worlds_without_colliding() -> None:
    base = scenario("clutter")
    config = replace(base, layout=replace(base.layout, split="validation", worlds=6, order="cycle"))
    outcomes, _ = episode_outcomes(
        config, DwaAgent(config, 6), EvalSettings(episodes=6, num_worlds=6)
    )
    assert (outcomes == Outcome.COLLISION).sum() == 0
