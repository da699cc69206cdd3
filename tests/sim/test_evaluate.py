import pytest

from sim.config import scenario
from sim.evaluate import EvalSettings, RandomAgent, evaluate


def test_results_do_not_depend_on_the_batch_size() -> None:
    config = scenario("obstacles-increment")
    results = [
        evaluate(config, RandomAgent(worlds, seed=1), EvalSettings(episodes=60, num_worlds=worlds))
        for worlds in (1, 7, 60)
    ]
    assert results[0] == results[1] == results[2]


def test_fractions_cover_every_episode() -> None:
    result = evaluate(
        scenario("walls-inertia"), RandomAgent(16), EvalSettings(episodes=50, num_worlds=16)
    )
    assert result.episodes == 50
    assert result.success + result.collision + result.unfinished == pytest.approx(1.0)


@pytest.mark.parametrize("name", ["walls-inertia", "walls-increment"])
def test_turning_to_the_target_and_driving_always_succeeds_without_obstacles(name: str) -> None:
    from sim.evaluate import GoToTargetAgent

    result = evaluate(scenario(name), GoToTargetAgent(), EvalSettings(episodes=100))
    assert result.success == 1.0
