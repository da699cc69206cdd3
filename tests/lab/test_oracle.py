"""The oracle planner: knowing the future, it reaches targets that a blind walk would not."""

import numpy as np
import pytest

from qnav.lab.oracle import (
    PERCEPTION_LEVELS,
    StateError,
    held_sequences,
    plan,
    run_oracle,
    with_error,
)
from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings
from qnav.sim.world import reset, take_rows


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
    alone = [plan(config, take_rows(state, np.array([i])), sequences)[0] for i in range(6)]
    np.testing.assert_array_equal(together, alone)


def test_a_planner_with_no_state_error_plans_as_the_oracle_and_a_large_error_costs() -> None:
    config = scenario("obstacles-increment")
    settings = EvalSettings(episodes=12, num_worlds=12)
    fast = {"horizon": 10, "random_sequences": 16}
    exact = run_oracle(config, settings, **fast)  # type: ignore[arg-type]
    zero = run_oracle(config, settings, state_error=PERCEPTION_LEVELS["exact"], **fast)  # type: ignore[arg-type]
    assert (zero.success, zero.collision, zero.mean_steps) == (
        exact.success,
        exact.collision,
        exact.mean_steps,
    )
    state = reset(config, np.zeros(3, dtype=np.int64), np.arange(3))
    blurred = with_error(state, StateError(1.0, 1.0, 0.0, 0.0), np.random.default_rng(0))
    assert not np.allclose(blurred.obstacle_xy, state.obstacle_xy)
    np.testing.assert_array_equal(blurred.pose, state.pose)


def test_qnav_eval_offers_every_perception_level_and_refuses_others() -> None:
    from qnav.cli import build_parser

    parser = build_parser()
    for level in PERCEPTION_LEVELS:
        assert parser.parse_args(["eval", "--state-error", level]).state_error == level
    with pytest.raises(SystemExit):
        parser.parse_args(["eval", "--state-error", "psychic"])
