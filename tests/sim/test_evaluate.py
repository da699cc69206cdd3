from dataclasses import replace

import numpy as np
import pytest

from qnav.contracts.actions import Action
from qnav.contracts.motion import Outcome
from qnav.sim.config import scenario
from qnav.sim.evaluate import (
    EvalResult,
    EvalSettings,
    GoToTargetAgent,
    RandomAgent,
    drive,
    evaluate,
    go_to_target,
)
from qnav.sim.world import WorldState


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
    from qnav.sim.evaluate import GoToTargetAgent

    result = evaluate(scenario(name), GoToTargetAgent(), EvalSettings(episodes=100))
    assert result.success == 1.0


def test_go_to_target_drives_when_facing_and_turns_towards_the_target_otherwise() -> None:
    features = np.array([[1.0, 0.0, 1.0], [1.0, 0.5, 0.8], [1.0, -0.5, 0.8], [1.0, 0.0, -1.0]])
    chosen = go_to_target(features, aligned_cos=0.97)
    assert chosen.tolist() == [Action.FORWARD, Action.LEFT, Action.RIGHT, Action.RIGHT]


def test_drive_gives_the_test_protocols_outcomes() -> None:
    config = scenario("obstacles-increment")
    protocol = EvalSettings(episodes=40, max_episode_steps=500)
    expected = evaluate(config, GoToTargetAgent(), protocol)
    world = replace(config, max_episode_steps=500)
    agent = GoToTargetAgent()
    outcomes, steps = drive(world, protocol.seed, np.arange(40), lambda _, obs: agent.act(obs))
    assert np.mean(outcomes == Outcome.SUCCESS) == expected.success
    assert np.mean(outcomes == Outcome.COLLISION) == expected.collision
    assert EvalResult.of_outcomes(outcomes, steps) == expected  # steps too


def test_drive_records_only_the_running_worlds() -> None:
    config = scenario("walls-increment")
    agent = GoToTargetAgent()
    seen: list[int] = []

    def record(state: WorldState, _: object, action: np.ndarray) -> None:
        assert state.pose.shape[0] == action.size
        seen.append(action.size)

    drive(config, 7, np.arange(6), lambda _, obs: agent.act(obs), record)
    assert seen[0] == 6 and seen[-1] >= 1 and seen == sorted(seen, reverse=True)
