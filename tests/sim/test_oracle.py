"""The oracle planner: knowing the future, it reaches targets that a blind walk would not."""

from sim.config import scenario
from sim.evaluate import EvalSettings
from sim.oracle import run_oracle


def test_the_oracle_reaches_every_target_in_a_walls_only_world() -> None:
    result = run_oracle(
        scenario("walls-increment"), EvalSettings(episodes=6), horizon=12, random_sequences=16
    )
    assert result.success == 1.0
