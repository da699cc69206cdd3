"""The random agent under the paper's test protocol lands on the paper's Random rows."""

import math

import pytest

from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings, RandomAgent, evaluate
from qnav.sim.paper import RANDOM

EPISODES = 1000
TOLERANCE = 0.05
"""About 3 standard errors of a rate near 0.5 over `EPISODES` episodes."""
SLICE_EPISODES = 250
"""The default suite's seeded slice: one episode per world, about a quarter of the time."""


def _check(name: str, episodes: int, tolerance: float) -> None:
    settings = EvalSettings(episodes=episodes, num_worlds=250, seed=2024)
    result = evaluate(scenario(name), RandomAgent(250, seed=7), settings)
    success, collision, unfinished = RANDOM[name]
    assert abs(result.success - success) <= tolerance, result
    assert abs(result.collision - collision) <= tolerance, result
    assert abs(result.unfinished - unfinished) <= tolerance, result


@pytest.mark.slow
@pytest.mark.parametrize("name", list(RANDOM))
def test_random_agent_matches_the_papers_random_row(name: str) -> None:
    _check(name, EPISODES, TOLERANCE)


@pytest.mark.parametrize("name", list(RANDOM))
def test_random_agent_on_a_seeded_slice_matches_the_papers_random_row(name: str) -> None:
    # The same confidence on fewer episodes: the standard error grows as 1/sqrt(episodes).
    _check(name, SLICE_EPISODES, TOLERANCE * math.sqrt(EPISODES / SLICE_EPISODES))
