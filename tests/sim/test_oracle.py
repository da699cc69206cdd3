"""The oracle planner: knowing the future, it reaches targets that a blind walk would not."""

import numpy as np

from sim.config import scenario
from sim.evaluate import EvalSettings
from sim.oracle import held_sequences, plan, run_oracle
from sim.world import WorldState, reset


def test_the_oracle_reaches_every_target_in_a_walls_only_world() -> None:
    result = run_oracle(
        scenario("walls-increment"), EvalSettings(episodes=6), horizon=12, random_sequences=16
    )
    assert result.success == 1.0


def test_planning_worlds_together_picks_what_planning_each_alone_picks() -> None:
    config = scenario("obstacles-increment")
    state = reset(config, np.zeros(6, dtype=np.int64), np.arange(6))
    sequences = held_sequences(10, 32, np.random.default_rng(0))
    together = plan(config, state, sequences)
    alone = [
        plan(config, WorldState._make(field[i : i + 1] for field in state), sequences)[0]
        for i in range(6)
    ]
    np.testing.assert_array_equal(together, alone)
