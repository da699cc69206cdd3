"""Imitation before reinforcement (DAgger): labelled rounds kept, validated, resumed."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from qnav.contracts.errors import ConfigError
from qnav.sim.config import scenario
from qnav.training.config import DAGGER, ImitationSettings
from qnav.training.episode_log import read_rounds
from qnav.training.imitation import Imitation, MixedDriver
from qnav.training.run import train
from qnav.training.run_folder import Progress

TINY_DAGGER = replace(
    DAGGER,
    # Two rounds of 4 worlds, 40 steps; a small network; tests on 2 BARN and 2 held-out worlds.
    imitation=ImitationSettings(rounds=2, episodes_per_round=4, iterations_per_round=3),
    max_episode_steps=40, hidden_size=8, batch_size=8, threads=1,
    eval_episodes=2, final_eval_episodes=2,
)  # fmt: skip


def _world() -> object:
    base = scenario("clutter")
    return replace(base, layout=replace(base.layout, worlds=16))


def test_a_dagger_run_keeps_its_labelled_rounds_and_tests_on_barn(tmp_path: Path) -> None:
    world = _world()
    results = train(world, TINY_DAGGER, tmp_path, progress=False)  # type: ignore[arg-type]
    rounds = read_rounds(tmp_path / "imitation")
    assert [len(r) for r in rounds] == [4, 4]
    # The first round is all the planner's driving: its labels are the actions taken.
    first = rounds[0][0]
    assert first.action.size > 0
    progress = (tmp_path / "progress.csv").read_text().splitlines()
    assert len(progress) == 3 and progress[1].endswith(",imitation")
    assert results["barn"]["worlds"] == "BARN"
    assert results["test"]["episodes"] == 2
    assert results["held_out"]["worlds"] == "cave/test"
    # Run again: the finished run is read back, nothing is collected anew.
    again = train(world, TINY_DAGGER, tmp_path, progress=False)  # type: ignore[arg-type]
    assert again == results


def test_a_crashed_dagger_run_resumes_after_its_last_round(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    world = _world()
    finished_round = Imitation.round

    def crash_in_round_two(self: Imitation, index: int, state: Progress) -> object:
        if index == 1:
            raise KeyboardInterrupt
        return finished_round(self, index, state)

    monkeypatch.setattr(Imitation, "round", crash_in_round_two)
    with pytest.raises(KeyboardInterrupt):
        train(world, TINY_DAGGER, tmp_path, progress=False)  # type: ignore[arg-type]
    first_round = read_rounds(tmp_path / "imitation")
    assert len(first_round) == 1 and not (tmp_path / "results.json").exists()
    monkeypatch.setattr(Imitation, "round", finished_round)
    resumed = train(world, TINY_DAGGER, tmp_path, progress=False)  # type: ignore[arg-type]
    rounds = read_rounds(tmp_path / "imitation")
    assert len(rounds) == 2
    np.testing.assert_array_equal(rounds[0][0].pose, first_round[0][0].pose)
    assert len((tmp_path / "progress.csv").read_text().splitlines()) == 3
    assert resumed["test"]["episodes"] == 2


def test_imitation_needs_a_world_of_layouts(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="layout"):
        train(scenario("walls-inertia"), TINY_DAGGER, tmp_path, progress=False)


def test_the_expert_drives_its_share_of_the_steps() -> None:
    class Fixed:
        def __init__(self, action: int) -> None:
            self.action = action

        def start(self, worlds: object, episodes: object) -> None: ...

        def act(self, observation: object) -> np.ndarray:
            return np.full(1000, self.action)

    driver = MixedDriver(Fixed(0), Fixed(1), share=0.25, seed=0)  # type: ignore[arg-type]
    taken = driver.act(None)  # type: ignore[arg-type]
    assert abs(taken.mean() - 0.25) < 0.05
