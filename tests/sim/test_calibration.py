"""The random agent under the paper's test protocol lands on the paper's Random rows."""

import pytest

from sim.config import scenario
from sim.evaluate import EvalSettings, RandomAgent, evaluate
from sim.paper import RANDOM

EPISODES = 1000
TOLERANCE = 0.05


@pytest.mark.parametrize("name", list(RANDOM))
def test_random_agent_matches_the_papers_random_row(name: str) -> None:
    settings = EvalSettings(episodes=EPISODES, num_worlds=250, seed=2024)
    result = evaluate(scenario(name), RandomAgent(250, seed=7), settings)
    success, collision, unfinished = RANDOM[name]
    assert abs(result.success - success) <= TOLERANCE, result
    assert abs(result.collision - collision) <= TOLERANCE, result
    assert abs(result.unfinished - unfinished) <= TOLERANCE, result
