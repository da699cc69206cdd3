import numpy as np
import pytest

from qnav.contracts.motion import Outcome, outcome
from qnav.sim.config import RewardConfig
from qnav.sim.task import reward

L = 0.5


def test_reaching_the_target_wins_over_touching_a_wall() -> None:
    result = outcome(np.array([0.1]), np.array([0.1]), L)
    assert result[0] == Outcome.SUCCESS


def test_outcomes_follow_the_robot_radius() -> None:
    result = outcome(np.array([0.49, 2.0, 2.0]), np.array([3.0, 0.49, 0.51]), L)
    assert list(result) == [Outcome.SUCCESS, Outcome.COLLISION, Outcome.RUNNING]


def test_reward_is_the_papers_formula_between_terminal_states() -> None:
    params = RewardConfig()
    distance, gap = np.array([4.0, 12.0]), np.array([0.7, 3.0])
    expected = [0.01 * (0.7 - 1.0) - 0.002 * 4.0, -0.002 * 10.0]
    np.testing.assert_allclose(reward(distance, gap, L, params), expected)


@pytest.mark.parametrize(("distance", "gap", "value"), [(0.2, 5.0, 1.0), (3.0, 0.2, -1.0)])
def test_terminal_rewards(distance: float, gap: float, value: float) -> None:
    assert reward(np.array([distance]), np.array([gap]), L, RewardConfig())[0] == value
