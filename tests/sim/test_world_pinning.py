"""The world against every number the paper gives (issue 19 part 1): the random agent on the
paper's Random rows within two of its standard errors, and the oracle planner at least at the
paper's best recurrent seed in both obstacle tables, so the paper's results are possible here."""

import pytest

from qnav.contracts.motion import IncrementDynamics, InertiaDynamics
from qnav.lab.calibrate import calibrate
from qnav.sim import paper
from qnav.sim.config import scenario


@pytest.mark.slow
@pytest.mark.parametrize("name", list(paper.RANDOM))
def test_the_world_is_pinned_by_the_papers_numbers(name: str) -> None:
    oracle_episodes = 1000 if scenario(name).obstacles.count else 0
    [row] = calibrate(
        {name: scenario(name)}, episodes=1000, oracle_episodes=oracle_episodes, seed=12345
    )
    assert row.random_within_two_errors(), row.random
    assert row.oracle_reaches_best_seed() in (None, True), row.oracle


def test_the_increment_robot_is_slower_than_the_inertia_robots_top_speed() -> None:
    increment, inertia = scenario("obstacles-increment"), scenario("obstacles-inertia")
    assert isinstance(increment.dynamics, IncrementDynamics)
    assert isinstance(inertia.dynamics, InertiaDynamics)
    speed_mps = increment.dynamics.forward_step_m / increment.control_period_s
    assert speed_mps < inertia.dynamics.max_speed_mps
